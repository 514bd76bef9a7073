"""An estimate's outputs: the records a log holds of it and the files that open elsewhere.

The session, ``viper replay`` and ``viper demo`` write an estimate into their logs with
:func:`write_estimate_records` (LocationFix, the full JSON record, the region as GeoJSON, the
world -> skyline-grid transform, the lower posterior as a Foxglove Grid, the skyline rendered at the
estimate); ``viper estimate --report`` and the replay report write its files (:func:`write_png`,
:func:`write_geotiff`: float32, NaN nodata; :func:`write_region_geojson`: the region's polygons only;
:func:`write_points_geojson`: the estimate and the truth); :func:`write_png` draws the picture of
:mod:`appliance.outputs.picture`.  The region becomes GeoJSON in one place,
:func:`region_polygons`; its features and their properties (:func:`region_feature`,
:func:`estimate_feature`) are the same in the log's ``/region`` and in the files.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from appliance.atomic import atomic_output, write_text_atomic
from appliance.estimator.exact import EYE_SIGMA_M
from appliance.locate.position import (
    Position,
    altitude_m,
    covariance_json,
    fix_status,
    radius_json,
    status_text,
    truth_error_m,
)
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase


def region_mask(db: SkylineDatabase, pos: Position) -> np.ndarray:
    mask = np.zeros(db.grid.n_nodes, dtype=np.uint8)
    mask[pos.result.region_nodes] = 1
    return mask.reshape(db.grid.n_rows, db.grid.n_cols)


def region_polygons(db: SkylineDatabase, pos: Position) -> list[list[list[list[float]]]]:
    """The region's cells merged into polygons: rings of [lon, lat] (WGS84 or the body's geographic CRS)."""
    from rasterio import features

    polys = []
    for geom, value in features.shapes(region_mask(db, pos), transform=db.grid.transform):
        if value != 1:
            continue
        rings = []
        for ring in geom["coordinates"]:
            xy = np.asarray(ring, float)
            lon, lat = db.grid.xy_to_lonlat(xy[:, 0], xy[:, 1])
            rings.append([[round(float(a), 7), round(float(b), 7)] for a, b in zip(lon, lat, strict=True)])
        polys.append(rings)
    return polys


def region_feature(db: SkylineDatabase, pos: Position) -> dict[str, Any]:
    """The region as one GeoJSON MultiPolygon feature (lon/lat)."""
    r = pos.result
    return {
        "type": "Feature",
        "properties": {"name": "region", "kind": "region", "area_m2": r.region_area_m2,
                       "n_cells": int(r.region_nodes.size), "lower": r.lower, "upper": r.upper},
        "geometry": {"type": "MultiPolygon", "coordinates": region_polygons(db, pos)},
    }


def estimate_feature(pos: Position) -> dict[str, Any]:
    """The estimate as one GeoJSON Point feature (lon/lat)."""
    r = pos.result
    return {
        "type": "Feature",
        "properties": {"name": "estimate", "kind": "estimate", "lower": r.lower, "upper": r.upper,
                       "heading_correction_deg": r.heading_correction_deg, "status": fix_status(pos),
                       "covariance_m2": covariance_json(r.covariance_m2),
                       "radius95_m": radius_json(r.covariance_m2)},
        "geometry": {"type": "Point", "coordinates": [float(pos.lon), float(pos.lat)]},
    }


def truth_feature(truth: tuple[float, float]) -> dict[str, Any]:
    """The truth (lat, lon) as one GeoJSON Point feature (lon/lat)."""
    return {"type": "Feature", "properties": {"name": "truth", "kind": "truth"},
            "geometry": {"type": "Point", "coordinates": [float(truth[1]), float(truth[0])]}}


def region_features(db: SkylineDatabase, pos: Position) -> list[dict[str, Any]]:
    """The log's ``/region``: the region (polygons of its cells, lon/lat in the body's geographic
    CRS) and the estimate (a point), the same features as :func:`write_region_geojson` and
    :func:`write_points_geojson` write."""
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


def rendered_skyline(db: SkylineDatabase, pos: Position) -> Skyline:
    """The database's skyline at the estimate's node (azimuths clockwise from true north)."""
    return Skyline(np.asarray(db.azimuths_deg, float), np.asarray(db.skylines_deg(pos.result.node), float))


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
    """The estimate into ``log``: LocationFix, full JSON record, region (GeoJSON), world -> skyline-grid
    (FrameTransform), lower posterior (Grid) and the skyline rendered at the estimate; returns the
    record with its error against ``truth``."""
    rec = estimate_record(db, pos, skyline, truth)
    log.write_proto(t.ESTIMATE_FIX, estimate_fix(db, pos, time_ns, "estimate"), time_ns)
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
    cov = pos.result.covariance_m2
    enu = None
    if cov is not None:
        enu = np.zeros((3, 3))
        enu[:2, :2] = cov
        enu[2, 2] = EYE_SIGMA_M**2
    return m.location_fix(time_ns, pos.lat, pos.lon, altitude_m(db, pos), frame_id=frame_id, covariance_enu_m2=enu)


def write_region_geojson(db: SkylineDatabase, pos: Position, path: str | Path) -> None:
    """One layer of polygons only: the estimate's region as a MultiPolygon (lon/lat)."""
    fc = {"type": "FeatureCollection", "features": [region_feature(db, pos)]}
    write_text_atomic(Path(path), json.dumps(fc))


def write_points_geojson(pos: Position, path: str | Path, truth: tuple[float, float] | None = None) -> None:
    """One layer of points only: the estimate, and the truth (lat, lon) where known."""
    features = [estimate_feature(pos)]
    if truth is not None:
        features.append(truth_feature(truth))
    write_text_atomic(Path(path), json.dumps({"type": "FeatureCollection", "features": features}))


def write_geotiff(db: SkylineDatabase, pos: Position, path: str | Path) -> None:
    """Two float32 bands, log10 of the lower and upper posterior of each node (its best heading); NaN is
    nodata (a posterior of zero), so no finite value, however small, is mistaken for nodata."""
    import rasterio

    p = Path(path)
    g = db.grid
    bands = np.stack([pos.result.log_lower_map, pos.result.log_upper_map]) / np.log(10.0)
    bands = np.where(np.isfinite(bands), bands, np.nan).astype(np.float32).reshape(2, g.n_rows, g.n_cols)
    with atomic_output(p) as tmp, rasterio.open(
        tmp, "w", driver="GTiff", width=g.n_cols, height=g.n_rows, count=2, dtype="float32",
        crs=g.crs.to_wkt(), transform=g.transform, nodata=float("nan"),
    ) as ds:
        ds.write(bands)
        ds.set_band_description(1, "log10 lower posterior")
        ds.set_band_description(2, "log10 upper posterior")


def write_png(db: SkylineDatabase, pos: Position, skyline: Skyline, path: str | Path,
              truth: tuple[float, float] | None = None) -> None:
    """The picture of :func:`appliance.outputs.picture.estimate_figure` as a PNG; ``truth`` is (lat, lon)."""
    from appliance.outputs.picture import estimate_figure

    fig = estimate_figure(db, pos, skyline, truth)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")


@dataclass(frozen=True)
class ReportEntry:
    """One skyline of ``viper estimate --report``: its name, estimate, truth (lat, lon) and files."""

    name: str
    pos: Position
    skyline: Skyline
    truth: tuple[float, float] | None
    picture: Path
    files: tuple[Path, ...]


def write_report_page(db: SkylineDatabase, entries: list[ReportEntry], folder: str | Path,
                      title: str = "Viper estimate") -> Path:
    """``report.html`` in ``folder``: a table of the estimates, then per skyline its facts, picture and
    files; returns the page's path."""
    from appliance.outputs import html as rp

    out = Path(folder)
    rows, sections = [], []
    for i, e in enumerate(entries):
        r = e.pos.result
        err = None if e.truth is None else truth_error_m(db, e.pos, e.truth)
        valid = f"{int(e.skyline.valid.sum())} of {e.skyline.elevation_deg.size}"
        rows.append({
            "skyline": e.name,
            "status": status_text(db, e.pos, e.truth),
            "lat": f"{e.pos.lat:.6f}",
            "lon": f"{e.pos.lon:.6f}",
            "truth_lat": "" if e.truth is None else f"{e.truth[0]:.6f}",
            "truth_lon": "" if e.truth is None else f"{e.truth[1]:.6f}",
            "error_m": "" if err is None else f"{err:.1f}",
            "region_km2": f"{r.region_area_m2 / 1e6:.4f}",
            "heading_correction_deg": f"{r.heading_correction_deg:+.2f}",
            "valid_azimuths": valid,
        })
        facts = [("estimate", f"{e.pos.lat:.6f}, {e.pos.lon:.6f}"),
                 ("error", "no truth given" if err is None else f"{err:.1f} m from the truth"),
                 ("region", f"{r.region_area_m2 / 1e6:.4f} km², {r.region_nodes.size} cells"),
                 ("valid azimuths", valid),
                 ("residual", f"{r.rms_residual_deg:.2f} deg RMS")]
        sections += [rp.heading(e.name, anchor=f"skyline-{i + 1}"), rp.facts_table(facts),
                     "<p>" + " · ".join(rp.link(f, out) for f in e.files) + "</p>",
                     rp.image(e.picture, out, e.picture.stem)]
    parts = [rp.paragraph(rp.shown_path(db.path, out), "Skyline database:"),
             rp.table(rows, {i: f"#skyline-{i + 1}" for i in range(len(entries))}), *sections]
    page = out / "report.html"
    write_text_atomic(page, rp.page(title, parts))
    return page
