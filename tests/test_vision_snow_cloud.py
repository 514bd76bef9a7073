"""White cloud behind a snowy ridge told from the snow by its colour (appliance.vision.skyline_snow.white_cloud)
and the skyline found under it by detect_rows without the capture ring's motion map."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.vision.skyline_detect import DetectionConfig, detect_rows
from appliance.vision.skyline_pixels import _luma, _to_float
from appliance.vision.skyline_snow import white_cloud

H, W = 140, 480
SKY_RGB = (0.76, 0.82, 0.90)  # the weather twin's snow-class sky at the horizon
SNOW_RGB = (0.90, 0.92, 0.95)  # the twin's snow: blue minus red 0.05
CLOUD_RGB = (0.90, 0.91, 0.93)  # a white cloud, blue minus red 0.03 (the twin's: 0.03 times its shade)
CLOUD_COLUMNS = slice(160, 320)


def ridge_rows() -> np.ndarray:
    cols = np.arange(W)
    return 60.0 + 10.0 * np.sin(cols / 45.0) + 4.0 * np.sin(cols / 13.0)


def cloudy_snow_ridge(seed: int, cloud_rgb: tuple[float, float, float] = CLOUD_RGB,
                      cloud_at_ridge: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A BGR uint8 image of a snowy ridge (snow brighter than the sky, dark rocks 20-30 rows below the
    skyline) under the pale sky, with a white cloud of ``cloud_rgb`` over CLOUD_COLUMNS: behind the
    ridge from 30 rows above it down to it (``cloud_at_ridge``), or from 40 to 20 rows above it with
    clear sky between; sensor noise.  And the skyline's row per column (pixel centres at integers)."""
    cols = np.arange(W)
    ridge = ridge_rows()
    rr = np.arange(H)[:, None]
    share_sky = np.clip(ridge[None, :] - rr + 0.5, 0.0, 1.0)[..., None]
    sky = np.array(SKY_RGB[::-1]) * np.ones((H, W, 1))
    lo, hi = (0.0, 30.0) if cloud_at_ridge else (20.0, 40.0)
    in_cloud = (rr <= ridge[None, :] - lo) & (rr >= ridge[None, :] - hi)
    in_cloud &= (cols[None, :] >= CLOUD_COLUMNS.start) & (cols[None, :] < CLOUD_COLUMNS.stop)
    sky[in_cloud] = cloud_rgb[::-1]
    ground = np.array(SNOW_RGB[::-1]) * np.ones((H, W, 1))
    rock = (rr - ridge[None, :] - 25.0) ** 2 / 36.0 + ((cols[None, :] % 60) - 30.0) ** 2 / 100.0 < 1.0
    ground[rock] = (0.15, 0.20, 0.15)
    img = sky * share_sky + ground * (1.0 - share_sky)
    img = np.clip(img + np.random.default_rng(seed).normal(0.0, 0.01, img.shape), 0.0, 1.0)
    return (img * 255.0 + 0.5).astype(np.uint8), ridge


def cloud_map(img: np.ndarray, ridge: np.ndarray) -> np.ndarray | None:
    f = _to_float(img)
    rr = np.arange(H)[:, None]
    return white_cloud(f, _luma(f), (rr >= ridge[None, :] + 3) & (rr <= ridge[None, :] + 30))


def test_a_cloud_less_blue_than_the_snow_is_marked_and_the_snow_is_not() -> None:
    img, ridge = cloudy_snow_ridge(1)
    cloud = cloud_map(img, ridge)
    assert cloud is not None
    rr = np.arange(H)[:, None]
    cols = np.arange(W)[None, :]
    inner = (cols >= CLOUD_COLUMNS.start + 10) & (cols < CLOUD_COLUMNS.stop - 10)
    # the cloud's inside (a box from its edges is all cloud); the snow, rocks or not, anywhere below the ridge
    inside = inner & (rr <= ridge[None, :] - 3) & (rr >= ridge[None, :] - 27)
    assert cloud[inside].mean() >= 0.95
    assert not cloud[rr >= ridge[None, :] + 2].any()
    # the blue sky beside the cloud
    assert not cloud[(rr <= ridge[None, :] - 3) & (cols < CLOUD_COLUMNS.start - 10)].any()


def test_a_cloud_as_blue_as_the_snow_is_not_marked() -> None:
    img, ridge = cloudy_snow_ridge(2, cloud_rgb=SNOW_RGB)
    cloud = cloud_map(img, ridge)
    assert cloud is not None and not cloud.any()


@pytest.mark.parametrize("seed", [1, 2])
def test_the_ridge_under_a_white_cloud_is_found_without_a_motion_map(seed: int) -> None:
    img, ridge = cloudy_snow_ridge(seed)
    cols = slice(CLOUD_COLUMNS.start + 5, CLOUD_COLUMNS.stop - 5)
    rows, _ = detect_rows(img, DetectionConfig(), wrap=False)
    err = np.nan_to_num(rows[cols] - ridge[cols], nan=99.0)
    # 0.2 deg is 1.93 px at the capture ring's 9.67 px/deg; the line is placed on the first pixel the
    # cloud marked does not reach, up to a row or two above the ridge (the boxes blend cloud and snow)
    assert np.mean(np.abs(err) <= 1.93) >= 0.85
    assert -2.0 <= float(np.median(err)) <= 0.5
    # and none on the snow below the ridge by more than the 0.5 deg (4.8 px)
    assert not np.any((err > 4.8) & (err < 99.0))
    # without the colour cue the cloud, as white and as bright as the snow, hides the ridge
    rows_off, _ = detect_rows(img, DetectionConfig(cloud_colour=False), wrap=False)
    err_off = np.nan_to_num(rows_off[cols] - ridge[cols], nan=99.0)
    assert np.mean(np.abs(err_off) <= 1.0) < 0.5


def test_a_cloud_in_the_sky_above_the_ridge_leaves_the_line_on_the_ridge() -> None:
    img, ridge = cloudy_snow_ridge(3, cloud_at_ridge=False)
    rows, _ = detect_rows(img, DetectionConfig(), wrap=False)
    inner = slice(20, 460)
    err = np.nan_to_num(rows[inner] - ridge[inner], nan=99.0)
    assert np.mean(np.abs(err) <= 1.0) >= 0.9
    assert not np.any((err > 2.0) & (err < 99.0))
