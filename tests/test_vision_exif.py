"""A photo's EXIF, read from real image files written here by Pillow: the lens in pixels against
hand-computed focal lengths, the sizes against OpenCV's own decode of the same file (EXIF
orientation applied), the GPS block's signs, a magnetic heading turned by the World Magnetic Model
(pygeomag called here directly), the time, and bad or damaged input refused in one line or left out
with a warning."""

from __future__ import annotations

import datetime as dt
import logging
import math
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from PIL import ExifTags, Image, TiffImagePlugin
from pygeomag import GeoMag

from appliance.errors import InputError
from appliance.vision.exif import PhotoExif, heading_true_deg, intrinsics_from_exif, read_exif
from appliance.vision.panorama import read_image

R = TiffImagePlugin.IFDRational
T = ExifTags.Base
G = ExifTags.GPS
CAMERA_HINT = "--camera"
# a sensor 6.4 mm wide behind 4000 pixels: 625 px/mm, written as pixels per inch (FocalPlaneResolutionUnit 2)
PX_PER_MM = 625.0
PX_PER_INCH = R(625 * 254, 10)
Tags = Mapping[Any, Any]  # tag number -> value


def write_photo(path: Path, size: tuple[int, int] = (4000, 3000), base: Tags | None = None, sub: Tags | None = None,
                gps: Tags | None = None, fmt: str = "JPEG", exif: bool = True,
                save: dict[str, Any] | None = None) -> Path:
    """A real image file with an EXIF block holding ``base`` (IFD0), ``sub`` (the Exif IFD) and
    ``gps`` (the GPS IFD); the image has a marked top-left corner so its orientation shows."""
    w, h = size
    pixels = np.full((h, w, 3), 90, np.uint8)
    pixels[: max(1, h // 8), : max(1, w // 8)] = (255, 0, 0)
    im = Image.fromarray(pixels)
    save = dict(save or {})
    if exif:
        block = Image.Exif()
        for key, value in (base or {}).items():
            block[key] = value
        if sub:
            block.get_ifd(ExifTags.IFD.Exif).update(sub)
        if gps:
            block.get_ifd(ExifTags.IFD.GPSInfo).update(gps)
        save["exif"] = block
    im.save(path, fmt, **save)
    return path


def opencv_size(path: Path) -> tuple[int, int]:
    """(width, height) of the file as OpenCV decodes it (the flags of read_image)."""
    img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return img.shape[1], img.shape[0]


def one_line_error(exif: PhotoExif, name: str = "photo.jpg") -> str:
    with pytest.raises(InputError) as info:
        intrinsics_from_exif(exif, name)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{name}: ")
    assert CAMERA_HINT in message
    return message


FULL_SUB = {
    T.FocalLength: R(425, 100),
    T.FocalLengthIn35mmFilm: 24,
    T.FocalPlaneXResolution: PX_PER_INCH,
    T.FocalPlaneResolutionUnit: 2,
    T.DateTimeOriginal: "2024:05:06 07:08:09",
    T.OffsetTimeOriginal: "+02:00",
}
FULL_GPS = {
    G.GPSLatitudeRef: "S",
    G.GPSLatitude: (R(46, 1), R(30, 1), R(36, 1)),
    G.GPSLongitudeRef: "W",
    G.GPSLongitude: (R(7, 1), R(15, 1), R(0, 1)),
    G.GPSAltitudeRef: b"\x00",
    G.GPSAltitude: R(12345, 10),
    G.GPSImgDirectionRef: "M",
    G.GPSImgDirection: R(9050, 100),
}


# ----------------------------------------------------------------------------- reading the tags


def test_every_tag_read_with_its_sign_and_unit(tmp_path: Path) -> None:
    path = write_photo(tmp_path / "p.jpg", base={T.Make: "Maker", T.Model: "Model 1"}, sub=FULL_SUB, gps=FULL_GPS)
    exif = read_exif(path)
    assert (exif.width_px, exif.height_px, exif.orientation) == (4000, 3000, 1)
    assert exif.focal_length_mm == pytest.approx(4.25)
    assert exif.focal_35mm_mm == 24.0
    assert exif.focal_plane_px_per_mm == pytest.approx(625.0)  # 15875 px/inch / 25.4
    # 46 deg 30' 36" S, 7 deg 15' 0" W
    assert exif.lat == pytest.approx(-46.51, abs=1e-12)
    assert exif.lon == pytest.approx(-7.25, abs=1e-12)
    assert exif.altitude_m == pytest.approx(1234.5)
    assert (exif.heading_deg, exif.heading_reference) == (pytest.approx(90.5), "M")
    # 07:08:09 at +02:00 is 05:08:09 UTC
    assert exif.taken_utc == dt.datetime(2024, 5, 6, 5, 8, 9, tzinfo=dt.timezone.utc)
    assert exif.taken_utc_source == "DateTimeOriginal+OffsetTimeOriginal"
    assert exif.camera == "Maker Model 1"
    assert exif.has_exif and exif.exif_problem is None


def test_north_east_positive_and_below_sea_level_negative(tmp_path: Path) -> None:
    gps = {G.GPSLatitudeRef: "N", G.GPSLatitude: (R(61, 1), R(30, 1), R(0, 1)),
           G.GPSLongitudeRef: "E", G.GPSLongitude: (R(7, 1), R(30, 1), R(18, 1)),
           G.GPSAltitudeRef: b"\x01", G.GPSAltitude: R(28, 1)}
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), gps=gps))
    assert exif.lat == pytest.approx(61.5, abs=1e-12)
    assert exif.lon == pytest.approx(7.505, abs=1e-12)
    assert exif.altitude_m == -28.0


def test_no_exif_gives_nones(tmp_path: Path) -> None:
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(640, 480), exif=False))
    assert exif == PhotoExif(640, 480, 1)
    assert not exif.has_exif


@pytest.mark.parametrize(
    ("dto", "offset", "gps", "expected", "source"),
    [
        ("2023:12:31 23:30:00", "-05:30", None, dt.datetime(2024, 1, 1, 5, 0, 0),
         "DateTimeOriginal+OffsetTimeOriginal"),
        # no zone on DateTimeOriginal: the GPS time (UTC) is the better one
        ("2024:05:06 07:08:09", None, ("2024:05:06", (R(4, 1), R(8, 1), R(95, 10))),
         dt.datetime(2024, 5, 6, 4, 8, 9, 500000), "GPSDateStamp+GPSTimeStamp"),
        (None, None, ("2024:02:29", (R(23, 1), R(59, 1), R(59, 1))), dt.datetime(2024, 2, 29, 23, 59, 59),
         "GPSDateStamp+GPSTimeStamp"),
        ("2024:05:06 07:08:09", None, None, dt.datetime(2024, 5, 6, 7, 8, 9),
         "DateTimeOriginal (local time of unknown zone, read as UTC)"),
        ("0000:00:00 00:00:00", None, None, None, None),  # EXIF's "unknown"
        # an offset that is none, and a GPS date that is no day: both left out (with a warning)
        ("2024:05:06 07:08:09", "+2h", ("2024:02:30", (R(1, 1), R(0, 1), R(0, 1))),
         dt.datetime(2024, 5, 6, 7, 8, 9), "DateTimeOriginal (local time of unknown zone, read as UTC)"),
    ],
)
def test_time_taken(tmp_path: Path, dto: str | None, offset: str | None, gps: tuple[str, tuple[R, R, R]] | None,
                    expected: dt.datetime | None, source: str | None) -> None:
    sub: dict[int, Any] = {}
    if dto:
        sub[T.DateTimeOriginal] = dto
    if offset:
        sub[T.OffsetTimeOriginal] = offset
    gps_ifd = {G.GPSDateStamp: gps[0], G.GPSTimeStamp: gps[1]} if gps else None
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), base={T.Make: "M"}, sub=sub, gps=gps_ifd))
    assert exif.taken_utc == (None if expected is None else expected.replace(tzinfo=dt.timezone.utc))
    assert exif.taken_utc_source == source


# ----------------------------------------------------------------------------- orientation against OpenCV


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_sizes_are_those_opencv_decodes(tmp_path: Path, orientation: int) -> None:
    path = write_photo(tmp_path / "p.jpg", size=(400, 300), base={T.Orientation: orientation},
                       sub={T.FocalLengthIn35mmFilm: 24})
    exif = read_exif(path)
    quarter = orientation >= 5
    assert exif.orientation == orientation
    assert (exif.width_px, exif.height_px) == ((300, 400) if quarter else (400, 300))
    assert opencv_size(path) == (exif.width_px, exif.height_px)
    assert read_image(path).shape[:2] == (exif.height_px, exif.width_px)
    assert exif.stored_size_px == (400, 300)


def test_orientation_6_portrait_camera_and_decoded_pixels(tmp_path: Path) -> None:
    """Orientation 6 (turn the stored image a quarter clockwise to see it): OpenCV returns the
    turned pixels, and the camera is built for them (width 3000, height 4000)."""
    path = write_photo(tmp_path / "p.jpg", size=(4000, 3000), base={T.Orientation: 6},
                       sub={T.FocalLengthIn35mmFilm: 24})
    exif = read_exif(path)
    assert (exif.width_px, exif.height_px) == (3000, 4000)
    img = read_image(path)
    assert img.shape[:2] == (4000, 3000)
    # the stored top-left mark (red) is now at the top-right
    assert img[10, 3000 - 10, 2] > 200 and img[10, 10, 2] < 150
    camera, _ = intrinsics_from_exif(exif, "p.jpg")
    assert (camera.width, camera.height) == (3000, 4000)
    assert (camera.cx, camera.cy) == (1499.5, 1999.5)
    assert camera.fx == pytest.approx(24 * 5000 / 43.266615305567875, rel=1e-12)


@pytest.mark.parametrize("fmt", ["PNG", "WEBP", "TIFF"])
@pytest.mark.parametrize("orientation", [6, 8])
def test_other_formats_turned_as_opencv_turns_them(tmp_path: Path, fmt: str, orientation: int) -> None:
    path = write_photo(tmp_path / f"p.{fmt.lower()}", size=(400, 300), base={T.Orientation: orientation},
                       fmt=fmt, save={"lossless": True} if fmt == "WEBP" else None)
    exif = read_exif(path)
    assert (exif.width_px, exif.height_px) == (300, 400)
    assert opencv_size(path) == (300, 400)


@pytest.mark.parametrize("orientation", [0, 9, 300])
def test_orientation_out_of_range_is_upright_as_for_opencv(tmp_path: Path, orientation: int,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    path = write_photo(tmp_path / "p.jpg", size=(400, 300), base={T.Orientation: orientation})
    with caplog.at_level(logging.WARNING):
        exif = read_exif(path)
    assert (exif.orientation, exif.width_px, exif.height_px) == (1, 400, 300)
    assert opencv_size(path) == (400, 300)
    assert f"Orientation {orientation}" in caplog.text


def test_xmp_orientation_is_not_applied_as_opencv_does_not(tmp_path: Path) -> None:
    """Pillow takes a missing EXIF Orientation from XMP; OpenCV does not turn the image for it."""
    xmp = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
           b'<rdf:Description xmlns:tiff="http://ns.adobe.com/tiff/1.0/" tiff:Orientation="6"/></rdf:RDF></x:xmpmeta>')
    path = write_photo(tmp_path / "p.jpg", size=(400, 300), base={T.Make: "M"}, save={"xmp": xmp})
    with Image.open(path) as im:
        assert im.getexif().get(T.Orientation) == 6  # what Pillow alone would say
    exif = read_exif(path)
    assert (exif.orientation, exif.width_px, exif.height_px) == (1, 400, 300)
    assert opencv_size(path) == (400, 300)


# ----------------------------------------------------------------------------- the lens


def test_35mm_equivalent_on_the_diagonal(tmp_path: Path) -> None:
    exif = read_exif(write_photo(tmp_path / "p.jpg", sub=FULL_SUB))
    camera, sigma = intrinsics_from_exif(exif, "p.jpg")
    # 24 mm on a 43.27 mm diagonal, 5000 px across the 4000 x 3000 diagonal
    assert camera.fx == pytest.approx(2773.5009811261452, rel=1e-12)
    assert camera.fy == camera.fx
    assert (camera.width, camera.height, camera.cx, camera.cy) == (4000, 3000, 1999.5, 1499.5)
    assert camera.distortion == (0.0, 0.0, 0.0, 0.0, 0.0)
    assert camera.hfov_deg == pytest.approx(2 * math.degrees(math.atan(2000 / 2773.5009811261452)))
    assert sigma == 0.03


@pytest.mark.parametrize(("f35", "sigma"), [(14, 0.5 / 14), (16, 0.5 / 16), (17, 0.03), (200, 0.03)])
def test_35mm_uncertainty_is_half_a_millimetre_or_3_percent(tmp_path: Path, f35: int, sigma: float) -> None:
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(400, 300), sub={T.FocalLengthIn35mmFilm: f35}))
    camera, got = intrinsics_from_exif(exif, "p.jpg")
    assert got == pytest.approx(sigma, rel=1e-12)
    assert camera.fx == pytest.approx(f35 * 500 / 43.266615305567875, rel=1e-12)


@pytest.mark.parametrize(("resolution", "unit"),
                         [(PX_PER_INCH, 2), (PX_PER_INCH, None), (R(6250, 1), 3), (R(625, 1), 4)])
def test_focal_plane_when_the_35mm_equivalent_is_0(tmp_path: Path, resolution: R, unit: int | None) -> None:
    """FocalLengthIn35mmFilm 0 is the maker's "unknown": FocalLength times the focal-plane
    resolution (in inches, the default unit, in cm or in mm) is used."""
    sub: dict[int, Any] = {T.FocalLengthIn35mmFilm: 0, T.FocalLength: R(425, 100),
                           T.FocalPlaneXResolution: resolution}
    if unit is not None:
        sub[T.FocalPlaneResolutionUnit] = unit
    exif = read_exif(write_photo(tmp_path / "p.jpg", sub=sub))
    assert exif.focal_35mm_mm == 0.0
    camera, sigma = intrinsics_from_exif(exif, "p.jpg")
    assert camera.fx == pytest.approx(4.25 * 625, rel=1e-12)  # 2656.25 px
    assert sigma == 0.02


def test_focal_plane_of_a_photo_resized_after_the_camera(tmp_path: Path) -> None:
    """PixelXDimension says the camera wrote 8000 x 6000; the file holds 4000 x 3000: the pitch
    halves.  A crop (another shape) keeps it."""
    sub = {T.FocalLength: R(425, 100), T.FocalPlaneXResolution: PX_PER_INCH, T.FocalPlaneResolutionUnit: 2,
           T.ExifImageWidth: 8000, T.ExifImageHeight: 6000}
    camera, _ = intrinsics_from_exif(read_exif(write_photo(tmp_path / "r.jpg", sub=sub)), "r.jpg")
    assert camera.fx == pytest.approx(4.25 * 625 / 2, rel=1e-12)
    crop = write_photo(tmp_path / "c.jpg", size=(4000, 2250), sub={**sub, T.ExifImageWidth: 4000,
                                                                   T.ExifImageHeight: 3000})
    camera, _ = intrinsics_from_exif(read_exif(crop), "c.jpg")
    assert camera.fx == pytest.approx(4.25 * 625, rel=1e-12)


def test_focal_plane_of_a_turned_photo_is_along_the_sensor(tmp_path: Path) -> None:
    sub = {T.FocalLength: R(425, 100), T.FocalPlaneXResolution: PX_PER_INCH, T.ExifImageWidth: 4000,
           T.ExifImageHeight: 3000}
    exif = read_exif(write_photo(tmp_path / "p.jpg", base={T.Orientation: 8}, sub=sub))
    camera, _ = intrinsics_from_exif(exif, "p.jpg")
    assert (camera.width, camera.height, camera.fx) == (3000, 4000, pytest.approx(2656.25, rel=1e-12))


def test_disagreeing_sources_are_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    sub = {T.FocalLengthIn35mmFilm: 50, T.FocalLength: R(425, 100), T.FocalPlaneXResolution: PX_PER_INCH}
    with caplog.at_level(logging.WARNING):
        camera, _ = intrinsics_from_exif(read_exif(write_photo(tmp_path / "p.jpg", sub=sub)), "p.jpg")
    assert camera.fx == pytest.approx(50 * 5000 / 43.266615305567875, rel=1e-12)
    assert "% apart" in caplog.text


# ----------------------------------------------------------------------------- no usable lens


def test_no_exif_needs_a_camera_file(tmp_path: Path) -> None:
    exif = read_exif(write_photo(tmp_path / "p.jpg", exif=False))
    assert one_line_error(exif) == ("photo.jpg: no lens: the photo has no EXIF; "
                                    "give --camera CAM.toml (from 'viper calibrate camera')")


def test_exif_without_a_lens(tmp_path: Path) -> None:
    exif = read_exif(write_photo(tmp_path / "p.jpg", gps=FULL_GPS))
    assert one_line_error(exif) == (
        "photo.jpg: no lens: its EXIF has no FocalLengthIn35mmFilm nor FocalLength with FocalPlaneXResolution; "
        "give --camera CAM.toml (from 'viper calibrate camera')")
    exif = read_exif(write_photo(tmp_path / "q.jpg", sub={T.FocalLength: R(425, 100)}))
    assert "FocalLength 4.25 mm but neither FocalLengthIn35mmFilm nor FocalPlaneXResolution" in one_line_error(exif)


@pytest.mark.parametrize(
    ("sub", "named"),
    [
        ({T.FocalLengthIn35mmFilm: 0}, "FocalLengthIn35mmFilm is 0"),
        ({T.FocalLength: R(0, 1), T.FocalPlaneXResolution: PX_PER_INCH}, "FocalLength 0 mm is not a positive length"),
        ({T.FocalLength: R(-425, 100), T.FocalPlaneXResolution: PX_PER_INCH}, "FocalLength -4.25 mm"),
        ({T.FocalLength: R(425, 0), T.FocalPlaneXResolution: PX_PER_INCH}, "FocalLength nan mm"),  # 425/0
        ({T.FocalLength: R(425, 100), T.FocalPlaneXResolution: R(1, 0)}, "FocalPlaneXResolution of nan px/mm"),
        # 1 mm equivalent: 115.6 px across 4000 px, a 173.4 deg view; 2 m: a 0.99 deg view
        ({T.FocalLengthIn35mmFilm: 1}, "FocalLengthIn35mmFilm 1 mm gives a horizontal field of view of 173 deg"),
        ({T.FocalLengthIn35mmFilm: 2000}, "FocalLengthIn35mmFilm 2000 mm gives a horizontal field of view of 0.992"),
        # 0.05 mm at 625 px/mm: 31 px across 4000 px, a 178.2 deg view (a pinhole never reaches 180)
        ({T.FocalLength: R(5, 100), T.FocalPlaneXResolution: PX_PER_INCH},
         "FocalLength 0.05 mm at 625 px/mm gives a horizontal field of view of 178 deg"),
    ],
)
def test_bad_lens_values_named_in_one_line(tmp_path: Path, sub: Tags, named: str) -> None:
    message = one_line_error(read_exif(write_photo(tmp_path / "p.jpg", sub=sub)))
    assert named in message
    assert "nan" not in message or "nan" in named


def test_a_bad_35mm_equivalent_falls_back_to_the_focal_plane(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    sub = {T.FocalLengthIn35mmFilm: 1, T.FocalLength: R(425, 100), T.FocalPlaneXResolution: PX_PER_INCH}
    with caplog.at_level(logging.WARNING):
        camera, sigma = intrinsics_from_exif(read_exif(write_photo(tmp_path / "p.jpg", sub=sub)), "p.jpg")
    assert (camera.fx, sigma) == (pytest.approx(2656.25, rel=1e-12), 0.02)
    assert "FocalLengthIn35mmFilm 1 mm gives" in caplog.text


def test_a_text_focal_length_is_absent(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        exif = read_exif(write_photo(tmp_path / "p.jpg", sub={T.FocalLength: "4.25 mm"}))
    assert exif.focal_length_mm is None
    assert "FocalLength '4.25 mm' is not a number" in caplog.text


# ----------------------------------------------------------------------------- the heading


def wmm_declination_deg(lat: float, lon: float, alt_km: float, decimal_year: float) -> float:
    return float(GeoMag(base_year=int(decimal_year)).calculate(glat=lat, glon=lon, alt=alt_km, time=decimal_year).d)


def test_true_heading_is_kept(tmp_path: Path) -> None:
    gps = {**FULL_GPS, G.GPSImgDirectionRef: "T", G.GPSImgDirection: R(35999, 100)}
    assert heading_true_deg(read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), gps=gps))) == 359.99


def test_magnetic_heading_turned_by_the_wmm_at_the_photo(tmp_path: Path) -> None:
    # 46.51 S, 7.25 W, 1234.5 m, 2024-05-06 05:08 UTC: day 126 of the 366 of 2024
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), sub=FULL_SUB, gps=FULL_GPS))
    declination = wmm_declination_deg(-46.51, -7.25, 1.2345, 2024 + 126 / 366)
    assert -25.0 < declination < -15.0  # the South Atlantic's westerly declination
    assert heading_true_deg(exif) == pytest.approx((90.5 + declination) % 360.0, abs=1e-9)


def test_magnetic_heading_at_a_given_place(tmp_path: Path) -> None:
    gps = {G.GPSImgDirectionRef: "M", G.GPSImgDirection: R(359, 1)}
    sub = {T.DateTimeOriginal: "2026:07:01 12:00:00", T.OffsetTimeOriginal: "+00:00"}
    exif = read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), sub=sub, gps=gps))
    assert exif.lat is None
    assert heading_true_deg(exif) is None  # magnetic and nowhere
    # Finse, Norway: an easterly declination of a few degrees; day 181 of the 365 of 2026
    declination = wmm_declination_deg(60.6, 7.5, 0.0, 2026 + 181 / 365)
    assert 1.0 < declination < 6.0
    assert heading_true_deg(exif, lat=60.6, lon=7.5) == pytest.approx((359.0 + declination) % 360.0, abs=1e-9)


def test_heading_without_reference_or_model_is_left_out(tmp_path: Path) -> None:
    no_ref = read_exif(write_photo(tmp_path / "a.jpg", size=(64, 48), gps={G.GPSImgDirection: R(90, 1)}))
    assert (no_ref.heading_deg, no_ref.heading_reference) == (90.0, None)
    assert heading_true_deg(no_ref) is None
    old = read_exif(write_photo(tmp_path / "b.jpg", size=(64, 48), gps=FULL_GPS,
                                sub={T.DateTimeOriginal: "2005:06:01 12:00:00", T.OffsetTimeOriginal: "+00:00"}))
    assert heading_true_deg(old) is None  # no WMM before 2010
    assert heading_true_deg(read_exif(write_photo(tmp_path / "c.jpg", size=(64, 48)))) is None


# ----------------------------------------------------------------------------- damaged values and blocks


def test_zero_denominators_do_not_crash(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    gps = {G.GPSLatitudeRef: "N", G.GPSLatitude: (R(46, 1), R(30, 0), R(0, 1)),
           G.GPSLongitudeRef: "E", G.GPSLongitude: (R(7, 1), R(0, 1), R(0, 1)),
           G.GPSAltitude: R(5, 0), G.GPSImgDirectionRef: "T", G.GPSImgDirection: R(0, 0),
           G.GPSDateStamp: "2024:05:06", G.GPSTimeStamp: (R(1, 0), R(0, 1), R(0, 1))}
    sub = {T.FocalLengthIn35mmFilm: 24, T.FocalPlaneXResolution: R(0, 0), T.FocalLength: R(0, 0)}
    with caplog.at_level(logging.WARNING):
        exif = read_exif(write_photo(tmp_path / "p.jpg", sub=sub, gps=gps))
    assert (exif.lat, exif.lon, exif.altitude_m, exif.heading_deg, exif.taken_utc) == (None,) * 5
    assert math.isnan(exif.focal_length_mm or 0.0) and math.isnan(exif.focal_plane_px_per_mm or 0.0)
    for tag in ("GPSLatitude", "GPSAltitude", "GPSImgDirection", "GPSTimeStamp"):
        assert f"EXIF {tag} " in caplog.text
    camera, _ = intrinsics_from_exif(exif, "p.jpg")  # the 35 mm equivalent is whole
    assert camera.fx == pytest.approx(2773.5009811261452, rel=1e-12)


@pytest.mark.parametrize(
    ("gps", "why"),
    [
        ({G.GPSLatitude: (R(46, 1), R(0, 1), R(0, 1)), G.GPSLongitudeRef: "E", G.GPSLongitude: (R(7, 1),)},
         "no hemisphere"),
        ({G.GPSLatitudeRef: "N", G.GPSLatitude: (R(95, 1), R(0, 1), R(0, 1)), G.GPSLongitudeRef: "E",
          G.GPSLongitude: (R(7, 1),)}, "is not 0..90 degrees"),
        ({G.GPSLatitudeRef: "N", G.GPSLatitude: (R(0, 1), R(0, 1), R(0, 1)), G.GPSLongitudeRef: "E",
          G.GPSLongitude: (R(0, 1), R(0, 1), R(0, 1))}, "placeholder"),
    ],
)
def test_a_position_that_is_no_place_is_left_out(tmp_path: Path, gps: Tags, why: str,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        exif = read_exif(write_photo(tmp_path / "p.jpg", size=(64, 48), gps=gps))
    assert (exif.lat, exif.lon) == (None, None)
    assert why in caplog.text


def exif_segment(path: Path) -> tuple[bytes, int, int]:
    """The file's bytes, and the start and length of its EXIF block's TIFF data in them."""
    data = path.read_bytes()
    start = data.index(b"Exif\x00\x00") + 6
    (length,) = struct.unpack(">H", data[start - 8: start - 6])
    return data, start, length - 8


def test_a_garbled_exif_block_is_absent_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = write_photo(tmp_path / "p.jpg", size=(400, 300), base={T.Orientation: 6}, sub=FULL_SUB, gps=FULL_GPS)
    data, start, _ = exif_segment(path)
    path.write_bytes(data[:start] + b"XX" + data[start + 2:])  # neither II nor MM: no TIFF header
    with caplog.at_level(logging.WARNING):
        exif = read_exif(path)
    assert exif == PhotoExif(400, 300, 1, has_exif=True, exif_problem=exif.exif_problem)
    assert exif.exif_problem and "damaged" in exif.exif_problem
    assert "EXIF block is damaged" in caplog.text
    message = one_line_error(exif, "p.jpg")
    assert message.startswith("p.jpg: no lens: its EXIF has no FocalLengthIn35mmFilm")
    assert "(its EXIF block is damaged" in message


def test_a_directory_beyond_the_block_keeps_what_was_read(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The Exif IFD's pointer aims past the block's end: the lens is lost, the orientation kept."""
    path = write_photo(tmp_path / "p.jpg", size=(400, 300), base={T.Orientation: 6}, sub=FULL_SUB)
    data, start, length = exif_segment(path)
    block = bytearray(data[start:start + length])
    endian = "<" if block[:2] == b"II" else ">"
    (ifd0,) = struct.unpack(endian + "I", block[4:8])
    (count,) = struct.unpack(endian + "H", block[ifd0:ifd0 + 2])
    for i in range(count):
        entry = ifd0 + 2 + 12 * i
        if struct.unpack(endian + "H", block[entry:entry + 2])[0] == ExifTags.IFD.Exif:
            block[entry + 8:entry + 12] = struct.pack(endian + "I", 0xFFFFFF)
    path.write_bytes(data[:start] + bytes(block) + data[start + length:])
    with caplog.at_level(logging.WARNING):
        exif = read_exif(path)
    assert (exif.orientation, exif.width_px, exif.height_px) == (6, 300, 400)
    assert opencv_size(path) == (300, 400)
    assert exif.focal_35mm_mm is None and exif.exif_problem
    assert "Corrupt EXIF data" in caplog.text
    assert "damaged" in one_line_error(exif)


# ----------------------------------------------------------------------------- bounded reading


def test_files_that_are_no_photo_are_refused_in_one_line(tmp_path: Path) -> None:
    (tmp_path / "notes.jpg").write_text("not an image\n")
    fifo = tmp_path / "fifo.jpg"
    os.mkfifo(fifo)
    # a PNG header declaring 100000 x 100000 pixels, refused before anything is decoded
    huge = tmp_path / "huge.png"
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)
    huge.write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + b"\0\0\0\0")
    cases = {tmp_path / "missing.jpg": "not found", tmp_path / "notes.jpg": "not an image", fifo: "a FIFO",
             tmp_path: "a folder", huge: "more than 50,000,000"}
    for path, why in cases.items():
        with pytest.raises(InputError) as info:
            read_exif(path)
        assert why in str(info.value) and "\n" not in str(info.value)
        assert str(info.value).startswith(str(path))


def test_random_damage_to_the_exif_block_never_escapes(tmp_path: Path) -> None:
    """Bytes of the EXIF block overwritten at random, 300 times: reading gives a PhotoExif (the
    size always the file's), and the lens is a camera or a one-line InputError."""
    path = write_photo(tmp_path / "p.jpg", size=(64, 48), base={T.Orientation: 1, T.Make: "M"}, sub=FULL_SUB,
                       gps=FULL_GPS)
    data, start, length = exif_segment(path)
    rng = np.random.default_rng(7)
    outcomes = {"camera": 0, "refused": 0}
    for i in range(300):
        block = bytearray(data[start:start + length])
        at = rng.integers(0, length, size=int(rng.integers(1, 9)))
        values = rng.integers(0, 256, size=at.size)
        for j, v in zip(at, values):
            block[int(j)] = int(v)
        damaged = tmp_path / f"d{i}.jpg"
        damaged.write_bytes(data[:start] + bytes(block) + data[start + length:])
        exif = read_exif(damaged)
        assert {exif.width_px, exif.height_px} == {64, 48}
        try:
            camera, sigma = intrinsics_from_exif(exif, "d.jpg")
        except InputError as exc:
            assert "\n" not in str(exc) and CAMERA_HINT in str(exc)
            outcomes["refused"] += 1
        else:
            assert 3.0 <= camera.hfov_deg <= 160.0 and sigma > 0
            outcomes["camera"] += 1
    assert outcomes["camera"] > 0 and outcomes["refused"] > 0
