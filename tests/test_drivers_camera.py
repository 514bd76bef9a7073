"""V4L2 camera driver over the simulated capture: checked settings, flushed stills, unplug."""

from __future__ import annotations

import datetime as dt

import cv2
import numpy as np
import pytest

from appliance.config import CameraDeviceConfig
from appliance.drivers.camera import V4l2Camera
from appliance.errors import DeviceError
from appliance.sim.camera_twin import SimVideoCapture
from appliance.sim.world import SimClock, SimWorld
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.synth import analytic_skyline_fn

INTR = CameraIntrinsics.from_fov(96, 64, 60.0)
CFG = CameraDeviceConfig(width=96, height=64, exposure=100.0, flush_frames=3)


class CountingCapture(SimVideoCapture):
    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.grabs = 0

    def grab(self) -> bool:
        self.grabs += 1
        return super().grab()


def make(refuse: frozenset[int] = frozenset(), cfg: CameraDeviceConfig = CFG) -> tuple[V4l2Camera, CountingCapture]:
    world = SimWorld(36.6, -84.25, 500.0, clock=SimClock(dt.datetime(2026, 6, 1, tzinfo=dt.timezone.utc)))
    cap = CountingCapture(world, INTR, skyline_fn=analytic_skyline_fn(seed=1), refuse=refuse)
    return V4l2Camera(cfg, INTR, lambda *_: cap), cap


def test_settings_applied_and_stills_flushed() -> None:
    cam, cap = make()
    assert cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) == 1.0 and cap.get(cv2.CAP_PROP_EXPOSURE) == 100.0
    frame = cam.capture()
    assert frame.image.shape == (64, 96, 3) and cap.grabs == 3 and frame.exposure == 100.0
    cam.set_exposure(50.0)
    darker = cam.capture()
    assert darker.image.mean() < frame.image.mean() * 0.75


def test_refused_setting_is_a_device_error_naming_it() -> None:
    with pytest.raises(DeviceError, match="exposure set to 100.0"):
        make(refuse=frozenset({cv2.CAP_PROP_EXPOSURE}))
    with pytest.raises(DeviceError, match="width set to 640"):
        make(cfg=CameraDeviceConfig(width=640, height=64))


def test_optional_buffer_size_refusal_is_only_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    cam, _ = make(refuse=frozenset({cv2.CAP_PROP_BUFFERSIZE}))
    assert "buffer size" in caplog.text
    assert isinstance(cam.capture().image, np.ndarray)


def test_unplugged_camera_raises_on_capture() -> None:
    cam, cap = make()
    cap.unplug()
    with pytest.raises(DeviceError, match="unplugged"):
        cam.capture()


def test_missing_device_cannot_open() -> None:
    with pytest.raises(DeviceError, match="cannot open camera"):
        V4l2Camera(CameraDeviceConfig(device="/dev/video-none", width=96, height=64), INTR)
