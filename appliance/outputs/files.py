"""An estimate's files that open elsewhere: the picture as PNG (:func:`write_png`, the figure of
:mod:`appliance.outputs.picture`), the posteriors as GeoTIFF (:func:`write_geotiff`: float32, NaN
nodata), the region's polygons (:func:`write_region_geojson`) and the estimate and the truth
(:func:`write_points_geojson`) as GeoJSON; :func:`save_png` saves any figure the reports show.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rasterio

from appliance.atomic import atomic_output, write_text_atomic
from appliance.locating.position import Position
from appliance.outputs.features import estimate_feature, region_feature, truth_feature
from appliance.outputs.picture import estimate_figure
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase

if TYPE_CHECKING:
    from matplotlib.figure import Figure


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


def save_png(fig: Figure, path: str | Path, dpi: int) -> None:
    """``fig`` as a PNG of ``dpi`` dots per inch, written atomically."""
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")


def write_png(db: SkylineDatabase, pos: Position, skyline: Skyline, path: str | Path,
              truth: tuple[float, float] | None = None) -> None:
    """The picture of :func:`appliance.outputs.picture.estimate_figure` as a PNG; ``truth`` is (lat, lon)."""
    save_png(estimate_figure(db, pos, skyline, truth), path, dpi=90)
