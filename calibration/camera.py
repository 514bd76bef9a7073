"""Camera intrinsics from chessboard images (paper section 5.4).

Inner corners are found with ``cv2.findChessboardCornersSB`` and the pinhole model with OpenCV's
plumb_bob distortion (k1, k2, p1, p2, k3) is fitted by ``cv2.calibrateCamera``.  Pixel coordinates
follow OpenCV: the centre of the top-left pixel is (0, 0), x to the right, y down.  The result is a
:class:`appliance.vision.intrinsics.CameraIntrinsics` that :func:`write_camera_calibration` writes
as the ``[camera]`` table of a calibration file, keeping the rest of the file byte for byte.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from viper_calibration.config_edit import update_toml_table

from appliance.errors import CalibrationError, ConfigError, InputError
from appliance.inputs import read_image_buffer
from appliance.vision.intrinsics import CameraIntrinsics

MIN_BOARDS_FLOOR = 3  # calibrateCamera's own minimum for a 9-parameter fit from planar views
FIND_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY


@dataclass(frozen=True)
class CameraCalibration:
    """Intrinsics with the images used, the images without a board and the per-view RMS errors (px)."""

    intrinsics: CameraIntrinsics
    pattern_size: tuple[int, int]
    used: tuple[Path, ...]
    rejected: tuple[Path, ...]
    per_view_error_px: tuple[float, ...]

    @property
    def reprojection_error_px(self) -> float:
        err = self.intrinsics.reprojection_error_px
        assert err is not None
        return err

    def as_dict(self) -> dict[str, Any]:
        k = self.intrinsics
        return {
            "width": k.width,
            "height": k.height,
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "distortion": list(k.distortion),
            "reprojection_error_px": k.reprojection_error_px,
            "boards": len(self.used),
            "rejected": [str(p) for p in self.rejected],
        }


def board_object_points(pattern_size: tuple[int, int], square_size_m: float) -> np.ndarray:
    """Inner-corner coordinates on the board plane (metres, z = 0), row by row, shape (cols*rows, 3)."""
    cols, rows = pattern_size
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_size_m
    return grid


def find_board(gray: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 2) of a chessboard in an 8-bit grey image, or None if there is none."""
    found, corners = cv2.findChessboardCornersSB(gray, pattern_size, flags=FIND_FLAGS)
    if not found or corners is None:
        return None
    return np.asarray(corners, np.float32).reshape(-1, 2)


def read_grey(path: str | Path) -> np.ndarray:
    p = Path(path)
    data = np.frombuffer(read_image_buffer(p), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if image is None:
        raise InputError(f"{p}: not a readable image")
    return image


def calibrate_from_corners(
    corners: Sequence[np.ndarray],
    image_size: tuple[int, int],
    pattern_size: tuple[int, int],
    square_size_m: float,
) -> tuple[CameraIntrinsics, tuple[float, ...]]:
    """Fit K and plumb_bob distortion to corner lists; ``image_size`` is (width, height) in pixels."""
    if len(corners) < MIN_BOARDS_FLOOR:
        raise CalibrationError(f"{len(corners)} board view(s); calibration needs at least {MIN_BOARDS_FLOOR}")
    grid = board_object_points(pattern_size, square_size_m)
    object_points = [grid] * len(corners)
    image_points = [np.asarray(c, np.float32).reshape(-1, 1, 2) for c in corners]
    width, height = image_size
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, (width, height), None, None)
    dist = np.asarray(dist, np.float64).ravel()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and np.isfinite(rms)):
        raise CalibrationError(f"calibration diverged (rms {rms} px); take views at more varied angles")
    errors = []
    for obj, img, rvec, tvec in zip(object_points, image_points, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        errors.append(float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=2)))))
    try:
        intrinsics = CameraIntrinsics(
            width=width,
            height=height,
            fx=float(K[0, 0]),
            fy=float(K[1, 1]),
            cx=float(K[0, 2]),
            cy=float(K[1, 2]),
            distortion=(float(dist[0]), float(dist[1]), float(dist[2]), float(dist[3]), float(dist[4])),
            reprojection_error_px=float(rms),
        )
    except ConfigError as exc:
        raise CalibrationError(f"calibration gave an impossible camera: {exc}") from None
    return intrinsics, tuple(errors)


def calibrate_camera(
    images: Sequence[str | Path],
    pattern_size: tuple[int, int] = (9, 6),
    square_size_m: float = 0.025,
    min_boards: int = 5,
) -> CameraCalibration:
    """Find the board in every image and calibrate; refuses when fewer than ``min_boards`` are found.

    ``pattern_size`` counts inner corners (columns, rows).  All images must share one size.
    """
    if min_boards < MIN_BOARDS_FLOOR:
        raise InputError(f"min_boards must be at least {MIN_BOARDS_FLOOR}, got {min_boards}")
    if not images:
        raise InputError("no images given")
    size: tuple[int, int] | None = None
    first: Path | None = None
    used: list[Path] = []
    rejected: list[Path] = []
    corners: list[np.ndarray] = []
    for path in map(Path, images):
        grey = read_grey(path)
        this_size = (grey.shape[1], grey.shape[0])
        if size is None:
            size, first = this_size, path
        elif this_size != size:
            raise InputError(
                f"{path}: image is {this_size[0]}x{this_size[1]} but {first} is {size[0]}x{size[1]}"
            )
        found = find_board(grey, pattern_size)
        if found is None:
            rejected.append(path)
        else:
            used.append(path)
            corners.append(found)
    assert size is not None
    if len(used) < min_boards:
        cols, rows = pattern_size
        raise CalibrationError(
            f"a {cols}x{rows} board was found in {len(used)} of {len(used) + len(rejected)} image(s);"
            f" at least {min_boards} are needed"
        )
    intrinsics, errors = calibrate_from_corners(corners, size, pattern_size, square_size_m)
    return CameraCalibration(intrinsics, pattern_size, tuple(used), tuple(rejected), errors)


def format_report(result: CameraCalibration) -> str:
    k = result.intrinsics
    lines = [f"{'image':<40}  {'rms_px':>7}"]
    for path, err in zip(result.used, result.per_view_error_px, strict=True):
        lines.append(f"{str(path)[-40:]:<40}  {err:>7.3f}")
    for path in result.rejected:
        lines.append(f"{str(path)[-40:]:<40}  {'no board':>7}")
    k1, k2, p1, p2, k3 = k.distortion
    lines += [
        f"image {k.width}x{k.height}, {len(result.used)} boards of {result.pattern_size[0]}x"
        f"{result.pattern_size[1]} inner corners",
        f"focal length fx = {k.fx:.3f} px, fy = {k.fy:.3f} px, hfov {k.hfov_deg:.2f} deg",
        f"principal point cx = {k.cx:.3f} px, cy = {k.cy:.3f} px",
        f"plumb_bob k1 = {k1:.6f}, k2 = {k2:.6f}, p1 = {p1:.6f}, p2 = {p2:.6f}, k3 = {k3:.6f}",
        f"reprojection error (rms) = {result.reprojection_error_px:.4f} px",
    ]
    return "\n".join(lines)


def camera_table(intrinsics: CameraIntrinsics) -> dict[str, Any]:
    """The ``[camera]`` keys of a calibration file (as :func:`appliance.vision.intrinsics.load_intrinsics` reads)."""
    k = intrinsics
    table: dict[str, Any] = {
        "width": k.width, "height": k.height, "fx": float(k.fx), "fy": float(k.fy),
        "cx": float(k.cx), "cy": float(k.cy), "distortion": [float(d) for d in k.distortion],
    }
    if k.reprojection_error_px is not None:
        table["reprojection_error_px"] = float(k.reprojection_error_px)
    return table


def write_camera_calibration(path: str | Path, intrinsics: CameraIntrinsics) -> None:
    """Set ``[camera]`` in the TOML file ``path`` (created if absent); every other byte is kept."""
    table = camera_table(intrinsics)
    stale = () if "reprojection_error_px" in table else ("reprojection_error_px",)
    update_toml_table(path, "camera", table, must_exist=False, remove=stale)
