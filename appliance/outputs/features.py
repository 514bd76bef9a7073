"""What every output shows of an estimate: its region (the cells as a mask, merged into polygons, one
GeoJSON feature), the estimate and the truth as GeoJSON points, and the skyline the map renders at the
estimate.

The region becomes GeoJSON in one place, :func:`region_polygons`; its features and their properties
(:func:`region_feature`, :func:`estimate_feature`) are the same in the log's ``/region``
(:mod:`appliance.outputs.records`) and in the files (:mod:`appliance.outputs.files`), the colours of each
kind among them (:mod:`appliance.outputs.styles`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rasterio.features

from appliance.locating.position import Position, covariance_json, fix_status, radius_json
from appliance.outputs.styles import simplestyle
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase


def region_mask(db: SkylineDatabase, pos: Position) -> np.ndarray:
    mask = np.zeros(db.grid.n_nodes, dtype=np.uint8)
    mask[pos.result.region_nodes] = 1
    return mask.reshape(db.grid.n_rows, db.grid.n_cols)


def region_polygons(db: SkylineDatabase, pos: Position) -> list[list[list[list[float]]]]:
    """The region's cells merged into polygons: rings of [lon, lat] (WGS84 or the body's geographic CRS)."""
    polys = []
    for geom, value in rasterio.features.shapes(region_mask(db, pos), transform=db.grid.transform):
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
                       "n_cells": int(r.region_nodes.size), "lower": r.lower, "upper": r.upper,
                       **simplestyle("region")},
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
                       "radius95_m": radius_json(r.covariance_m2), **simplestyle("estimate")},
        "geometry": {"type": "Point", "coordinates": [float(pos.lon), float(pos.lat)]},
    }


def truth_feature(truth: tuple[float, float]) -> dict[str, Any]:
    """The truth (lat, lon) as one GeoJSON Point feature (lon/lat)."""
    return {"type": "Feature", "properties": {"name": "truth", "kind": "truth", **simplestyle("truth")},
            "geometry": {"type": "Point", "coordinates": [float(truth[1]), float(truth[0])]}}


def rendered_skyline(db: SkylineDatabase, pos: Position) -> Skyline:
    """The database's skyline at the estimate's node (azimuths clockwise from true north)."""
    return Skyline(np.asarray(db.azimuths_deg, float), np.asarray(db.skylines_deg(pos.result.node), float))
