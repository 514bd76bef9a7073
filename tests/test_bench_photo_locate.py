"""bench/photo_locate.py's synthetic photos: the EXIF focal length, and the skyline where the camera model puts it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import ExifTags, Image

from appliance.terrain.dem import load_dem
from appliance.vision.synth import dem_skyline_fn
from bench.photo_locate import (
    CAMERA_HEIGHT_M,
    Occluder,
    PhotoSpec,
    RecordedSkylineFn,
    exif_f35_mm,
    f35_from_px,
    near_share,
    photo_skyline_fn,
    px_from_f35,
    skyline_check,
    skyline_offsets_px,
    skyline_rows_px,
    write_photo,
)

LAT, LON = 36.69162, -84.19854  # jacksboro: a ridge in view to the east
POLE = Occluder(azimuth_deg=80.0, width_deg=3.0, raise_deg=6.0, distance_m=20.0, kind="pole")
TREE = Occluder(azimuth_deg=95.0, width_deg=2.0, raise_deg=4.0, distance_m=30.0, kind="tree")
SPEC = PhotoSpec(world="jacksboro", seed=7, fov_deg=60.0, site="test", lat=LAT, lon=LON, yaw_deg=86.4,
                 pitch_deg=1.6, roll_deg=1.0, weather="cloudy", occluders=(POLE, TREE), focal_error=0.025,
                 near_lat=LAT, near_lon=LON, near_radius_m=1784.0, width_px=480, height_px=270)


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    dem = load_dem("jacksboro")
    path = tmp_path_factory.mktemp("photo") / "p.jpg"
    recorded = RecordedSkylineFn(photo_skyline_fn(dem, SPEC))
    image = write_photo(path, dem, SPEC, recorded)
    return dem, path, image, recorded.table()


def test_the_35mm_focal_length_is_on_the_frame_diagonal():
    # a 36 x 24 mm frame 1800 x 1200 px: 50 mm is 2500 px, and the diagonal gives the same
    assert px_from_f35(50.0 * 43.2666 / np.hypot(36, 24), 1800, 1200) == pytest.approx(2500.0, rel=1e-12)
    assert f35_from_px(px_from_f35(28.0, 1280, 720), 1280, 720) == pytest.approx(28.0)


def test_the_jpeg_carries_the_drawn_focal_length_in_exif(photo):
    _, path, image, _ = photo
    true_f35 = f35_from_px(SPEC.intrinsics.fx, 480, 270)
    assert SPEC.exif_f35_mm == round(true_f35 * 1.025)
    assert exif_f35_mm(path) == SPEC.exif_f35_mm
    with Image.open(path) as img:
        assert img.format == "JPEG" and img.size == (480, 270)
        assert img.getexif()[ExifTags.Base.Make] == "viper bench"
    f_px = px_from_f35(exif_f35_mm(path), 480, 270)
    assert abs(f_px / SPEC.intrinsics.fx - 1.0) <= 0.025 + 0.5 / true_f35 + 1e-9
    assert image.shape == (270, 480, 3)


def test_the_skyline_lies_where_the_camera_model_puts_it(photo):
    _, _, image, table = photo
    check = skyline_check(image, table, SPEC, step_deg=None)
    assert check["skyline_in_frame"] == 1.0
    assert check["columns"] > 400
    assert check["median_abs_px"] < 0.3
    assert check["within_1_5_px"] > 0.95


def test_a_pose_half_a_degree_off_is_seen(photo):
    _, _, image, table = photo
    tilted = dataclasses.replace(SPEC, pitch_deg=SPEC.pitch_deg + 0.5)  # 0.5 deg is 3.6 px here
    off = skyline_offsets_px(image, skyline_rows_px(table, tilted, step_deg=None))
    assert np.nanmedian(off) == pytest.approx(-0.5 * np.pi / 180 * SPEC.intrinsics.fy, abs=0.5)


def test_the_near_objects_stand_above_the_terrain_in_the_photo(photo):
    dem, _, image, table = photo
    az = np.array([POLE.azimuth_deg, TREE.azimuth_deg, 70.0])  # the pole's and the tree's middle, then clear sky
    bare_deg, _ = dem_skyline_fn(dem, LAT, LON, CAMERA_HEIGHT_M)(az)
    seen_deg, seen_m = table(az)
    np.testing.assert_allclose(seen_deg - bare_deg, [6.0, 4.0, 0.0], atol=0.01)
    np.testing.assert_allclose(seen_m[:2], [20.0, 30.0])
    # the image's edge follows the pole, 6 deg (about 44 px) above the terrain behind it
    f = SPEC.intrinsics.fx
    u_pole = int(round(SPEC.intrinsics.cx + f * np.tan(np.radians(POLE.azimuth_deg - SPEC.yaw_deg))))
    rows = skyline_rows_px(table, SPEC, step_deg=None)
    off = skyline_offsets_px(image, rows)
    assert abs(off[u_pole]) < 1.0
    assert rows[u_pole] < rows[u_pole - 30] - 15  # 30 columns to the left (4 deg): the terrain, well below


def test_the_near_slope_share_tells_a_slope_in_front_from_a_far_ridge():
    """A camera facing up a slope 55-80 m away sees only near terrain; the camera of SPEC sees the
    ridge kilometres to the east."""
    dem = load_dem("jacksboro")
    slope = dataclasses.replace(SPEC, lat=36.55693, lon=-84.17902, yaw_deg=32.5, occluders=())
    assert near_share(dem, slope) == 1.0
    assert near_share(dem, dataclasses.replace(SPEC, occluders=())) == 0.0
    _, dist = dem_skyline_fn(dem, slope.lat, slope.lon, CAMERA_HEIGHT_M)(np.array([2.5, 32.5, 62.5]))
    assert np.all(dist < 150.0)
