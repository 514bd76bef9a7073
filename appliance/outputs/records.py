"""What a log holds of an estimate: :func:`write_estimate_records` writes it into the logs of the
session, ``viper replay`` and ``viper demo`` (LocationFix, the full JSON record, the region and the
estimate as GeoJSON, the world -> skyline-grid transform, the lower posterior as a Foxglove Grid, the
skyline rendered at the estimate).  The files that open elsewhere are :mod:`appliance.outputs.files`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.estimator.exact import EYE_SIGMA_M
from appliance.locating.position import Position, altitude_m, truth_error_m
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook
from appliance.outputs.features import estimate_feature, region_feature, rendered_skyline
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase


def region_features(db: SkylineDatabase, pos: Position) -> list[dict[str, Any]]:
    """The log's ``/region``: the region (polygons of its cells, lon/lat in the body's geographic
    CRS) and the estimate (a point), the same features as
    :func:`appliance.outputs.files.write_region_geojson` and
    :func:`appliance.outputs.files.write_points_geojson` write."""
    return [region_feature(db, pos), estimate_feature(pos)]


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


def skyline_payload(sky: Skyline) -> dict[str, Any]:
    """A skyline as the log's ``viper.Skyline`` JSON message."""
    return {"azimuth_deg": sky.azimuth_deg, "elevation_deg": sky.elevation_deg}


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
        err = truth_error_m(db, pos, truth)
        rec["error_m"] = err
        rec["truth_lat"], rec["truth_lon"] = truth
    return EstimateRecord(rec, err)


def write_estimate_records(log: Logbook, time_ns: int, db: SkylineDatabase, pos: Position, skyline: Skyline,
                           truth: tuple[float, float] | None) -> EstimateRecord:
    """The estimate into ``log``: LocationFix, the pose at the origin of ``world`` with its covariance
    (PoseWithCovarianceStamped in a ROS 2 log), full JSON record, region (GeoJSON), world -> skyline-grid
    (FrameTransform), lower posterior (Grid) and the skyline rendered at the estimate; returns the
    record with its error against ``truth``."""
    rec = estimate_record(db, pos, skyline, truth)
    log.write_proto(t.ESTIMATE_FIX, estimate_fix(db, pos, time_ns, "estimate"), time_ns)
    log.write_pose(t.ESTIMATE_POSE, time_ns, "world", (0.0, 0.0, 0.0), covariance_enu_m2(pos))
    log.write_json(t.ESTIMATE_RECORD, "viper.Estimate", rec.record, time_ns)
    log.write_proto(t.REGION, m.geojson(region_features(db, pos)), time_ns)
    log.write_proto(t.TF, posterior_transform(db, pos, time_ns), time_ns)
    log.write_proto(t.POSTERIOR, posterior_grid(db, pos, time_ns), time_ns)
    log.write_json(t.SKYLINE_RENDERED, "viper.Skyline", skyline_payload(rendered_skyline(db, pos)), time_ns)
    log.flush()
    return rec


def estimate_fix(db: SkylineDatabase, pos: Position, time_ns: int, frame_id: str) -> m.LocationFix:
    """The estimate as a LocationFix: the map's altitude plus the eye's height, and the covariance
    (east, north from the estimate; up: the map's height error under the camera)."""
    return m.location_fix(time_ns, pos.lat, pos.lon, altitude_m(db, pos), frame_id=frame_id,
                          covariance_enu_m2=covariance_enu_m2(pos))


def covariance_enu_m2(pos: Position) -> np.ndarray | None:
    """The estimate's covariance (3 x 3, m^2) in east, north, up: east and north from the estimate, up the
    map's height error under the camera; None when the estimate has none."""
    cov = pos.result.covariance_m2
    if cov is None:
        return None
    enu = np.zeros((3, 3))
    enu[:2, :2] = cov
    enu[2, 2] = EYE_SIGMA_M**2
    return enu
