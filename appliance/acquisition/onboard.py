"""The onboard estimate: tagged frames -> panorama -> skyline -> position, and its log records.

Stitching uses the tags, not image features: every panorama pixel is a direction (azimuth,
elevation); each frame's pose (yaw = true heading of the optical axis, pitch and roll from the
inclinometers) says where that direction falls in the frame; frames are blended with weights that
fall to zero at their edges.  The position comes from the skyline database with
:func:`appliance.position.locate` (the interval-valued posterior of the paper, section 4);
:func:`estimate_messages` turns it into the log's records (LocationFix, the full JSON record, the
region as GeoJSON, the lower posterior as a Grid), shared by the session and by ``viper replay``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from appliance.acquisition.procedures import TaggedFrame
from appliance.config import EstimatorConfig, SessionConfig
from appliance.errors import EstimationError, InputError
from appliance.logbook import messages as m
from appliance.logbook.summary import great_circle_m
from appliance.skyline import Skyline
from appliance.vision.camera import CameraPose, directions_to_pixels
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection

if TYPE_CHECKING:
    from appliance.position import Position
    from appliance.terrain.database import SkylineDatabase
    from appliance.terrain.dem import Dem


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


def load_session_database(cfg: SessionConfig, dem: Dem | None = None,
                          cache_dir: Path | None = None) -> SkylineDatabase | None:
    """The skyline database of ``[session] database``; on the demo map (jacksboro) without one, the
    demo's database built once in ``cache_dir``; otherwise None (the estimate is then skipped)."""
    from appliance.terrain.database import load_database

    if cfg.database is not None:
        return load_database(cfg.database, dem)
    if dem is not None and cache_dir is not None and Path(dem.source).name.startswith("jacksboro"):
        from appliance.demo import demo_database

        cache_dir.mkdir(parents=True, exist_ok=True)
        return demo_database(dem, cache_dir)
    return None


def locate_skyline(db: SkylineDatabase, skyline: Skyline, cfg: EstimatorConfig, source: str = "") -> Position:
    """The position of ``skyline`` in ``db``; refuses a skyline with too few valid azimuths."""
    from appliance.position import locate

    if skyline.valid_fraction < cfg.min_valid_fraction:
        raise EstimationError(
            f"skyline has {skyline.valid_fraction:.0%} valid azimuths, below {cfg.min_valid_fraction:.0%}"
        )
    return locate(db, skyline, cfg.sigma_deg, cfg.heading_tolerance_deg, source=source,
                  occlusion_weight=cfg.occlusion_weight, map_sigma_m=cfg.map_vertical_sigma_m)


def mask_stage_angles(skyline: Skyline, platform_heading_deg: float,
                      stage_ranges_deg: Sequence[tuple[float, float]]) -> Skyline:
    """The skyline with the azimuths that the platform's own body hides removed: each range is in
    stage angles (deg, from..to clockwise), placed on true azimuths by the platform's heading."""
    if not stage_ranges_deg:
        return skyline
    rel = np.mod(skyline.azimuth_deg - platform_heading_deg, 360.0)
    hidden = np.zeros(rel.shape, dtype=bool)
    for lo, hi in stage_ranges_deg:
        width = (hi - lo) % 360.0
        hidden |= np.mod(rel - lo, 360.0) <= width
    el = np.where(hidden, np.nan, skyline.elevation_deg)
    conf = None if skyline.confidence is None else np.where(hidden, 0.0, skyline.confidence)
    return Skyline(skyline.azimuth_deg, el, conf)


def region_features(db: SkylineDatabase, pos: Position) -> list[dict[str, Any]]:
    """The region (polygons of its cells, lon/lat) and the estimate (a point) as GeoJSON features."""
    from rasterio import features

    mask = np.zeros(db.grid.n_nodes, dtype=np.uint8)
    mask[pos.result.region_nodes] = 1
    polys = []
    for geom, value in features.shapes(mask.reshape(db.grid.n_rows, db.grid.n_cols), transform=db.grid.transform):
        if value != 1:
            continue
        rings = []
        for ring in geom["coordinates"]:
            xy = np.asarray(ring, float)
            lon, lat = db.grid.xy_to_lonlat(xy[:, 0], xy[:, 1])
            rings.append([[round(float(a), 7), round(float(b), 7)] for a, b in zip(lon, lat, strict=True)])
        polys.append(rings)
    region = {
        "type": "Feature",
        "properties": {"name": "region", "area_m2": pos.result.region_area_m2,
                       "lower": pos.result.lower, "upper": pos.result.upper},
        "geometry": {"type": "MultiPolygon", "coordinates": polys},
    }
    return [region, m.point_feature(pos.lon, pos.lat, "estimate")]


def posterior_grid(db: SkylineDatabase, pos: Position, time_ns: int, floor_decades: float = 20.0) -> Any:
    """The lower posterior (log10, floored ``floor_decades`` below its peak) as a Foxglove Grid.

    Row 0 is the grid's southernmost row; cells are ``dx_m`` x ``dy_m`` metres in the frame
    ``skyline-grid`` whose origin is the south-west corner of the south-west node's cell (placed in
    ``world`` by :func:`posterior_transform`).
    """
    g = db.grid
    lower = np.asarray(pos.result.log_lower_map, float).reshape(g.n_rows, g.n_cols) / math.log(10.0)
    top = float(np.nanmax(np.where(np.isfinite(lower), lower, -np.inf)))
    floored = np.where(np.isfinite(lower), np.maximum(lower, top - floor_decades), top - floor_decades)
    return m.grid(time_ns, floored[::-1], (g.dx_m, g.dy_m), (0.0, 0.0), frame_id="skyline-grid",
                  field_name="log10_lower_posterior")


def posterior_transform(db: SkylineDatabase, pos: Position, time_ns: int) -> Any:
    """world -> skyline-grid, with the world's origin at the estimate: the grid's south-west corner
    rotated from grid into true east/north by the grid convergence at the estimate's node."""
    g = db.grid
    x0, y0 = g.rc_to_xy(g.n_rows - 0.5, -0.5)
    gamma = float(db.convergence_deg[pos.result.node])
    dx_m = (float(x0) - pos.x) * g.dx_m / g.dx
    dy_m = (float(y0) - pos.y) * g.dy_m / g.dy
    c, s = math.cos(math.radians(gamma)), math.sin(math.radians(gamma))
    # grid north at true azimuth gamma: grid +x = (cos g, -sin g), grid +y = (sin g, cos g) in (east, north)
    east, north = c * dx_m + s * dy_m, -s * dx_m + c * dy_m
    return m.grid_transform(time_ns, east, north, gamma)


@dataclass(frozen=True)
class EstimateRecord:
    """What the log holds of one estimate: the JSON record and the error against the truth (m)."""

    record: dict[str, Any]
    error_m: float | None


def estimate_record(db: SkylineDatabase, pos: Position, skyline: Skyline,
                    truth: tuple[float, float] | None) -> EstimateRecord:
    """``Position.to_json`` plus the skyline's valid fraction and the error against ``truth`` (lat, lon)."""
    rec = pos.to_json(db, truth)
    rec["valid_fraction"] = skyline.valid_fraction
    err = None
    if truth is not None:
        err = great_circle_m(pos.lat, pos.lon, truth[0], truth[1])
        rec["error_m"] = err
        rec["truth_lat"], rec["truth_lon"] = truth
    return EstimateRecord(rec, err)


def rendered_skyline(db: SkylineDatabase, pos: Position) -> Skyline:
    """The database's skyline at the estimate's node (azimuths clockwise from true north)."""
    return Skyline(np.asarray(db.azimuths_deg, float), np.asarray(db.skylines_deg(pos.result.node), float))
