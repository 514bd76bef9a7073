"""A single perspective photo: detect the skyline in its own pixels, then turn it into true azimuths.

The photo keeps its lens: the skyline is found in the distorted image (no resampling, so no
columns are lost at the edges), and every detected pixel goes through the full camera model
(undistortion, then the orientation; :mod:`appliance.vision.camera`) to a true azimuth and an
elevation.  The skyline record is then sampled on a regular azimuth grid over the whole field of
view; azimuths the photo does not see, or where no confident skyline was found, are missing.

Orientation comes from the command line or from a sidecar JSON beside the photo
(``photo.jpg.json`` or ``photo.json``) holding ``yaw_deg``, ``pitch_deg`` and ``roll_deg``
(and optionally ``camera``: the calibration TOML, relative to the sidecar).

Burnt-in text (timestamps, logos) is found by :func:`find_text_boxes` and, with any rectangle the
user masks, filled from its surroundings before detection; a column whose skyline would pass
through a masked rectangle is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from appliance.errors import ConfigError, InputError
from appliance.inputs import read_json_bounded
from appliance.skyline import Skyline
from appliance.vision.camera import CameraPose, directions_to_pixels, pixels_to_directions
from appliance.vision.intrinsics import CameraIntrinsics, load_intrinsics
from appliance.vision.panorama import read_image
from appliance.vision.skyline_detect import DetectionConfig, detect_rows

MIN_FOV_DEG = 20.0  # a narrower view cannot pin a position down
PHOTO_MIN_ELEVATION_DEG = -30.0  # the elevation window a photo's frame must reach into
PHOTO_MAX_ELEVATION_DEG = 45.0

Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 (pixels, inclusive start, exclusive end)


@dataclass(frozen=True)
class Photo:
    """A BGR uint8 image with the camera that took it."""

    image: np.ndarray
    intrinsics: CameraIntrinsics
    pose: CameraPose
    name: str = "photo"

    def __post_init__(self) -> None:
        h, w = self.image.shape[:2]
        k = self.intrinsics
        if (w, h) != (k.width, k.height):
            raise InputError(
                f"{self.name}: the image is {w}x{h} but the camera calibration is for {k.width}x{k.height} images"
            )


@dataclass(frozen=True)
class PhotoSkyline:
    """The skyline per photo column: fractional row, true azimuth, elevation (NaN = missing), confidence."""

    row: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    confidence: np.ndarray
    masked: tuple[Rect, ...]


# ----------------------------------------------------------------------------- orientation input


def parse_orientation(text: str) -> CameraPose:
    """``"YAW,PITCH,ROLL"`` in degrees, or a JSON file holding yaw_deg, pitch_deg, roll_deg."""
    if text.lower().endswith(".json"):
        pose, _ = read_orientation_file(Path(text))
        if pose is None:
            raise InputError(f"{text}: no yaw_deg in this JSON file")
        return pose
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--orientation {text!r}: expected YAW,PITCH,ROLL in degrees, e.g. 60.9,-7.2,-0.6")
    return _checked_pose(values[0], values[1], values[2], f"--orientation {text!r}")


def _checked_pose(yaw: float, pitch: float, roll: float, source: str) -> CameraPose:
    if not -90.0 < pitch < 90.0:
        raise InputError(f"{source}: pitch {pitch} deg must lie strictly between -90 and 90")
    if not -180.0 <= roll <= 180.0:
        raise InputError(f"{source}: roll {roll} deg must lie within -180..180")
    return CameraPose(yaw % 360.0, pitch, roll)


def photo_sidecars(photo_path: str | Path) -> list[Path]:
    p = Path(photo_path)
    return [p.with_name(p.name + ".json"), p.with_suffix(".json")]


def read_sidecar(photo_path: str | Path) -> tuple[CameraPose | None, Path | None]:
    """The orientation and camera file named by the photo's sidecar, if it has one with ``yaw_deg``."""
    for side in photo_sidecars(photo_path):
        if side.is_file():
            pose, camera = read_orientation_file(side)
            if pose is not None:
                return pose, camera
    return None, None


def read_orientation_file(side: Path) -> tuple[CameraPose | None, Path | None]:
    """The orientation (``yaw_deg``, ``pitch_deg``, ``roll_deg``) and ``camera`` of a JSON file;
    (None, None) for a JSON object without ``yaw_deg`` (a panorama's geometry sidecar)."""
    if not side.exists():
        raise InputError(f"{side}: orientation file not found")
    try:
        data = read_json_bounded(side, "JSON sidecar")
    except OSError as exc:
        raise InputError(f"{side}: not a readable JSON sidecar: {exc}") from None
    if not isinstance(data, dict) or "yaw_deg" not in data:
        return None, None
    try:
        pose = _checked_pose(
            float(data["yaw_deg"]), float(data.get("pitch_deg", 0.0)), float(data.get("roll_deg", 0.0)), str(side)
        )
    except (TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{side}: yaw_deg, pitch_deg and roll_deg must be numbers") from None
    camera = data.get("camera")
    return pose, (side.parent / str(camera)) if camera else None


def load_photo(
    path: str | Path,
    camera: str | Path | None = None,
    orientation: CameraPose | None = None,
    image: np.ndarray | None = None,
) -> Photo:
    """The photo with its camera: command-line values first, then the sidecar's."""
    side_pose, side_camera = read_sidecar(path)
    pose = orientation or side_pose
    cam = camera or side_camera
    name = Path(path).name
    if cam is None:
        raise InputError(f"{name}: no camera calibration: give --camera camera.toml (from 'viper calibrate camera')")
    if pose is None:
        raise InputError(
            f"{name}: no orientation: give --orientation YAW,PITCH,ROLL or a sidecar {name}.json with yaw_deg,"
            " pitch_deg, roll_deg"
        )
    if image is None:
        image = read_image(path)
    try:
        intrinsics = load_intrinsics(cam)
    except ConfigError as exc:
        raise InputError(str(exc)) from None
    return Photo(image, intrinsics, pose, name)


# ----------------------------------------------------------------------------- geometry checks


def check_geometry(photo: Photo, min_fov_deg: float = MIN_FOV_DEG) -> tuple[float, float]:
    """The photo's azimuth span and elevation span (degrees) along its middle row and column.

    Refuses a view narrower than ``min_fov_deg`` and an orientation whose frame lies wholly outside
    the elevations where a skyline can be (the horizon far above or below the frame).
    """
    k = photo.intrinsics
    uc, vc = (k.width - 1) / 2.0, (k.height - 1) / 2.0
    az, _ = pixels_to_directions(k, photo.pose, np.array([0.0, k.width - 1.0]), np.array([vc, vc]))
    fov = float((az[1] - az[0]) % 360.0)
    if fov < min_fov_deg:
        raise InputError(
            f"{photo.name}: the field of view is {fov:.1f} deg wide, narrower than the {min_fov_deg:g} deg"
            " needed to locate anything"
        )
    _, el = pixels_to_directions(k, photo.pose, np.array([uc, uc]), np.array([0.0, k.height - 1.0]))
    top, bottom = float(el[0]), float(el[1])
    if bottom > PHOTO_MAX_ELEVATION_DEG or top < PHOTO_MIN_ELEVATION_DEG:
        raise InputError(
            f"{photo.name}: with pitch {photo.pose.pitch_deg:g} deg the frame spans elevations"
            f" {bottom:.1f}..{top:.1f} deg: the horizon is outside the frame (is the orientation right?)"
        )
    return fov, top - bottom


# ----------------------------------------------------------------------------- masks


def parse_rect(text: str) -> Rect:
    """``"x0,y0,x1,y1"`` in pixels (x0 < x1, y0 < y1)."""
    try:
        x0, y0, x1, y1 = (int(round(float(v))) for v in text.split(","))
    except ValueError:
        raise InputError(f"--mask {text!r}: expected a pixel rectangle x0,y0,x1,y1") from None
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"--mask {text!r}: expected x0 < x1 and y0 < y1")
    return x0, y0, x1, y1


def find_text_boxes(image: np.ndarray, band_fraction: float = 0.15) -> list[Rect]:
    """Rectangles around lines of burnt-in text (timestamps, captions) near the top or bottom edge.

    Text is a row of small glyphs, each of strong contrast against a locally uniform background
    (dark on light or light on dark), of similar height and on one baseline.  Glyph candidates are
    the connected blobs of strong black-hat or top-hat response; a text line is at least four of
    them, of similar height, aligned and closely spaced.  Terrain texture (rocks on snow) fails on
    alignment and spacing; only the bands along the top and bottom edges are searched.
    """
    h, w = image.shape[:2]
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    band = max(16, int(h * band_fraction))
    boxes: list[Rect] = []
    for y0 in (0, h - band):
        strip = grey[y0 : y0 + band]
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (25, 25))
        for op in (cv2.MORPH_BLACKHAT, cv2.MORPH_TOPHAT):
            resp = cv2.morphologyEx(strip, op, kernel)
            binary = (resp > 70).astype(np.uint8)
            n, _, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
            glyphs = [
                tuple(int(v) for v in stats[i, :4])
                for i in range(1, n)
                if 6 <= stats[i, 3] <= 80 and 2 <= stats[i, 2] <= 80 and stats[i, 4] >= 10
            ]
            boxes.extend((x, y + y0, x + gw, y + y0 + gh) for x, y, gw, gh in _text_lines(glyphs))
    return boxes


def _text_lines(glyphs: list[tuple[int, ...]]) -> list[tuple[int, int, int, int]]:
    """Chains of at least four glyphs (x, y, w, h) of similar height, aligned, closely spaced."""
    glyphs = sorted(glyphs)
    used = [False] * len(glyphs)
    lines: list[tuple[int, int, int, int]] = []
    for i, g in enumerate(glyphs):
        if used[i]:
            continue
        chain = [i]
        last = g
        for j in range(i + 1, len(glyphs)):
            x, y, gw, gh = glyphs[j]
            lx, ly, lw, lh = last
            if used[j] or x - (lx + lw) > 1.5 * max(lh, gh):
                continue
            similar = 0.6 <= gh / lh <= 1.6 or min(gh, lh) < 0.6 * max(gh, lh) and abs(y - ly) < 0.5 * lh
            aligned = abs((y + gh) - (ly + lh)) <= 0.35 * max(lh, gh) or abs(y - ly) <= 0.35 * max(lh, gh)
            if similar and aligned and x >= lx:
                chain.append(j)
                last = glyphs[j]
        if len(chain) >= 4:
            for j in chain:
                used[j] = True
            xs = [glyphs[j][0] for j in chain]
            ys = [glyphs[j][1] for j in chain]
            xe = [glyphs[j][0] + glyphs[j][2] for j in chain]
            ye = [glyphs[j][1] + glyphs[j][3] for j in chain]
            lines.append((min(xs), min(ys), max(xe) - min(xs), max(ye) - min(ys)))
    return lines


def _fill_rects(image: np.ndarray, rects: list[Rect], margin_px: int = 4) -> np.ndarray:
    """The image with the rectangles (grown by ``margin_px``) filled from their surroundings."""
    h, w = image.shape[:2]
    mask = np.zeros((h, w), dtype=np.uint8)
    for x0, y0, x1, y1 in rects:
        mask[max(0, y0 - margin_px) : min(h, y1 + margin_px), max(0, x0 - margin_px) : min(w, x1 + margin_px)] = 255
    if not mask.any():
        return image
    return np.asarray(cv2.inpaint(image, mask, 5, cv2.INPAINT_TELEA))


# ----------------------------------------------------------------------------- detection


def detect_photo(
    photo: Photo, cfg: DetectionConfig | None = None, masks: list[Rect] | None = None, find_text: bool = True
) -> PhotoSkyline:
    """The skyline in every column of the photo, with its true azimuth and elevation."""
    cfg = cfg or DetectionConfig()
    check_geometry(photo)
    k = photo.intrinsics
    rects = list(masks or [])
    if find_text:
        rects += find_text_boxes(photo.image)
    image = _fill_rects(photo.image, rects)
    rows, conf = detect_rows(np.ascontiguousarray(image), cfg)
    cols = np.arange(k.width, dtype=np.float64)
    rows = np.where(_through_rects(rows, rects, k.width), np.nan, rows)
    ok = np.isfinite(rows)
    az, el = pixels_to_directions(k, photo.pose, cols, np.where(ok, rows, k.height / 2.0))
    el = np.where(ok, el, np.nan)
    # outside the elevation window the line is not a skyline
    inside = (el >= cfg.min_elevation_deg) & (el <= cfg.max_elevation_deg)
    el = np.where(ok & inside, el, np.nan)
    rows = np.where(np.isfinite(el), rows, np.nan)
    return PhotoSkyline(rows, az, el, np.where(np.isfinite(el), conf, 0.0), tuple(rects))


def _through_rects(rows: np.ndarray, rects: list[Rect], width: int) -> np.ndarray:
    out = np.zeros(width, dtype=bool)
    cols = np.arange(width)
    for x0, y0, x1, y1 in rects:
        out |= (cols >= x0) & (cols < x1) & (rows >= y0 - 2) & (rows < y1 + 2)
    return out


def resample_photo(sky: PhotoSkyline, step_deg: float) -> Skyline:
    """The skyline at azimuths ``0, step, 2 step...`` (whole circle): linear between neighbouring valid
    columns, missing outside the photo's view and across gaps in the detection."""
    n = int(round(360.0 / step_deg))
    out_az = np.arange(n) * step_deg
    out_el = np.full(n, np.nan)
    az = np.asarray(sky.azimuth_deg, dtype=np.float64)
    # unwrap the columns' azimuths from the first column so that the view may straddle north
    rel = np.mod(az - az[0] + 180.0, 360.0) - 180.0
    rel = np.maximum.accumulate(rel)
    el = sky.elevation_deg
    pair = np.isfinite(el[:-1]) & np.isfinite(el[1:]) & (rel[1:] > rel[:-1])
    q = np.mod(out_az - az[0] + 180.0, 360.0) - 180.0
    idx = np.searchsorted(rel, q, side="right") - 1
    inside = (idx >= 0) & (idx < rel.size - 1)
    i = np.clip(idx, 0, rel.size - 2)
    usable = inside & pair[i]
    span = np.where(usable, rel[i + 1] - rel[i], 1.0)
    t = np.where(usable, (q - rel[i]) / span, 0.0)
    out_el = np.where(usable, el[i] * (1 - t) + el[np.minimum(i + 1, el.size - 1)] * t, np.nan)
    c = sky.confidence
    out_conf = np.where(np.isfinite(out_el), np.clip(np.minimum(c[i], c[np.minimum(i + 1, c.size - 1)]), 0, 1), 0.0)
    return Skyline(out_az, out_el, out_conf)


def skyline_pixels(photo: Photo, skyline: Skyline) -> tuple[np.ndarray, np.ndarray]:
    """Where a skyline (true azimuth, elevation) falls in the photo: pixel columns and rows, NaN outside."""
    u, v = directions_to_pixels(photo.intrinsics, photo.pose, skyline.azimuth_deg, skyline.elevation_deg)
    k = photo.intrinsics
    inside = (u >= 0) & (u <= k.width - 1) & (v >= 0) & (v <= k.height - 1)
    return np.where(inside, u, np.nan), np.where(inside, v, np.nan)


def draw_photo_overlay(photo: Photo, sky: PhotoSkyline, thickness_px: int = 2) -> np.ndarray:
    """The photo with the detected skyline in red and the masked rectangles outlined in yellow."""
    out = photo.image.copy()
    h = out.shape[0]
    ok = np.isfinite(sky.row)
    cols = np.arange(out.shape[1])[ok]
    for k in range(-thickness_px + 1, thickness_px):
        r = np.clip(np.round(sky.row[ok]).astype(np.int64) + k, 0, h - 1)
        out[r, cols] = (0, 0, 255)
    for x0, y0, x1, y1 in sky.masked:
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), (0, 255, 255), 1)
    return out
