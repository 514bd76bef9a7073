"""Camera through OpenCV's V4L2 backend: manual exposure, every ``set()`` checked, fresh stills.

``cv2.VideoCapture.set`` returns False when the driver refuses a property, and a driver may accept
a value but apply another: each setting is therefore set, read back and compared, and a refusal
raises :class:`DeviceError` naming the property.  V4L2 keeps a queue of frames filled while the
application was busy: :meth:`V4l2Camera.capture` drops ``flush_frames`` of them (``grab``) before
the still it returns, so a still shows the scene after the stage stopped, not before.

``capture_factory`` makes the capture object (``cv2.VideoCapture`` by default); the simulated
camera (:class:`appliance.sim.camera_twin.SimVideoCapture`) has the same methods.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from appliance.config import CameraDeviceConfig
from appliance.errors import DeviceError
from appliance.vision.intrinsics import CameraIntrinsics

log = logging.getLogger(__name__)

#: V4L2's manual-exposure value of CAP_PROP_AUTO_EXPOSURE (V4L2_EXPOSURE_MANUAL through OpenCV).
V4L2_EXPOSURE_MANUAL = 1.0


@dataclass(frozen=True)
class CameraFrame:
    """One still: HxWx3 uint8 BGR, its UTC receive time (ns) and the exposure it was taken with."""

    time_ns: int
    image: np.ndarray
    exposure: float


class V4l2Camera:
    def __init__(
        self,
        config: CameraDeviceConfig,
        intrinsics: CameraIntrinsics,
        capture_factory: Callable[..., Any] = cv2.VideoCapture,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.config = config
        self._intrinsics = intrinsics
        self._clock_ns = clock_ns
        self.cap = capture_factory(config.device, cv2.CAP_V4L2)
        if not self.cap.isOpened():
            raise DeviceError(f"{config.device}: cannot open camera (V4L2)")
        self._set(cv2.CAP_PROP_FRAME_WIDTH, config.width, "width")
        self._set(cv2.CAP_PROP_FRAME_HEIGHT, config.height, "height")
        self._set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL, "auto exposure (manual)")
        self._set(cv2.CAP_PROP_EXPOSURE, config.exposure, "exposure")
        self._set(cv2.CAP_PROP_GAIN, config.gain, "gain")
        self._set(cv2.CAP_PROP_BUFFERSIZE, 1, "buffer size", required=False)
        if (config.width, config.height) != (intrinsics.width, intrinsics.height):
            raise DeviceError(
                f"{config.device}: capture size {config.width}x{config.height} differs from the calibration's "
                f"{intrinsics.width}x{intrinsics.height}"
            )

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    def _set(self, prop: int, value: float, name: str, required: bool = True) -> None:
        ok = bool(self.cap.set(prop, value))
        got = float(self.cap.get(prop))
        if ok and abs(got - value) <= max(1e-6, 1e-3 * abs(value)):
            return
        verb = "reports" if ok else "refused it and reports"
        msg = f"{self.config.device}: {name} set to {value}, the driver {verb} {got}"
        if required:
            raise DeviceError(msg)
        log.warning("%s (not required)", msg)

    def set_exposure(self, exposure: float) -> None:
        self._set(cv2.CAP_PROP_EXPOSURE, exposure, "exposure")

    def capture(self) -> CameraFrame:
        """A fresh still (the queued frames flushed first)."""
        for _ in range(self.config.flush_frames):
            if not self.cap.grab():
                raise DeviceError(f"{self.config.device}: grab failed (unplugged?)")
        ok, image = self.cap.read()
        t = self._clock_ns()
        if not ok or image is None:
            raise DeviceError(f"{self.config.device}: read failed (unplugged?)")
        if image.shape[:2] != (self._intrinsics.height, self._intrinsics.width):
            raise DeviceError(f"{self.config.device}: frame {image.shape[1]}x{image.shape[0]} of unexpected size")
        return CameraFrame(t, image, float(self.cap.get(cv2.CAP_PROP_EXPOSURE)))

    def close(self) -> None:
        self.cap.release()
