"""Stitching by pose: images whose orientation is known become one full-circle panorama.

No image features are used: every panorama pixel is a direction (azimuth clockwise from true
north, elevation); each image's pose (yaw = true azimuth of the optical axis, pitch and roll from
the inclinometers) says where that direction falls in the image; images are blended with weights
that fall to zero at their side edges.  Where neighbouring images overlap, their disagreement is
kept as the panorama's ``motion`` (:mod:`appliance.vision.temporal`: a cloud drifts between frames,
terrain does not).  (:mod:`appliance.vision.stitching` registers images by
their content instead, when the poses are only approximate.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.errors import InputError
from appliance.vision.camera import CameraPose, directions_to_pixels
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection
from appliance.vision.temporal import frame_disagreement, luminance


@dataclass(frozen=True)
class PosedImage:
    """One HxWx3 uint8 BGR image and the camera's pose when it was taken."""

    image: np.ndarray
    pose: CameraPose


def stitch_posed(shots: Sequence[PosedImage], intrinsics: CameraIntrinsics,
                 height_px: int | None = None) -> Panorama:
    """A full-circle cylindrical panorama (azimuth 0 = true north at column 0) of ``shots``; the
    columns that they leave less than half covered are its ``empty_columns``."""
    if not shots:
        raise InputError("stitch: no image with a known pose")
    width = int(round(2 * math.pi * intrinsics.fx))
    px_per_rad = width / (2 * math.pi)
    height = height_px or intrinsics.height
    horizon_row = (height - 1) / 2.0
    cols = np.arange(width, dtype=np.float64)
    rows = np.arange(height, dtype=np.float64)
    az = np.degrees(cols / px_per_rad)
    el = np.degrees(np.arctan((horizon_row - rows) / px_per_rad))
    az_grid, el_grid = np.meshgrid(az, el)
    acc = np.zeros((height, width, 3), np.float64)
    wsum = np.zeros((height, width), np.float64)
    warped: list[tuple[np.ndarray, np.ndarray]] = []
    for shot in shots:
        u, v = directions_to_pixels(intrinsics, shot.pose, az_grid.ravel(), el_grid.ravel())
        u = u.reshape(height, width).astype(np.float32)
        v = v.reshape(height, width).astype(np.float32)
        inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= intrinsics.width - 1)
        inside &= (v >= 0) & (v <= intrinsics.height - 1)
        if not inside.any():
            continue
        u_safe = np.where(inside, u, -1).astype(np.float32)
        v_safe = np.where(inside, v, -1).astype(np.float32)
        img = cv2.remap(shot.image, u_safe, v_safe, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        warped.append((luminance(img), inside))
        wu = np.minimum(u_safe, intrinsics.width - 1 - u_safe) / (intrinsics.width / 2)
        w = np.where(inside, np.clip(wu, 1e-3, 1.0), 0.0)
        acc += img.astype(np.float64) * w[..., None]
        wsum += w
    covered = wsum > 0
    image = np.zeros((height, width, 3), np.uint8)
    image[covered] = np.clip(acc[covered] / wsum[covered][:, None] + 0.5, 0, 255).astype(np.uint8)
    # a column less than half covered (a frame missing from the turn) holds no skyline to find
    empty = covered.mean(axis=0) < 0.5
    motion = frame_disagreement(warped) if len(warped) > 1 else None
    return Panorama(image, Projection.CYLINDRICAL, px_per_rad, 0.0, horizon_row, True,
                    empty if empty.any() else None, motion)
