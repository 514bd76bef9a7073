"""``viper calibrate camera --output existing.toml`` replaces only its own table."""

from __future__ import annotations

import pytest
from viper_calibration.camera import write_camera_calibration

from appliance.vision.intrinsics import CameraIntrinsics, load_intrinsics

BEFORE = """# field kit 3, calibrated in the lab
[devices]
calibration_file = "calibration.toml"  # read by the drivers

[camera]
width = 640   # sensor mode
height = 480
fx = 1.0
fy = 1.0
cx = 1.0
cy = 1.0
distortion = [0.0, 0.0, 0.0, 0.0, 0.0]
reprojection_error_px = 9.0

[compass]
hard_iron_offset = [1e-06, -2e-06, 3e-07]
"""


def test_the_camera_table_is_replaced_and_every_other_byte_kept(tmp_path):
    path = tmp_path / "camera.toml"
    path.write_text(BEFORE)
    k = CameraIntrinsics(800, 600, 612.5, 611.0, 399.5, 299.5, (0.1, -0.2, 0.001, 0.002, 0.05), 0.31)
    write_camera_calibration(path, k)
    after = path.read_text()
    head, tail = BEFORE.split("[camera]")[0], BEFORE.split("[compass]")[1]
    assert after.startswith(head) and after.endswith("[compass]" + tail)
    assert "width = 800   # sensor mode" in after
    assert load_intrinsics(path) == k
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.toml"]


def test_a_calibration_without_an_error_drops_the_stale_one(tmp_path):
    path = tmp_path / "camera.toml"
    path.write_text(BEFORE)
    write_camera_calibration(path, CameraIntrinsics(640, 480, 500.0, 500.0, 319.5, 239.5))
    assert "reprojection_error_px" not in path.read_text()
    assert load_intrinsics(path).reprojection_error_px is None


def test_a_new_file_holds_only_the_camera_table(tmp_path):
    path = tmp_path / "new.toml"
    k = CameraIntrinsics(320, 240, 250.0, 250.0, 159.5, 119.5)
    write_camera_calibration(path, k)
    assert path.read_text().lstrip().startswith("[camera]")
    assert load_intrinsics(path) == k


@pytest.mark.parametrize("content", ["[camera\nwidth = 1\n", "camera = 3\n"])
def test_a_broken_file_is_refused_and_kept(tmp_path, content):
    from appliance.errors import ConfigError

    path = tmp_path / "camera.toml"
    path.write_text(content)
    with pytest.raises(ConfigError):
        write_camera_calibration(path, CameraIntrinsics(320, 240, 250.0, 250.0, 159.5, 119.5))
    assert path.read_text() == content
