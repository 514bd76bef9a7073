"""Estimate outputs that open elsewhere: a PNG for the operator, GeoTIFF posteriors (NaN nodata) and two
GeoJSON layers for QGIS, the region's polygons and the points (estimate, truth)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from appliance.atomic import atomic_output, write_text_atomic
from appliance.position import Position
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
            rings.append([[round(float(a), 7), round(float(b), 7)] for a, b in zip(lon, lat)])
        polys.append(rings)
    return polys


def write_region_geojson(db: SkylineDatabase, pos: Position, path: str | Path) -> None:
    """One layer of polygons only: the estimate's region as a MultiPolygon (lon/lat)."""
    fc = {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature",
             "properties": {"kind": "region", "area_m2": pos.result.region_area_m2, "n_cells":
                            int(pos.result.region_nodes.size), "lower": pos.result.lower, "upper": pos.result.upper},
             "geometry": {"type": "MultiPolygon", "coordinates": region_polygons(db, pos)}},
        ],
    }
    write_text_atomic(Path(path), json.dumps(fc))


def write_points_geojson(pos: Position, path: str | Path, truth: tuple[float, float] | None = None) -> None:
    """One layer of points only: the estimate, and the truth (lat, lon) where known."""
    features = [
        {"type": "Feature",
         "properties": {"kind": "estimate", "lower": pos.result.lower, "upper": pos.result.upper,
                        "heading_correction_deg": pos.result.heading_correction_deg},
         "geometry": {"type": "Point", "coordinates": [pos.lon, pos.lat]}},
    ]
    if truth is not None:
        features.append({"type": "Feature", "properties": {"kind": "truth"},
                         "geometry": {"type": "Point", "coordinates": [float(truth[1]), float(truth[0])]}})
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
    """Map (hillshade, lower posterior, region outline, estimate, truth) and the skylines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    from appliance.estimator import resample_to_grid

    g = db.grid
    ground = np.asarray(db.ground_m, float).reshape(g.n_rows, g.n_cols)
    fig, (ax_map, ax_sky) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [1, 1.4]})
    filled = np.where(np.isfinite(ground), ground, np.nanmin(ground))
    shade = LightSource(azdeg=315, altdeg=45).hillshade(filled, vert_exag=2.0, dx=g.dx_m, dy=g.dy_m)
    ax_map.imshow(shade, cmap="gray", origin="upper")
    lower = pos.result.log_lower_map.reshape(g.n_rows, g.n_cols) / np.log(10.0)
    top = float(np.nanmax(lower))
    show = np.ma.masked_less(np.where(np.isfinite(lower), lower, -np.inf), top - 20.0)
    im = ax_map.imshow(show, cmap="magma", alpha=0.6, origin="upper", vmin=top - 20.0, vmax=top)
    fig.colorbar(im, ax=ax_map, fraction=0.046, label="log10 lower posterior")
    ax_map.contour(region_mask(db, pos), levels=[0.5], colors="cyan", linewidths=1.0)
    ax_map.plot(pos.result.col, pos.result.row, "c+", ms=14, mew=2, label="estimate")
    if truth is not None:
        tx, ty = g.lonlat_to_xy(truth[1], truth[0])
        tr, tc = g.xy_to_rc(tx, ty)
        ax_map.plot(float(tc), float(tr), "gx", ms=12, mew=2, label="truth")
    ax_map.set_title(f"region {pos.result.region_area_m2 / 1e6:.3f} km^2, {pos.result.region_nodes.size} cells")
    ax_map.legend(loc="lower right")
    ax_map.set_xlabel("column")
    ax_map.set_ylabel("row")

    n_az = db.n_azimuths
    az = db.azimuths_deg
    measured = resample_to_grid((skyline.azimuth_deg + pos.result.heading_correction_deg) % 360.0,
                                skyline.elevation_deg, n_az)
    ax_sky.plot(az, db.skylines_deg(pos.result.node), color="tab:orange", lw=1.5, label="rendered at the estimate")
    ax_sky.plot(az, measured, color="tab:blue", lw=1.0, label="measured (heading corrected)")
    ax_sky.set_xlim(0, 360)
    ax_sky.set_xlabel("azimuth (deg, clockwise from true north)")
    ax_sky.set_ylabel("elevation (deg)")
    ax_sky.set_title(f"{pos.lat:.5f}, {pos.lon:.5f}; residual {pos.result.rms_residual_deg:.2f} deg RMS")
    ax_sky.legend()
    ax_sky.grid(alpha=0.3)
    fig.tight_layout()
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
    finally:
        plt.close(fig)
