"""A photo's EXIF: its size as decoded, its lens, where it was taken, which way it looked and when.

With these a single photo can be located without a camera calibration file: the lens gives an
undistorted pinhole camera (:func:`intrinsics_from_exif`), the GPS block a position prior and
GPSImgDirection a heading (:func:`heading_true_deg`, magnetic ones turned to true by the World
Magnetic Model).

Sizes are those of the pixels :func:`appliance.vision.panorama.read_image` returns: OpenCV's decode
(``IMREAD_COLOR``) applies the EXIF Orientation tag, so a photo of orientation 5 to 8 (a quarter
turn, with or without a mirror) is decoded with its stored width and height swapped; an orientation
outside 1..8 is ignored by OpenCV and read here as 1.

The file is read through :func:`appliance.inputs.read_image_bytes` (a regular file, bytes and
pixels capped) and parsed by Pillow.  A file without EXIF gives a :class:`PhotoExif` of Nones.  A
damaged EXIF block is not an error: what Pillow could read is kept, the rest is absent, a warning
is logged and :attr:`PhotoExif.exif_problem` says what was wrong, so that the error for a missing
lens names the damage.  A tag of the wrong kind (text where a number belongs) is absent with a
warning; a rational with a zero denominator reads as NaN, which a lens check names and a position
or heading check drops with a warning.

Example::

    exif = read_exif("photo.jpg")
    camera, focal_sigma = intrinsics_from_exif(exif, "photo.jpg")
    azimuth_deg = heading_true_deg(exif)
"""

from __future__ import annotations

import datetime as dt
import functools
import io
import logging
import math
import numbers
import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import ExifTags, Image, TiffImagePlugin, UnidentifiedImageError
from pygeomag import GeoMag, decimal_year_from_date

from appliance.atomic import describe_os_error
from appliance.errors import InputError
from appliance.inputs import read_image_bytes
from appliance.vision.intrinsics import CameraIntrinsics

log = logging.getLogger(__name__)

#: The diagonal of the 36 x 24 mm frame on which a 35 mm equivalent focal length is defined.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: Horizontal fields of view (deg) a lens read from EXIF may give; outside them the value is wrong
#: or the lens is not a pinhole (a fisheye), and a calibration file is needed.
MIN_HFOV_DEG = 3.0
MAX_HFOV_DEG = 160.0
#: 1-sigma of a focal length from a 35 mm equivalent (a whole number of mm, rounded by the maker:
#: the larger of this and half a millimetre over the value) and from the focal-plane resolution.
SIGMA_35MM_FRACTION = 0.03
SIGMA_FOCAL_PLANE_FRACTION = 0.02
#: A 35 mm equivalent and a focal-plane focal length further apart than this are logged.
DISAGREEMENT_FRACTION = 0.10
CAMERA_HINT = "give --camera CAM.toml (from 'viper calibrate camera')"

# FocalPlaneResolutionUnit: millimetres per unit (2 inch, the default, and 3 cm are EXIF's; 4 mm and
# 5 micrometre are written by some makers)
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
# orientations that turn the stored image a quarter turn (OpenCV swaps its width and height)
_QUARTER_TURNS = frozenset({5, 6, 7, 8})
# the Pillow exceptions of a damaged EXIF block (Pillow 13 warns and skips instead; older ones raise)
_EXIF_ERRORS = (OSError, ValueError, SyntaxError, EOFError, IndexError, KeyError, TypeError, struct.error)

_T = ExifTags.Base
_G = ExifTags.GPS


@dataclass(frozen=True)
class PhotoExif:
    """What a photo's EXIF says, with sizes of the image as OpenCV decodes it (orientation applied)."""

    width_px: int
    height_px: int
    orientation: int  # EXIF Orientation 1..8 (1 when absent or out of range)
    focal_length_mm: float | None = None  # FocalLength (the lens's own)
    focal_35mm_mm: float | None = None  # FocalLengthIn35mmFilm (0: the maker's "unknown")
    focal_plane_px_per_mm: float | None = None  # FocalPlaneXResolution over FocalPlaneResolutionUnit
    heading_deg: float | None = None  # GPSImgDirection, clockwise from heading_reference's north
    heading_reference: str | None = None  # GPSImgDirectionRef: 'T' true or 'M' magnetic
    lat: float | None = None  # GPS block, signed degrees (S negative)
    lon: float | None = None  # (W negative)
    altitude_m: float | None = None  # GPSAltitude, above sea level (negative below)
    taken_utc: dt.datetime | None = None  # aware, UTC
    # added: what the above came from
    taken_utc_source: str | None = None  # which tags gave taken_utc (and whether its zone is known)
    recorded_width_px: int | None = None  # PixelXDimension: the stored image's width when the camera wrote it
    recorded_height_px: int | None = None  # PixelYDimension (both before orientation)
    camera: str | None = None  # Make and Model
    has_exif: bool = False  # the file holds an EXIF block (readable or not)
    exif_problem: str | None = None  # why some or all of the EXIF could not be read

    @property
    def stored_size_px(self) -> tuple[int, int]:
        """(width, height) of the image as stored, before the orientation is applied."""
        if self.orientation in _QUARTER_TURNS:
            return self.height_px, self.width_px
        return self.width_px, self.height_px


# --- reading ---------------------------------------------------------------------------------------


def read_exif(path: str | Path) -> PhotoExif:
    """The EXIF of the image file ``path`` (a bounded read: see :mod:`appliance.inputs`).

    A missing, unreadable, oversized or non-regular file, or one whose header no image reader
    knows, raises :class:`InputError` in one line; a file without EXIF gives Nones."""
    p = Path(path)
    try:
        data = read_image_bytes(p)
    except FileNotFoundError:
        raise InputError(f"{p}: image file not found") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read the image: {describe_os_error(exc)}") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the pixel cap was checked from the header already
            im = Image.open(io.BytesIO(data))
    except UnidentifiedImageError:
        raise InputError(f"{p}: not an image (no format known to Pillow, {len(data)} bytes)") from None
    except (OSError, ValueError, SyntaxError, EOFError, IndexError, TypeError) as exc:
        raise InputError(f"{p}: not a readable image ({len(data)} bytes): {_one_line(exc)}") from None
    with im:
        stored_w, stored_h = _stored_size(im)
        base, sub, gps, has_exif, problem = _read_tags(im)
    if problem:
        log.warning("%s: %s; what could not be read is left out", p, problem)
    tags = _Tags(p, sub, gps)

    orientation = 1
    raw_orientation = tags.integer(base, _T.Orientation, "Orientation")
    if raw_orientation is not None:
        if 1 <= raw_orientation <= 8:
            orientation = raw_orientation
        else:
            log.warning("%s: EXIF Orientation %d is not 1..8; read as 1 (upright), as OpenCV does", p, raw_orientation)
    w, h = (stored_h, stored_w) if orientation in _QUARTER_TURNS else (stored_w, stored_h)

    lat = tags.dms(_G.GPSLatitude, _G.GPSLatitudeRef, "NS", 90.0, "GPSLatitude")
    lon = tags.dms(_G.GPSLongitude, _G.GPSLongitudeRef, "EW", 180.0, "GPSLongitude")
    if lat is None or lon is None:
        lat = lon = None
    elif lat == 0.0 and lon == 0.0:
        log.warning("%s: EXIF GPS position 0, 0 is a receiver's placeholder, not a place: left out", p)
        lat = lon = None
    heading, reference = tags.heading()
    taken, source = tags.taken()
    return PhotoExif(
        width_px=w,
        height_px=h,
        orientation=orientation,
        focal_length_mm=tags.real(sub, _T.FocalLength, "FocalLength"),
        focal_35mm_mm=tags.real(sub, _T.FocalLengthIn35mmFilm, "FocalLengthIn35mmFilm"),
        focal_plane_px_per_mm=tags.focal_plane_px_per_mm(),
        heading_deg=heading,
        heading_reference=reference,
        lat=lat,
        lon=lon,
        altitude_m=tags.altitude_m(),
        taken_utc=taken,
        taken_utc_source=source,
        recorded_width_px=tags.integer(sub, _T.ExifImageWidth, "PixelXDimension"),
        recorded_height_px=tags.integer(sub, _T.ExifImageHeight, "PixelYDimension"),
        camera=" ".join(t for t in (tags.text(base, _T.Make), tags.text(base, _T.Model)) if t) or None,
        has_exif=has_exif,
        exif_problem=problem,
    )


def _read_tags(im: Image.Image) -> tuple[dict[int, Any], dict[int, Any], dict[int, Any], bool, str | None]:
    """The main, Exif and GPS directories of ``im``, whether it has an EXIF block, and what was
    wrong with the block (None when it read cleanly)."""
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        try:
            exif = im.getexif()  # a PNG's eXIf chunk after its pixels is found by decoding them
            base = dict(exif)
            sub = dict(exif.get_ifd(ExifTags.IFD.Exif))
            gps = dict(exif.get_ifd(ExifTags.IFD.GPSInfo))
            raw = im.info.get("exif")
            if _T.Orientation in base and not isinstance(im, TiffImagePlugin.TiffImageFile):
                # Pillow takes a missing Orientation from XMP; OpenCV applies only the EXIF block's
                block = Image.Exif()
                if isinstance(raw, bytes):
                    block.load(raw)
                if _T.Orientation not in block:
                    del base[_T.Orientation]
        except _EXIF_ERRORS as exc:
            return {}, {}, {}, True, f"its EXIF block cannot be read ({_one_line(exc)})"
    stored = isinstance(raw, bytes) and len(raw.removeprefix(b"Exif\x00\x00")) > 0
    if stored and not base:
        return {}, {}, {}, True, "its EXIF block is damaged (no readable directory)"
    problem = None
    if said:
        more = f" (and {len(said) - 1} more)" if len(said) > 1 else ""
        problem = f"its EXIF block is damaged ({_one_line(said[0].message)}{more})"
    return base, sub, gps, stored or bool(base), problem


def _stored_size(im: Image.Image) -> tuple[int, int]:
    """(width, height) of the pixels as stored.  Pillow reports a TIFF's size with its orientation
    applied (and turns its pixels when it loads them); the TIFF's own tags hold the stored size."""
    if isinstance(im, TiffImagePlugin.TiffImageFile):
        w, h = im.tag_v2.get(ExifTags.Base.ImageWidth), im.tag_v2.get(ExifTags.Base.ImageLength)
        if isinstance(w, int) and isinstance(h, int) and {w, h} == set(im.size):
            return w, h
    return int(im.size[0]), int(im.size[1])


def _one_line(what: object) -> str:
    return " ".join(str(what).split()) or type(what).__name__


class _Tags:
    """Typed values of the three directories; a value of the wrong kind or out of range is absent,
    with a warning naming the file and the tag."""

    def __init__(self, path: Path, sub: dict[int, Any], gps: dict[int, Any]) -> None:
        self.path, self.sub, self.gps = path, sub, gps

    def _drop(self, tag: str, value: object, why: str) -> None:
        log.warning("%s: EXIF %s %s %s: left out", self.path, tag, _one_line(repr(value))[:80], why)

    def real(self, ifd: dict[int, Any], key: int, tag: str) -> float | None:
        """A number (a rational with a zero denominator is NaN); None when absent or not a number."""
        if key not in ifd:
            return None
        value = ifd[key]
        if isinstance(value, tuple) and len(value) == 1:
            value = value[0]
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            return float(value)
        self._drop(tag, value, "is not a number")
        return None

    def integer(self, ifd: dict[int, Any], key: int, tag: str) -> int | None:
        value = self.real(ifd, key, tag)
        if value is None:
            return None
        if not math.isfinite(value) or value != int(value):
            self._drop(tag, value, "is not a whole number")
            return None
        return int(value)

    def text(self, ifd: dict[int, Any], key: int) -> str | None:
        value = ifd.get(key)
        if isinstance(value, bytes):
            value = value.decode("latin-1")
        if not isinstance(value, str):
            return None
        value = "".join(c for c in value if c.isprintable()).strip()
        return value or None

    def focal_plane_px_per_mm(self) -> float | None:
        resolution = self.real(self.sub, _T.FocalPlaneXResolution, "FocalPlaneXResolution")
        if resolution is None:
            return None
        unit = self.integer(self.sub, _T.FocalPlaneResolutionUnit, "FocalPlaneResolutionUnit")
        unit = 2 if unit is None else unit
        if unit not in _MM_PER_UNIT:
            self._drop("FocalPlaneResolutionUnit", unit, "is not a length unit (2 inch, 3 cm, 4 mm, 5 um)")
            return None
        return resolution / _MM_PER_UNIT[unit]

    def dms(self, key: int, ref_key: int, letters: str, limit: float, tag: str) -> float | None:
        """Signed degrees from degrees, minutes and seconds and a hemisphere letter."""
        if key not in self.gps:
            return None
        value = self.gps[key]
        parts = value if isinstance(value, tuple) else (value,)
        if not 1 <= len(parts) <= 3 or not all(isinstance(v, numbers.Real) for v in parts):
            self._drop(tag, value, "is not degrees, minutes and seconds")
            return None
        deg = sum(float(v) / 60.0**i for i, v in enumerate(parts))
        if not (math.isfinite(deg) and all(float(v) >= 0 for v in parts) and deg <= limit):
            self._drop(tag, value, f"is not 0..{limit:g} degrees")
            return None
        ref = (self.text(self.gps, ref_key) or "").upper()
        if len(ref) != 1 or ref not in letters:
            self._drop(tag, value, f"has no hemisphere ({tag}Ref {ref!r}, not {' or '.join(letters)})")
            return None
        return -deg if ref == letters[1] else deg

    def altitude_m(self) -> float | None:
        altitude = self.real(self.gps, _G.GPSAltitude, "GPSAltitude")
        if altitude is None:
            return None
        if not math.isfinite(altitude):
            self._drop("GPSAltitude", altitude, "is not a finite number")
            return None
        ref = self.gps.get(_G.GPSAltitudeRef, 0)
        below = ref[:1] == b"\x01" if isinstance(ref, bytes) else ref == 1
        return -abs(altitude) if below else altitude

    def heading(self) -> tuple[float | None, str | None]:
        heading = self.real(self.gps, _G.GPSImgDirection, "GPSImgDirection")
        if heading is not None and not (math.isfinite(heading) and 0.0 <= heading <= 360.0):
            self._drop("GPSImgDirection", heading, "is not 0..360 degrees")
            heading = None
        ref = self.text(self.gps, _G.GPSImgDirectionRef)
        if ref is not None and ref.upper() not in ("T", "M"):
            self._drop("GPSImgDirectionRef", ref, "is neither 'T' (true) nor 'M' (magnetic)")
            ref = None
        return (None if heading is None else heading % 360.0), (None if ref is None else ref.upper())

    def taken(self) -> tuple[dt.datetime | None, str | None]:
        """The time the photo was taken, in UTC, and the tags it came from: DateTimeOriginal with
        OffsetTimeOriginal; else the GPS date and time (UTC); else DateTimeOriginal alone, a local
        time of unknown zone, read as UTC."""
        local = self._datetime(self.text(self.sub, _T.DateTimeOriginal), "DateTimeOriginal")
        offset = self._offset(self.text(self.sub, _T.OffsetTimeOriginal))
        if local is not None and offset is not None:
            return local.replace(tzinfo=offset).astimezone(dt.timezone.utc), "DateTimeOriginal+OffsetTimeOriginal"
        gps = self._gps_time()
        if gps is not None:
            return gps, "GPSDateStamp+GPSTimeStamp"
        if local is not None:
            return local.replace(tzinfo=dt.timezone.utc), "DateTimeOriginal (local time of unknown zone, read as UTC)"
        return None, None

    def _datetime(self, text: str | None, tag: str, date_only: bool = False) -> dt.datetime | None:
        if text is None or not text.strip(" :0"):
            return None  # absent, or blanks and zeros: EXIF's "unknown"
        pattern = r"(\d{4})[:-](\d{2})[:-](\d{2})" + ("" if date_only else r"[ T](\d{2}):(\d{2}):(\d{2})")
        m = re.match(pattern, text)
        try:
            if m is None:
                raise ValueError
            g = [int(x) for x in m.groups()]
            day = dt.datetime(g[0], g[1], g[2])  # its zone is added by the caller
            return day if date_only else day.replace(hour=g[3], minute=g[4], second=g[5])
        except ValueError:
            self._drop(tag, text, "is not a date YYYY:MM:DD" if date_only else
                       "is not a date and time YYYY:MM:DD HH:MM:SS")
            return None

    def _offset(self, text: str | None) -> dt.timezone | None:
        m = re.fullmatch(r"([+-])(\d{2}):(\d{2})", text or "")
        if m is None:
            if text:
                self._drop("OffsetTimeOriginal", text, "is not an offset +HH:MM")
            return None
        minutes = int(m[2]) * 60 + int(m[3])
        if minutes >= 24 * 60:
            self._drop("OffsetTimeOriginal", text, "is a day or more")
            return None
        return dt.timezone(dt.timedelta(minutes=-minutes if m[1] == "-" else minutes))

    def _gps_time(self) -> dt.datetime | None:
        date_text = self.text(self.gps, _G.GPSDateStamp)
        stamp = self.gps.get(_G.GPSTimeStamp)
        if date_text is None or stamp is None:
            return None
        day = self._datetime(date_text, "GPSDateStamp", date_only=True)
        parts = stamp if isinstance(stamp, tuple) else (stamp,)
        if not (len(parts) == 3 and all(isinstance(v, numbers.Real) for v in parts)):
            self._drop("GPSTimeStamp", stamp, "is not hours, minutes and seconds")
            return None
        h, m, s = (float(v) for v in parts)
        if not (0 <= h < 24 and 0 <= m < 60 and 0 <= s < 61):  # NaN fails too
            self._drop("GPSTimeStamp", stamp, "is not a time of day")
            return None
        if day is None:
            return None
        return day.replace(tzinfo=dt.timezone.utc) + dt.timedelta(hours=h, minutes=m, seconds=s)


# --- the lens --------------------------------------------------------------------------------------


def intrinsics_from_exif(exif: PhotoExif, name: str) -> tuple[CameraIntrinsics, float]:
    """An undistorted pinhole camera for the photo's ``width_px`` x ``height_px`` pixels (square
    pixels, principal point at the centre) and the 1-sigma uncertainty of its focal length as a
    fraction.

    The focal length comes from FocalLengthIn35mmFilm when it is there and usable (the equivalent
    is defined on the 36 x 24 mm frame's diagonal: ``f_px = f35 * hypot(w, h) / 43.2666``;
    uncertainty ``max(0.03, 0.5 / f35)``), else from FocalLength times the focal-plane resolution
    (2 %), scaled by the image's width over PixelXDimension when the photo was resized whole after
    the camera wrote it.  No usable lens raises a one-line :class:`InputError` naming ``name``,
    the values at fault or what is missing, and the way out (``--camera``).

    Example: 24 mm equivalent on 4000 x 3000 pixels -> fx = 24 * 5000 / 43.2666 = 2773.5 px."""
    from_35mm = _from_35mm(exif)
    from_plane = _from_focal_plane(exif)
    if isinstance(from_35mm, tuple) and isinstance(from_plane, tuple):
        apart = abs(from_35mm[0] / from_plane[0] - 1.0)
        if apart > DISAGREEMENT_FRACTION:
            log.warning("%s: the 35 mm equivalent gives a focal length of %.1f px, FocalLength with the focal "
                        "plane %.1f px (%.0f %% apart): the 35 mm equivalent is used", name, from_35mm[0],
                        from_plane[0], 100 * apart)
    if isinstance(from_35mm, tuple):
        chosen, source, unused = from_35mm, "FocalLengthIn35mmFilm", from_plane
    elif isinstance(from_plane, tuple):
        chosen, source, unused = from_plane, "FocalLength and the focal plane", from_35mm
    else:
        raise InputError(_no_lens(exif, name, from_35mm, from_plane))
    if unused is not None and not isinstance(unused, tuple):
        log.warning("%s: %s; the focal length is taken from %s", name, unused, source)
    f_px, sigma = chosen
    w, h = exif.width_px, exif.height_px
    camera = CameraIntrinsics(w, h, f_px, f_px, (w - 1) / 2.0, (h - 1) / 2.0)
    log.debug("%s: lens from EXIF: %.1f px (%.2f deg across), 1-sigma %.1f %%", name, f_px, camera.hfov_deg,
             100 * sigma)
    return camera, sigma


def _from_35mm(exif: PhotoExif) -> tuple[float, float] | str | None:
    """(focal length px, 1-sigma fraction) from FocalLengthIn35mmFilm; what is wrong with it; or
    None when it is absent."""
    f35 = exif.focal_35mm_mm
    if f35 is None:
        return None
    if f35 == 0:
        return "FocalLengthIn35mmFilm is 0 (the maker's 'unknown')"
    if not (math.isfinite(f35) and f35 > 0):
        return f"FocalLengthIn35mmFilm {f35:g} mm is not a positive length"
    f_px = f35 * math.hypot(exif.width_px, exif.height_px) / FULL_FRAME_DIAGONAL_MM
    why = _field_of_view_problem(f_px, exif, f"FocalLengthIn35mmFilm {f35:g} mm")
    return why or (f_px, max(SIGMA_35MM_FRACTION, 0.5 / f35))


def _from_focal_plane(exif: PhotoExif) -> tuple[float, float] | str | None:
    """(focal length px, 1-sigma fraction) from FocalLength and the focal-plane resolution; what is
    wrong with them; or None when either is absent."""
    focal, pitch = exif.focal_length_mm, exif.focal_plane_px_per_mm
    if focal is not None and not (math.isfinite(focal) and focal > 0):
        return f"FocalLength {focal:g} mm is not a positive length"
    if pitch is not None and not (math.isfinite(pitch) and pitch > 0):
        return f"FocalPlaneXResolution of {pitch:g} px/mm is not positive"
    if focal is None or pitch is None:
        return None
    scale = _resize_scale(exif)
    f_px = focal * pitch * scale
    resized = f" (x {scale:.4g}: the photo was resized)" if scale != 1.0 else ""
    why = _field_of_view_problem(f_px, exif, f"FocalLength {focal:g} mm at {pitch:g} px/mm{resized}")
    return why or (f_px, SIGMA_FOCAL_PLANE_FRACTION)


def _field_of_view_problem(f_px: float, exif: PhotoExif, what: str) -> str | None:
    w, h = exif.width_px, exif.height_px
    hfov_deg = math.degrees(2.0 * math.atan(w / (2.0 * f_px)))
    if MIN_HFOV_DEG <= hfov_deg <= MAX_HFOV_DEG:
        return None
    return (f"{what} gives a horizontal field of view of {hfov_deg:.3g} deg on {w} x {h} pixels, "
            f"outside {MIN_HFOV_DEG:g}..{MAX_HFOV_DEG:g} deg")


def _resize_scale(exif: PhotoExif) -> float:
    """The stored width over PixelXDimension when the two sizes have the same shape (a photo resized
    whole after the camera wrote its focal-plane resolution); else 1 (a crop keeps the pitch)."""
    rw, rh = exif.recorded_width_px, exif.recorded_height_px
    sw, sh = exif.stored_size_px
    if not (rw and rh and rw > 0 and rh > 0) or (rw, rh) == (sw, sh):
        return 1.0
    if abs(rw * sh - rh * sw) > 0.01 * rw * sh:
        return 1.0
    return sw / rw


def _no_lens(exif: PhotoExif, name: str, p35: str | None, plane: str | None) -> str:
    """The error for a photo whose lens cannot be read: ``p35`` and ``plane`` say what is wrong with
    each way to it (None: absent)."""
    if not exif.has_exif:
        return f"{name}: no lens: the photo has no EXIF; {CAMERA_HINT}"
    focal = exif.focal_length_mm
    if p35 is None and plane is None:
        missing = (f"its EXIF has FocalLength {focal:g} mm but neither FocalLengthIn35mmFilm nor "
                   "FocalPlaneXResolution to turn it into pixels" if focal is not None else
                   "its EXIF has no FocalLengthIn35mmFilm nor FocalLength with FocalPlaneXResolution")
    elif p35 is None:
        missing = "its EXIF has no FocalLengthIn35mmFilm"
    elif plane is None:
        missing = (f"its FocalLength {focal:g} mm has no FocalPlaneXResolution to turn it into pixels"
                   if focal is not None else "its EXIF has no FocalLength with FocalPlaneXResolution")
    else:
        missing = None
    reasons = "; ".join(r for r in (p35, plane, missing) if r)
    damage = f" ({exif.exif_problem})" if exif.exif_problem else ""
    usable = "no lens" if p35 is None and plane is None else "no usable lens"
    return f"{name}: {usable}: {reasons}{damage}; {CAMERA_HINT}"


# --- the heading -----------------------------------------------------------------------------------


def heading_true_deg(exif: PhotoExif, lat: float | None = None, lon: float | None = None) -> float | None:
    """GPSImgDirection as an azimuth clockwise from true north (deg, 0..360).

    A magnetic direction ('M') is turned to true by the World Magnetic Model's declination at
    ``lat``, ``lon`` (both, or else the EXIF GPS position) and the EXIF altitude, at ``taken_utc``
    (or today).  None when there is no heading, when its reference is unknown, when it is magnetic
    and no position is known, or when no WMM covers the date (each but the first logged)."""
    if exif.heading_deg is None:
        return None
    if exif.heading_reference == "T":
        return exif.heading_deg
    if exif.heading_reference != "M":
        log.warning("EXIF GPSImgDirection %.2f deg without GPSImgDirectionRef: true or magnetic unknown, left out",
                    exif.heading_deg)
        return None
    if lat is None or lon is None:
        lat, lon = exif.lat, exif.lon
    if lat is None or lon is None:
        log.warning("EXIF GPSImgDirection %.2f deg is magnetic and the photo's position is unknown: left out",
                    exif.heading_deg)
        return None
    when = exif.taken_utc or dt.datetime.now(dt.timezone.utc)
    declination = _declination_deg(lat, lon, exif.altitude_m or 0.0, when)
    if declination is None:
        return None
    log.debug("EXIF heading %.2f deg magnetic, declination %.3f deg at %.5f, %.5f on %s", exif.heading_deg,
             declination, lat, lon, when.date())
    return (exif.heading_deg + declination) % 360.0


@functools.lru_cache(maxsize=8)
def _geomag(year: int) -> GeoMag:
    return GeoMag(base_year=year)


def _declination_deg(lat: float, lon: float, alt_m: float, when: dt.datetime) -> float | None:
    """The WMM declination (deg, east positive) at a place and time; None, logged, outside the
    models' years.  (The drivers' ``magnetic_to_true`` does the same, but vision may not import
    drivers.)"""
    try:
        result = _geomag(when.year).calculate(glat=lat, glon=lon, alt=alt_m / 1000.0,
                                              time=decimal_year_from_date(when))
    except ValueError as exc:
        log.warning("no World Magnetic Model for %s (%s): the magnetic heading is left out", when.date(), exc)
        return None
    return float(result.d)
