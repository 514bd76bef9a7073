"""The panorama record: an image plus how each column maps to azimuth and each row to elevation.

Two projections:

- ``cylindrical`` (what ``viper stitch`` writes): column ``c`` looks at azimuth
  ``azimuth0_deg + degrees(c / px_per_rad)``; row ``r`` at elevation
  ``atan((horizon_row - r) / px_per_rad)``; ``px_per_rad`` is the cylinder's focal length in pixels.
- ``equirectangular`` (a 360-degree photo): the same columns, and rows linear in elevation,
  ``degrees((horizon_row - r) / px_per_rad)``.

``azimuth0_deg`` is the azimuth (clockwise from true north) of the centre of column 0, and
``horizon_row`` the (fractional) row of elevation 0.  A panorama whose width covers 360 degrees is
``full_circle``; otherwise it is partial and columns beyond its ends see nothing.

On disk a panorama is an image file (PNG or JPEG) with a sidecar JSON ``<image>.json`` holding the
geometry.  An image without its sidecar is read as an equirectangular 360-degree photo.
"""

from __future__ import annotations

import enum
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from appliance.atomic import atomic_output
from appliance.errors import InputError
from appliance.inputs import read_image_buffer, read_json_bounded
from appliance.native import native_messages

SIDECAR_SUFFIX = ".json"
#: A panorama narrower than this (deg) holds too little skyline to locate anything.
MIN_SPAN_DEG = 1.0
log = logging.getLogger(__name__)


class Projection(enum.Enum):
    CYLINDRICAL = "cylindrical"
    EQUIRECTANGULAR = "equirectangular"


@dataclass(frozen=True)
class Panorama:
    """An HxWx3 uint8 BGR image with its angular geometry (see the module docstring)."""

    image: np.ndarray
    projection: Projection
    px_per_rad: float
    azimuth0_deg: float
    horizon_row: float
    full_circle: bool
    #: Columns that no photo covers (one flag per column), where a panorama is stitched from too
    #: few frames; None when every column holds pixels.
    empty_columns: np.ndarray | None = None
    #: Per pixel, how far the overlapping frames it was stitched from appear shifted (px; NaN where
    #: fewer than two frames cover it; :mod:`appliance.vision.temporal`): a drifting cloud moves,
    #: terrain does not.  None for a panorama read from a file or made of one photo.
    motion: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[2] != 3 or self.image.dtype != np.uint8:
            raise InputError(f"panorama: expected an HxWx3 uint8 image, got {self.image.shape} {self.image.dtype}")
        if self.empty_columns is not None and self.empty_columns.shape != (self.width,):
            raise InputError(f"panorama: {self.empty_columns.shape} empty-column flags for {self.width} columns")
        if self.motion is not None and self.motion.shape != self.image.shape[:2]:
            raise InputError(f"panorama: a {self.motion.shape} motion map for a {self.image.shape[:2]} image")
        if not (self.px_per_rad > 0 and math.isfinite(self.px_per_rad)):
            raise InputError(f"panorama: px_per_rad must be positive, got {self.px_per_rad}")
        span = self.width / self.px_per_rad
        if span < math.radians(MIN_SPAN_DEG):
            raise InputError(
                f"panorama: {self.width} columns at {self.px_per_rad:.6g} px/rad span {math.degrees(span):.3g} degrees,"
                f" less than {MIN_SPAN_DEG:g}"
            )
        if span > 2 * math.pi * (1 + 1e-6):
            raise InputError(
                f"panorama: {self.width} columns at {self.px_per_rad:.3f} px/rad span more than 360 degrees"
            )

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def deg_per_column(self) -> float:
        return math.degrees(1.0 / self.px_per_rad)

    def column_azimuth_deg(self, col: np.ndarray | float) -> np.ndarray:
        """Azimuth (degrees in [0, 360)) seen by (fractional) column ``col``."""
        return np.mod(self.azimuth0_deg + np.degrees(np.asarray(col, dtype=np.float64) / self.px_per_rad), 360.0)

    def azimuth_to_column(self, azimuth_deg: np.ndarray | float) -> np.ndarray:
        """Fractional column of azimuth; for a partial panorama NaN outside its columns."""
        off = np.mod(np.asarray(azimuth_deg, dtype=np.float64) - self.azimuth0_deg, 360.0)
        col = np.radians(off) * self.px_per_rad
        if self.full_circle:
            return col
        # a partial panorama: azimuths just before column 0 map to small negative columns
        back = col - 2 * math.pi * self.px_per_rad
        col = np.where(np.abs(back) < np.abs(col - (self.width - 1)), back, col)
        return np.where((col >= -0.5) & (col <= self.width - 0.5), col, np.nan)

    def row_elevation_deg(self, row: np.ndarray | float) -> np.ndarray:
        """Elevation (degrees) seen by (fractional) row ``row``."""
        t = (self.horizon_row - np.asarray(row, dtype=np.float64)) / self.px_per_rad
        if self.projection is Projection.CYLINDRICAL:
            return np.degrees(np.arctan(t))
        return np.degrees(t)

    def elevation_to_row(self, elevation_deg: np.ndarray | float) -> np.ndarray:
        """Fractional row where elevation (degrees) is imaged."""
        el = np.radians(np.asarray(elevation_deg, dtype=np.float64))
        t = np.tan(el) if self.projection is Projection.CYLINDRICAL else el
        return self.horizon_row - t * self.px_per_rad

    def geometry(self) -> dict[str, object]:
        return {
            "projection": self.projection.value,
            "px_per_rad": float(self.px_per_rad),
            "azimuth0_deg": float(self.azimuth0_deg),
            "horizon_row": float(self.horizon_row),
            "full_circle": bool(self.full_circle),
            "width": self.width,
            "height": self.height,
        }


def equirectangular(image: np.ndarray, azimuth_offset_deg: float = 0.0) -> Panorama:
    """A 360x180-degree photo: the left edge is azimuth ``azimuth_offset_deg``, the middle row the horizon."""
    h, w = image.shape[:2]
    px_per_rad = w / (2 * math.pi)
    if abs(h / px_per_rad - math.pi) > 0.02 * math.pi:
        raise InputError(
            f"equirectangular panorama: a {w}x{h} image does not span 360x180 degrees"
            " (its width must be twice its height)"
        )
    return Panorama(
        image=image,
        projection=Projection.EQUIRECTANGULAR,
        px_per_rad=px_per_rad,
        azimuth0_deg=float(np.mod(azimuth_offset_deg + 0.5 * 360.0 / w, 360.0)),
        horizon_row=(h - 1) / 2.0,
        full_circle=True,
    )


def full_circle_width(px_per_rad: float) -> int:
    return int(round(2 * math.pi * px_per_rad))


def sidecar_path(image_path: str | Path) -> Path:
    p = Path(image_path)
    return p.with_name(p.name + SIDECAR_SUFFIX)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as HxWx3 uint8 BGR; an unreadable file raises :class:`InputError`."""
    p = Path(path)
    data = np.frombuffer(read_image_buffer(p), dtype=np.uint8)
    with native_messages() as said:
        img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        why = f": {said[0]}" if said else ""
        raise InputError(f"{p}: not a readable image ({data.size} bytes){why}")
    if said:
        more = f" (and {len(said) - 1} more)" if len(said) > 1 else ""
        log.warning("%s: the image is damaged, read what could be decoded: %s%s", p, said[0], more)
    return img


def load_panorama(
    path: str | Path, projection: Projection | None = None, azimuth_offset_deg: float | None = None
) -> Panorama:
    """Read a panorama and its geometry.

    With a sidecar (``<image>.json``) the geometry comes from it; ``azimuth_offset_deg`` then
    shifts its azimuths.  Without one the image must be equirectangular (``projection`` may say so
    explicitly; a cylindrical panorama needs its sidecar).
    """
    p = Path(path)
    img = read_image(p)
    side = sidecar_path(p)
    if side.is_file():
        pano = _from_sidecar(img, side)
        proj = pano.projection
        if projection is not None and projection is not proj:
            raise InputError(f"{p}: --projection {projection.value} contradicts its sidecar ({proj.value})")
        if azimuth_offset_deg:
            pano = Panorama(
                img,
                proj,
                pano.px_per_rad,
                float(np.mod(pano.azimuth0_deg + azimuth_offset_deg, 360.0)),
                pano.horizon_row,
                pano.full_circle,
            )
        return pano
    if projection is Projection.CYLINDRICAL:
        raise InputError(f"{p}: a cylindrical panorama needs its geometry sidecar {side.name}")
    return equirectangular(img, azimuth_offset_deg or 0.0)


def _from_sidecar(img: np.ndarray, side: Path) -> Panorama:
    """The panorama ``img`` with the geometry its sidecar gives; any malformed field is an InputError."""
    try:
        meta = read_json_bounded(side, "panorama sidecar")
    except OSError as exc:
        raise InputError(f"{side}: cannot read the panorama sidecar: {exc.strerror or exc}") from None
    try:
        if not isinstance(meta, dict):
            raise ValueError("not a JSON object")
        proj = Projection(meta["projection"])
        numbers = {}
        for key in ("px_per_rad", "azimuth0_deg", "horizon_row"):
            v = meta[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{key} must be a finite number, got {v!r}")
            numbers[key] = float(v)
        if not isinstance(meta["full_circle"], bool):
            raise ValueError(f"full_circle must be true or false, got {meta['full_circle']!r}")
        size = [meta.get(key, n) for key, n in (("width", img.shape[1]), ("height", img.shape[0]))]
        if any(isinstance(v, bool) or not isinstance(v, int) for v in size):
            raise ValueError(f"width and height must be whole numbers, got {size}")
    except (ValueError, KeyError, OverflowError) as exc:
        raise InputError(f"{side}: not a valid panorama sidecar: {exc}") from None
    if tuple(size) != (img.shape[1], img.shape[0]):
        raise InputError(f"{side}: geometry is for {size[0]}x{size[1]}, image is {img.shape[1]}x{img.shape[0]}")
    return Panorama(img, proj, numbers["px_per_rad"], numbers["azimuth0_deg"], numbers["horizon_row"],
                    meta["full_circle"])


def save_panorama(pano: Panorama, path: str | Path) -> Path:
    """Write the image (format from the suffix) and its geometry sidecar; returns the sidecar path."""
    p = Path(path)
    try:
        ok, buf = cv2.imencode(p.suffix or ".png", pano.image)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(f"{p}: cannot encode an image with suffix {p.suffix!r}")
    side = sidecar_path(p)
    with atomic_output(p) as tmp_image, atomic_output(side) as tmp_side:
        tmp_image.write_bytes(buf.tobytes())
        tmp_side.write_text(json.dumps(pano.geometry(), indent=2) + "\n", encoding="utf-8")
    return side
