"""Camera model: pixel <-> direction round trips and the levelled-camera oracle atan(dp / f)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.vision.camera import CameraPose, directions_to_pixels, pixels_to_directions, world_from_camera
from appliance.vision.intrinsics import CameraIntrinsics

K = CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)
K_DIST = CameraIntrinsics(640, 480, 500.0, 502.0, 318.0, 243.0, (-0.2, 0.05, 0.001, -0.0005, 0.0))


def test_levelled_camera_elevation_is_atan_dp_over_f() -> None:
    rows = np.array([0.0, 100.0, 240.0, 400.0])
    az, el = pixels_to_directions(K, CameraPose(30.0, 0.0, 0.0), np.full(4, 320.0), rows)
    np.testing.assert_allclose(el, np.degrees(np.arctan((240.0 - rows) / 500.0)), atol=1e-9)
    np.testing.assert_allclose(az, 30.0, atol=1e-9)


def test_right_of_centre_is_clockwise() -> None:
    az, _ = pixels_to_directions(K, CameraPose(350.0), np.array([820.0 - 0.0]), np.array([240.0]))
    assert az[0] == pytest.approx((350.0 + math.degrees(math.atan(500.0 / 500.0))) % 360.0)


def test_pitch_moves_the_horizon_row() -> None:
    # pitched up by 5 deg, the horizon (el 0) appears f * tan(5 deg) below the centre
    u, v = directions_to_pixels(K, CameraPose(0.0, 5.0, 0.0), np.array([0.0]), np.array([0.0]))
    assert v[0] == pytest.approx(240.0 + 500.0 * math.tan(math.radians(5.0)), abs=1e-6)
    assert u[0] == pytest.approx(320.0, abs=1e-6)


def test_roll_right_side_down() -> None:
    # rolled 10 deg (right side down): a horizon point to the right of centre appears above centre
    u, v = directions_to_pixels(K, CameraPose(0.0, 0.0, 10.0), np.array([20.0]), np.array([0.0]))
    assert v[0] < 240.0 - 10.0


@pytest.mark.parametrize("intr", [K, K_DIST])
@pytest.mark.parametrize("pose", [CameraPose(0, 0, 0), CameraPose(123.0, 3.0, -2.0), CameraPose(359.0, -8.0, 7.0)])
def test_round_trip(intr: CameraIntrinsics, pose: CameraPose) -> None:
    rng = np.random.default_rng(1)
    u = rng.uniform(20, 620, 200)
    v = rng.uniform(20, 460, 200)
    az, el = pixels_to_directions(intr, pose, u, v)
    u2, v2 = directions_to_pixels(intr, pose, az, el)
    np.testing.assert_allclose(u2, u, atol=1e-3)
    np.testing.assert_allclose(v2, v, atol=1e-3)


def test_rotation_is_orthonormal() -> None:
    r = world_from_camera(CameraPose(40.0, 12.0, -30.0))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_behind_camera_is_nan() -> None:
    u, v = directions_to_pixels(K, CameraPose(0.0), np.array([180.0]), np.array([0.0]))
    assert np.isnan(u[0]) and np.isnan(v[0])
