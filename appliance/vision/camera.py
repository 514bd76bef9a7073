"""Camera model: pixel <-> (azimuth, elevation) for a posed pinhole camera with plumb_bob distortion.

Frames.  World: local east-north-up (ENU) at the camera.  Camera: OpenCV's (x right, y down,
z forward along the optical axis).  The pose is three angles, in degrees:

- ``yaw_deg``: azimuth of the optical axis, clockwise from true north (stage angle plus heading);
- ``pitch_deg``: elevation of the optical axis above the local horizontal (nose up is positive);
- ``roll_deg``: rotation of the camera about its optical axis, positive when the right-hand side
  of the image goes down (as an inclinometer on the camera's right side reports it).

The camera is first yawed, then pitched about its own x axis, then rolled about its own z axis.
For a levelled camera (pitch = roll = 0) with no distortion, a pixel ``dp`` rows above the
principal point has elevation ``atan(dp / fy)``; the pose corrects residual tilt rather than
assuming it away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.vision.intrinsics import CameraIntrinsics

UNDISTORT_ITERATIONS = 40  # OpenCV's default of 5 leaves ~0.01 px at the corners of a wide lens


@dataclass(frozen=True)
class CameraPose:
    """Orientation of the camera (degrees; see the module docstring for the conventions)."""

    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0


def world_from_camera(pose: CameraPose) -> np.ndarray:
    """3x3 rotation taking camera-frame vectors (x right, y down, z forward) to ENU."""
    psi, theta, phi = (math.radians(a) for a in (pose.yaw_deg, pose.pitch_deg, pose.roll_deg))
    forward = np.array([math.sin(psi), math.cos(psi), 0.0])
    right = np.array([math.cos(psi), -math.sin(psi), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    forward, up = (
        math.cos(theta) * forward + math.sin(theta) * up,
        -math.sin(theta) * forward + math.cos(theta) * up,
    )
    right, up = math.cos(phi) * right - math.sin(phi) * up, math.sin(phi) * right + math.cos(phi) * up
    return np.column_stack([right, -up, forward])


def pose_from_world_from_camera(rotation: np.ndarray) -> CameraPose:
    """The (yaw, pitch, roll) of a camera-to-ENU rotation matrix; the inverse of :func:`world_from_camera`."""
    m = np.asarray(rotation, dtype=np.float64)
    right, forward = m[:, 0], m[:, 2]
    yaw = math.atan2(forward[0], forward[1])
    pitch = math.asin(max(-1.0, min(1.0, float(forward[2]))))
    right0 = np.array([math.cos(yaw), -math.sin(yaw), 0.0])
    up0 = -math.sin(pitch) * np.array([math.sin(yaw), math.cos(yaw), 0.0]) + math.cos(pitch) * np.array([0, 0, 1.0])
    roll = math.atan2(-float(right @ up0), float(right @ right0))
    return CameraPose(math.degrees(yaw) % 360.0, math.degrees(pitch), math.degrees(roll))


def _has_distortion(intrinsics: CameraIntrinsics) -> bool:
    return any(d != 0.0 for d in intrinsics.distortion)


def pixels_to_rays(intrinsics: CameraIntrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit rays in the camera frame (shape ``u.shape + (3,)``) through pixels (u = column, v = row)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    shape = np.broadcast_shapes(u.shape, v.shape)
    u, v = np.broadcast_to(u, shape).ravel(), np.broadcast_to(v, shape).ravel()
    if _has_distortion(intrinsics):
        pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, UNDISTORT_ITERATIONS, 1e-10)
        norm = cv2.undistortPoints(
            pts, intrinsics.matrix, intrinsics.dist_coeffs, R=None, P=None, criteria=criteria
        ).reshape(-1, 2)
        x, y = norm[:, 0], norm[:, 1]
    else:
        x = (u - intrinsics.cx) / intrinsics.fx
        y = (v - intrinsics.cy) / intrinsics.fy
    rays = np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float64)
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    return rays.reshape(shape + (3,))


def rays_to_pixels(intrinsics: CameraIntrinsics, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (u, v) of camera-frame rays (``(..., 3)``); NaN for rays behind the camera."""
    rays = np.asarray(rays, dtype=np.float64)
    shape = rays.shape[:-1]
    r = rays.reshape(-1, 3)
    behind = r[:, 2] <= 1e-9
    z = np.where(behind, 1.0, r[:, 2])
    if _has_distortion(intrinsics):
        obj = np.stack([r[:, 0] / z, r[:, 1] / z, np.ones_like(z)], axis=-1).reshape(-1, 1, 3)
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.dist_coeffs)
        img = img.reshape(-1, 2)
        u, v = img[:, 0].copy(), img[:, 1].copy()
    else:
        u = intrinsics.fx * r[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * r[:, 1] / z + intrinsics.cy
    u[behind] = np.nan
    v[behind] = np.nan
    return u.reshape(shape), v.reshape(shape)


def directions_to_enu(azimuth_deg: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    """Unit ENU vectors (``(..., 3)``) of directions given as azimuth/elevation in degrees."""
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    el = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    c = np.cos(el)
    return np.stack(np.broadcast_arrays(c * np.sin(az), c * np.cos(az), np.sin(el)), axis=-1)


def enu_to_directions(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth_deg in [0, 360), elevation_deg) of ENU vectors (``(..., 3)``)."""
    e, n, up = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    az = np.mod(np.degrees(np.arctan2(e, n)), 360.0)
    el = np.degrees(np.arctan2(up, np.hypot(e, n)))
    return az, el


def pixels_to_directions(
    intrinsics: CameraIntrinsics, pose: CameraPose, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth_deg, elevation_deg) of the scene seen at pixels (u = column, v = row)."""
    rays = pixels_to_rays(intrinsics, u, v)
    return enu_to_directions(rays @ world_from_camera(pose).T)


def directions_to_pixels(
    intrinsics: CameraIntrinsics, pose: CameraPose, azimuth_deg: np.ndarray, elevation_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (u, v) where directions (degrees) are imaged; NaN for directions behind the camera."""
    world = directions_to_enu(azimuth_deg, elevation_deg)
    return rays_to_pixels(intrinsics, world @ world_from_camera(pose))
