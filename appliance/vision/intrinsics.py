"""Camera intrinsics: pinhole with OpenCV's plumb_bob distortion, stored as a TOML calibration file.

File layout (written by ``viper calibrate camera``, read by the vision chain and the camera driver)::

    [camera]
    width = 640
    height = 480
    fx = 525.0
    fy = 525.0
    cx = 319.5
    cy = 239.5
    distortion = [k1, k2, p1, p2, k3]   # plumb_bob
    reprojection_error_px = 0.21       # optional, from the calibration
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.atomic import describe_os_error, write_text_atomic
from appliance.config import from_mapping
from appliance.errors import ConfigError
from appliance.inputs import MAX_CONFIG_BYTES, NestingError, check_nesting, read_text_bounded

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass(frozen=True)
class CameraIntrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    reprojection_error_px: float | None = None

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"camera: image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.fx)))

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
        """An undistorted camera with square pixels and the given horizontal field of view."""
        f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def load_intrinsics(path: str | Path) -> CameraIntrinsics:
    p = Path(path)
    try:
        text = read_text_bounded(p, MAX_CONFIG_BYTES, "calibration file", ConfigError)
        check_nesting(text)
        data = tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(f"{p}: calibration file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, NestingError) as exc:
        raise ConfigError(f"{p}: not a valid TOML calibration file: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the calibration file: {describe_os_error(exc)}") from None
    if "camera" not in data:
        raise ConfigError(f"{p}: no [camera] table")
    try:
        return from_mapping(CameraIntrinsics, data["camera"], prefix="camera")
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def save_intrinsics(intrinsics: CameraIntrinsics, path: str | Path) -> None:
    """Write the calibration file atomically (write a temporary file, then rename)."""
    p = Path(path)
    lines = [
        "[camera]",
        f"width = {intrinsics.width}",
        f"height = {intrinsics.height}",
        f"fx = {intrinsics.fx!r}",
        f"fy = {intrinsics.fy!r}",
        f"cx = {intrinsics.cx!r}",
        f"cy = {intrinsics.cy!r}",
        "distortion = [" + ", ".join(repr(float(d)) for d in intrinsics.distortion) + "]",
    ]
    if intrinsics.reprojection_error_px is not None:
        lines.append(f"reprojection_error_px = {intrinsics.reprojection_error_px!r}")
    write_text_atomic(p, "\n".join(lines) + "\n")
