"""Camera pose (and optionally focal length and radial distortion) from ground-control points.

A ground-control point is a pixel of the photo whose map position is known.  The map positions are
turned into local east-north-up (ENU) metres at the camera (exactly, through the ellipsoid: a
projected CRS's grid north is not true north), and ``cv2.calibrateCamera`` on that single view of
non-planar points fits the rotation and the camera centre; the intrinsics listed in ``refine``
(``f``: one focal length for both axes, ``k1``, ``k2``) are fitted with them, the others are kept.
The rotation is reported as the appliance's orientation (yaw = true azimuth of the optical axis,
pitch up positive, roll right side down positive; see :mod:`appliance.vision.camera`).

Points CSV: a header, then one point a row.  Pixel columns ``u_px,v_px`` (aliases ``x_img,y_img``;
the centre of the top-left pixel is (0, 0), v down), and either ``lat_deg,lon_deg,height_m``
(WGS84, ellipsoidal height) or ``x,y,z`` (aliases ``x_world,y_world,z_world``) in the CRS given by
the caller.  Optional: ``name``, and ``use`` (alias ``lstsq_IO``): 0 leaves the point out.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pyproj import CRS, Transformer
from viper_calibration.csvtable import read_input

from appliance.errors import CalibrationError, InputError
from appliance.vision.camera import CameraPose, pose_from_world_from_camera
from appliance.vision.intrinsics import CameraIntrinsics

REFINABLE = ("f", "k1", "k2")
MIN_POINTS = 6  # 6 pose parameters; each point gives two equations, but fewer than 6 are fragile
_ALIASES = {
    "u_px": ("u_px", "x_img", "u"),
    "v_px": ("v_px", "y_img", "v"),
    "lat_deg": ("lat_deg", "lat", "latitude"),
    "lon_deg": ("lon_deg", "lon", "longitude"),
    "height_m": ("height_m", "height", "h"),
    "x": ("x", "x_world", "easting"),
    "y": ("y", "y_world", "northing"),
    "z": ("z", "z_world"),
    "use": ("use", "lstsq_io"),
    "name": ("name", "point"),
}


@dataclass(frozen=True)
class ControlPoints:
    """Ground-control points: names, pixels (N x 2) and WGS84 geodetic positions (N x 3: lat, lon, h)."""

    names: tuple[str, ...]
    pixels: np.ndarray
    geodetic: np.ndarray


@dataclass(frozen=True)
class PoseFit:
    """The fitted camera: intrinsics, orientation, centre (WGS84 lat, lon; height in the points' vertical
    datum) and residuals."""

    intrinsics: CameraIntrinsics
    pose: CameraPose
    centre_geodetic: tuple[float, float, float]
    names: tuple[str, ...]
    residual_px: np.ndarray  # per point, pixels
    refined: tuple[str, ...]

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.residual_px**2)))

    def as_dict(self) -> dict[str, Any]:
        k = self.intrinsics
        return {
            "yaw_deg": self.pose.yaw_deg,
            "pitch_deg": self.pose.pitch_deg,
            "roll_deg": self.pose.roll_deg,
            "camera_lat_deg": self.centre_geodetic[0],
            "camera_lon_deg": self.centre_geodetic[1],
            "camera_height_m": self.centre_geodetic[2],
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "distortion": list(k.distortion),
            "refined": list(self.refined),
            "points": len(self.names),
            "rms_px": self.rms_px,
            "max_px": float(np.max(self.residual_px)),
            "residual_px": {n: float(r) for n, r in zip(self.names, self.residual_px)},
        }


def _column(header: list[str], key: str) -> int | None:
    lowered = [h.strip().lower() for h in header]
    for alias in _ALIASES[key]:
        if alias in lowered:
            return lowered.index(alias)
    return None


def read_control_points(path: str | Path, crs: str | None = None) -> ControlPoints:
    """Read the points CSV (see the module docstring); map x, y, z need ``crs`` (e.g. ``EPSG:32632``)."""
    source = str(path)
    try:
        text = read_input(path).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{source}: not UTF-8 text: {exc}") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    if len(rows) < 2:
        raise InputError(f"{source}: expected a header and at least one point")
    header, body = rows[0], rows[1:]
    cols = {key: _column(header, key) for key in _ALIASES}
    if cols["u_px"] is None or cols["v_px"] is None:
        raise InputError(f"{source}: no pixel columns (u_px,v_px or x_img,y_img) in the header {','.join(header)!r}")
    geodetic = all(cols[k] is not None for k in ("lat_deg", "lon_deg", "height_m"))
    mapped = all(cols[k] is not None for k in ("x", "y", "z"))
    if not (geodetic or mapped):
        raise InputError(f"{source}: need lat_deg,lon_deg,height_m or x,y,z columns, got {','.join(header)!r}")
    if not geodetic and crs is None:
        raise InputError(f"{source}: map coordinates x,y,z need their CRS (--crs EPSG:...)")
    keys = ("lat_deg", "lon_deg", "height_m") if geodetic else ("x", "y", "z")
    names: list[str] = []
    pix: list[tuple[float, float]] = []
    world: list[tuple[float, float, float]] = []
    for i, row in enumerate(body, start=2):

        def cell(key: str, row: list[str] = row, line: int = i) -> float:
            idx = cols[key]
            assert idx is not None
            try:
                value = float(row[idx])
            except (IndexError, ValueError):
                raise InputError(f"{source}: line {line}: {header[idx].strip()} is not a number") from None
            if not math.isfinite(value):
                raise InputError(f"{source}: line {line}: {header[idx].strip()} is not finite")
            return value

        if cols["use"] is not None and cell("use") == 0:
            continue
        name_idx = cols["name"]
        names.append(row[name_idx].strip() if name_idx is not None and name_idx < len(row) else f"line{i}")
        pix.append((cell("u_px"), cell("v_px")))
        world.append((cell(keys[0]), cell(keys[1]), cell(keys[2])))
    if len(names) < MIN_POINTS:
        raise InputError(f"{source}: {len(names)} usable points, at least {MIN_POINTS} are needed")
    arr = np.asarray(world, dtype=np.float64)
    if not geodetic:
        try:
            to_geo = Transformer.from_crs(CRS.from_user_input(crs), CRS.from_epsg(4979), always_xy=True)
        except Exception as exc:  # pyproj raises its own CRSError
            raise InputError(f"--crs {crs!r}: not a known CRS: {exc}") from None
        lon, lat, h = to_geo.transform(arr[:, 0], arr[:, 1], arr[:, 2])
        arr = np.column_stack([lat, lon, h])
    return ControlPoints(tuple(names), np.asarray(pix, dtype=np.float64), arr)


# ----------------------------------------------------------------------------- geodesy (WGS84)

_A = 6378137.0
_E2 = 6.69437999014e-3


def geodetic_to_ecef(geodetic: np.ndarray) -> np.ndarray:
    lat, lon, h = (np.radians(geodetic[..., 0]), np.radians(geodetic[..., 1]), geodetic[..., 2])
    n = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack(
        [(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon), (n * (1 - _E2) + h) * np.sin(lat)],
        axis=-1,
    )


def _enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rows: the east, north and up unit vectors (ECEF) at a geodetic position."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    return np.array(
        [
            [-math.sin(lo), math.cos(lo), 0.0],
            [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
            [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)],
        ]
    )


def geodetic_to_enu(geodetic: np.ndarray, origin: Sequence[float]) -> np.ndarray:
    """ENU metres of WGS84 positions (N x 3: lat, lon, h) relative to ``origin`` (lat, lon, h)."""
    o = np.asarray(origin, dtype=np.float64)
    return np.asarray((geodetic_to_ecef(geodetic) - geodetic_to_ecef(o)) @ _enu_basis(o[0], o[1]).T)


def enu_to_geodetic(enu: np.ndarray, origin: Sequence[float]) -> tuple[float, float, float]:
    o = np.asarray(origin, dtype=np.float64)
    ecef = geodetic_to_ecef(o) + np.asarray(enu) @ _enu_basis(o[0], o[1])
    to_geo = Transformer.from_crs(CRS.from_epsg(4978), CRS.from_epsg(4979), always_xy=True)
    lon, lat, h = to_geo.transform(ecef[0], ecef[1], ecef[2])
    return float(lat), float(lon), float(h)


# ----------------------------------------------------------------------------- the fit


def _flags(refine: Sequence[str]) -> int:
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_ZERO_TANGENT_DIST
    flags |= cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_ASPECT_RATIO
    if "f" not in refine:
        flags |= cv2.CALIB_FIX_FOCAL_LENGTH
    if "k1" not in refine:
        flags |= cv2.CALIB_FIX_K1
    if "k2" not in refine:
        flags |= cv2.CALIB_FIX_K2
    return flags


def _calibrate_once(
    points: ControlPoints, intr: CameraIntrinsics, origin: Sequence[float], refine: Sequence[str]
) -> tuple[CameraIntrinsics, np.ndarray, np.ndarray, np.ndarray]:
    obj = geodetic_to_enu(points.geodetic, origin).astype(np.float32)
    img = points.pixels.astype(np.float32)
    k = intr.matrix.copy()
    dist = intr.dist_coeffs.copy()
    try:
        _, k, dist, rvecs, tvecs = cv2.calibrateCamera(
            [obj], [img], (intr.width, intr.height), k, dist, flags=_flags(refine)
        )
    except cv2.error as exc:
        raise CalibrationError(f"pose fit failed: {exc.err}") from None
    rvec, tvec = np.asarray(rvecs[0]).ravel(), np.asarray(tvecs[0]).ravel()
    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    fitted = replace(
        intr,
        fx=float(k[0, 0]),
        fy=float(k[1, 1]),
        distortion=(float(dist[0]), float(dist[1]), float(dist[2]), float(dist[3]), float(dist[4])),
    )
    proj, _ = cv2.projectPoints(obj.astype(np.float64), rvec, tvec, fitted.matrix, fitted.dist_coeffs)
    residual = np.linalg.norm(proj.reshape(-1, 2) - points.pixels, axis=1)
    return fitted, rvec, tvec, residual


def fit_pose(
    points: ControlPoints,
    intrinsics: CameraIntrinsics,
    camera_guess: Sequence[float] | None = None,
    refine: Sequence[str] = (),
) -> PoseFit:
    """Fit the orientation and centre (and the ``refine`` intrinsics) to the control points.

    ``camera_guess`` (lat, lon, h) only places the local frame; the centre is fitted.  Without it
    the points' centroid does, and the frame is moved to the fitted centre and the fit repeated.
    """
    bad = [r for r in refine if r not in REFINABLE]
    if bad:
        raise InputError(f"cannot refine {', '.join(bad)}: choose among {', '.join(REFINABLE)}")
    u, v = points.pixels[:, 0], points.pixels[:, 1]
    if np.any((u < -0.5) | (u > intrinsics.width - 0.5) | (v < -0.5) | (v > intrinsics.height - 0.5)):
        raise InputError(f"control points lie outside the calibration's {intrinsics.width}x{intrinsics.height} image")
    origin: Sequence[float] = camera_guess if camera_guess is not None else points.geodetic.mean(axis=0)
    fitted, rvec, tvec, residual = _calibrate_once(points, intrinsics, origin, refine)
    for _ in range(2):
        r_cw, _ = cv2.Rodrigues(rvec)
        centre = -r_cw.T @ tvec
        origin = enu_to_geodetic(centre, origin)
        fitted, rvec, tvec, residual = _calibrate_once(points, intrinsics, origin, refine)
    r_cw, _ = cv2.Rodrigues(rvec)
    centre = enu_to_geodetic(-r_cw.T @ tvec, origin)
    if not np.all(np.isfinite(residual)):
        raise CalibrationError("pose fit diverged (non-finite reprojection)")
    pose = pose_from_world_from_camera(r_cw.T)
    return PoseFit(fitted, pose, centre, points.names, residual, tuple(refine))


def format_report(fit: PoseFit) -> str:
    k = fit.intrinsics
    worst = int(np.argmax(fit.residual_px))
    return "\n".join(
        [
            f"orientation: yaw {fit.pose.yaw_deg:.3f} deg (true azimuth), pitch {fit.pose.pitch_deg:.3f} deg,"
            f" roll {fit.pose.roll_deg:.3f} deg",
            f"camera centre: lat {fit.centre_geodetic[0]:.7f}, lon {fit.centre_geodetic[1]:.7f},"
            f" height {fit.centre_geodetic[2]:.2f} m (in the points' vertical datum)",
            f"intrinsics: fx {k.fx:.2f} fy {k.fy:.2f} cx {k.cx:.2f} cy {k.cy:.2f}"
            f" distortion [{', '.join(f'{d:.5f}' for d in k.distortion)}]"
            + (f" (refined: {', '.join(fit.refined)})" if fit.refined else ""),
            f"{len(fit.names)} points: reprojection RMS {fit.rms_px:.2f} px,"
            f" worst {fit.residual_px[worst]:.2f} px ({fit.names[worst]})",
        ]
    )
