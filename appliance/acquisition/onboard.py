"""The onboard estimate: tagged frames -> panorama -> skyline -> position.

Stitching uses the tags, not image features: every panorama pixel is a direction (azimuth,
elevation); each frame's pose (yaw = true heading of the optical axis, pitch and roll from the
inclinometers) says where that direction falls in the frame; frames are blended with weights that
fall to zero at their edges.  The estimator is any object with the :class:`PositionEstimator`
interface; :class:`GridSearchEstimator` is a small exhaustive search over a region (rendering the
DEM's skyline at each candidate) that stands in where no faster estimator is given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from appliance.acquisition.procedures import TaggedFrame
from appliance.errors import EstimationError, InputError
from appliance.skyline import Skyline
from appliance.vision.camera import CameraPose, directions_to_pixels
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection


def stitch_frames(
    frames: Sequence[TaggedFrame], intrinsics: CameraIntrinsics, height_px: int | None = None
) -> Panorama:
    """A full-circle cylindrical panorama (azimuth 0 = true north at column 0) from tagged frames."""
    usable = [f for f in frames if f.heading_deg is not None]
    if not usable:
        raise InputError("stitch: no frame has a heading (compass failed?); cannot place frames")
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
    for f in usable:
        pose = CameraPose(float(f.heading_deg or 0.0), float(f.pitch_deg or 0.0), float(f.roll_deg or 0.0))
        u, v = directions_to_pixels(intrinsics, pose, az_grid.ravel(), el_grid.ravel())
        u = u.reshape(height, width).astype(np.float32)
        v = v.reshape(height, width).astype(np.float32)
        inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= intrinsics.width - 1)
        inside &= (v >= 0) & (v <= intrinsics.height - 1)
        if not inside.any():
            continue
        u_safe = np.where(inside, u, -1).astype(np.float32)
        v_safe = np.where(inside, v, -1).astype(np.float32)
        img = cv2.remap(f.frame.image, u_safe, v_safe, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        wu = np.minimum(u_safe, intrinsics.width - 1 - u_safe) / (intrinsics.width / 2)
        w = np.where(inside, np.clip(wu, 1e-3, 1.0), 0.0)
        acc += img.astype(np.float64) * w[..., None]
        wsum += w
    covered = wsum > 0
    image = np.zeros((height, width, 3), np.uint8)
    image[covered] = np.clip(acc[covered] / wsum[covered][:, None] + 0.5, 0, 255).astype(np.uint8)
    return Panorama(image, Projection.CYLINDRICAL, px_per_rad, 0.0, horizon_row, True)


@dataclass(frozen=True)
class EstimateResult:
    """Position estimate; ``posterior`` over ``grid_lat``/``grid_lon`` (rows south->north) if any."""

    lat_deg: float
    lon_deg: float
    sigma_m: float
    heading_offset_deg: float
    rms_deg: float
    posterior: np.ndarray | None = None
    grid_lat: np.ndarray | None = None
    grid_lon: np.ndarray | None = None
    cell_m: float | None = None
    rendered: Skyline | None = None


class PositionEstimator(Protocol):
    def estimate(self, skyline: Skyline) -> EstimateResult: ...


def skyline_rms_deg(
    observed: Skyline, rendered_az_deg: np.ndarray, rendered_el_deg: np.ndarray, offset_deg: float
) -> float:
    """RMS difference (deg) of the observed skyline against a rendered one shifted by ``offset_deg``."""
    ref = np.interp((observed.azimuth_deg + offset_deg) % 360.0, rendered_az_deg, rendered_el_deg, period=360.0)
    diff = observed.elevation_deg - ref
    ok = np.isfinite(diff)
    if ok.sum() < 3:
        return math.inf
    return float(np.sqrt(np.mean(diff[ok] ** 2)))


class GridSearchEstimator:
    """Exhaustive search over a square region; heading searched within +-``heading_tolerance_deg``.

    ``posterior`` is proportional to exp(-rms^2 / (2 sigma^2)) with sigma = ``sigma_deg``.
    """

    def __init__(
        self,
        dem: Any,
        center_lat: float,
        center_lon: float,
        radius_m: float,
        step_m: float,
        height_m: float = 1.5,
        heading_tolerance_deg: float = 4.0,
        heading_step_deg: float = 0.5,
        sigma_deg: float = 0.3,
    ) -> None:
        if not (radius_m > 0 and step_m > 0):
            raise EstimationError(f"grid search: radius and step must be positive, got {radius_m}, {step_m}")
        self.dem = dem
        self.center = (center_lat, center_lon)
        self.radius_m, self.step_m = radius_m, step_m
        self.height_m = height_m
        self.offsets = np.arange(-heading_tolerance_deg, heading_tolerance_deg + 1e-9, heading_step_deg)
        self.sigma_deg = sigma_deg

    def region_lonlat(self) -> list[tuple[float, float]]:
        lat0, lon0 = self.center
        dlat = math.degrees(self.radius_m / 6_371_008.8)
        dlon = dlat / math.cos(math.radians(lat0))
        return [
            (lon0 - dlon, lat0 - dlat),
            (lon0 + dlon, lat0 - dlat),
            (lon0 + dlon, lat0 + dlat),
            (lon0 - dlon, lat0 + dlat),
        ]

    def estimate(self, skyline: Skyline) -> EstimateResult:
        from appliance.terrain.horizon import render_skyline

        if skyline.valid.sum() < 10:
            raise EstimationError(f"skyline has only {int(skyline.valid.sum())} valid azimuths; need 10")
        lat0, lon0 = self.center
        n = int(self.radius_m // self.step_m)
        ks = np.arange(-n, n + 1)
        dlat = math.degrees(self.step_m / 6_371_008.8)
        dlon = dlat / math.cos(math.radians(lat0))
        lats, lons = lat0 + ks * dlat, lon0 + ks * dlon
        az = np.arange(0.0, 360.0, 1.0)
        rms = np.full((ks.size, ks.size), np.inf)
        best_off = np.zeros_like(rms)
        for i, lat in enumerate(lats):
            for j, lon in enumerate(lons):
                h = render_skyline(self.dem, float(lat), float(lon), self.height_m, azimuths_deg=az)
                el = np.nan_to_num(np.asarray(h.elevation_deg, float), nan=-90.0)
                scores = [skyline_rms_deg(skyline, az, el, o) for o in self.offsets]
                k = int(np.argmin(scores))
                rms[i, j], best_off[i, j] = scores[k], self.offsets[k]
        if not np.isfinite(rms).any():
            raise EstimationError("grid search: no candidate could be compared with the skyline")
        bi, bj = (int(v) for v in np.unravel_index(int(np.argmin(rms)), rms.shape))
        post = np.exp(-0.5 * (np.where(np.isfinite(rms), rms, 1e9) ** 2 - rms[bi, bj] ** 2) / self.sigma_deg**2)
        post /= post.sum()
        yy, xx = np.meshgrid(ks * self.step_m, ks * self.step_m, indexing="ij")
        my, mx = float((post * yy).sum()), float((post * xx).sum())
        sigma = math.sqrt(float((post * ((yy - my) ** 2 + (xx - mx) ** 2)).sum()) + (self.step_m / 2) ** 2)
        best = render_skyline(self.dem, float(lats[i]), float(lons[j]), self.height_m, azimuths_deg=az)
        return EstimateResult(
            float(lats[i]),
            float(lons[j]),
            sigma,
            float(best_off[i, j]),
            float(rms[i, j]),
            post.astype(np.float32),
            lats,
            lons,
            self.step_m,
            Skyline(az, np.asarray(best.elevation_deg, float)),
        )
