"""An estimate's files that open elsewhere: the picture as PNG (:func:`write_png`, the figure of
:mod:`appliance.outputs.picture`), the posteriors as GeoTIFF (:func:`write_geotiff`: float32, NaN
nodata, tiled, DEFLATE-compressed with the floating-point predictor, internal overviews), the region's
polygons (:func:`write_region_geojson`) and the estimate and the truth (:func:`write_points_geojson`) as
GeoJSON, each with its QGIS layer style beside it; :func:`write_map_layers` writes all the map's layers
of one estimate, as every command does (``viper estimate --report``, ``demo``, ``capture``, ``replay``);
:func:`save_png` saves any figure the reports show.

GDAL does not always report a failed write (a full disk can leave a GeoTIFF cut short with no
exception, or crash the process while it writes compressed tiles), and its TIFF library prints its
errors on stderr itself: :func:`write_geotiff` has GDAL make the file in memory, writes its bytes itself,
reads the file back before it takes its final name, and turns what the library printed on reading into
the one error line.
"""

from __future__ import annotations

import errno
import json
import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.io import MemoryFile

from appliance.atomic import atomic_output, describe_os_error, write_text_atomic
from appliance.errors import OutputError
from appliance.locating.position import Position
from appliance.outputs.features import estimate_feature, region_feature, truth_feature
from appliance.outputs.picture import estimate_figure
from appliance.outputs.styles import MAP_LAYER_SUFFIXES, posterior_qml_text, write_qml
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase

if TYPE_CHECKING:
    from matplotlib.figure import Figure


#: the posterior GeoTIFF's style draws this many decades below the best cell
STYLE_DECADES = 20.0
#: the GeoTIFF's tiles (pixels a side) and its overviews: halvings down to about this many pixels a side
TIFF_BLOCK_PX = 256
OVERVIEW_MIN_PX = 32


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


def write_map_layers(db: SkylineDatabase, pos: Position, folder: str | Path, stem: str,
                     truth: tuple[float, float] | None = None) -> tuple[Path, ...]:
    """The map's layers of one estimate in ``folder``, named ``stem`` and :data:`MAP_LAYER_SUFFIXES`: the
    posteriors as GeoTIFF, the region and the points (estimate, and the truth (lat, lon) where known) as
    GeoJSON, each with its QGIS style (``.qml`` of the same name, which QGIS loads with it); returns
    their paths."""
    tif, tif_qml, region, region_qml, points, points_qml = (Path(folder) / f"{stem}{e}" for e in MAP_LAYER_SUFFIXES)
    write_geotiff(db, pos, tif)
    lower = np.asarray(pos.result.log_lower_map, float)
    top = float(np.max(lower[np.isfinite(lower)], initial=-np.inf)) / np.log(10.0)
    write_text_atomic(tif_qml, posterior_qml_text(top if np.isfinite(top) else 0.0, STYLE_DECADES))
    write_region_geojson(db, pos, region)
    write_qml(region_qml, ["region"])
    write_points_geojson(pos, points, truth)
    write_qml(points_qml, ["estimate", "truth"])
    return tif, tif_qml, region, region_qml, points, points_qml


def overview_factors(n_rows: int, n_cols: int) -> list[int]:
    """Halvings (2, 4, 8, ...) down to about :data:`OVERVIEW_MIN_PX` pixels a side; at least one."""
    factors = [2]
    while max(n_rows, n_cols) / (factors[-1] * 2) >= OVERVIEW_MIN_PX:
        factors.append(factors[-1] * 2)
    return factors


def write_geotiff(db: SkylineDatabase, pos: Position, path: str | Path) -> None:
    """Two float32 bands, log10 of the lower and upper posterior of each node (its best heading); NaN is
    nodata (a posterior of zero), so no finite value, however small, is mistaken for nodata.  Tiled,
    DEFLATE-compressed with the floating-point predictor, with internal overviews (the average of the
    cells' log10 posteriors) for :func:`overview_factors`.

    GDAL builds the file in memory; its bytes are written here, so a full disk is an ``OSError`` of our
    own write (the TIFF library, writing compressed tiles onto a disk that fills, can crash the
    process), and the written file is read back before it takes its name."""
    p = Path(path)
    g = db.grid
    bands = np.stack([pos.result.log_lower_map, pos.result.log_upper_map]) / np.log(10.0)
    bands = np.where(np.isfinite(bands), bands, np.nan).astype(np.float32).reshape(2, g.n_rows, g.n_cols)
    factors = overview_factors(g.n_rows, g.n_cols)
    data = _geotiff_bytes(db, bands, factors)
    with atomic_output(p) as tmp:
        try:
            with open(tmp, "wb") as f:
                f.write(data)
        except OSError as exc:
            raise OutputError(f"{p}: cannot write: {describe_os_error(exc)} ({_written(tmp, len(data))})") from None
        with _stderr_captured() as printed:
            ok = _reads_back(tmp, bands, len(factors))
        if not ok:
            raise OutputError(f"{p}: cannot write: {_write_failure(printed, tmp, len(data))}")
        sys.stderr.write(printed[0])  # what the library printed about a file that is whole


def _geotiff_bytes(db: SkylineDatabase, bands: np.ndarray, factors: list[int]) -> bytes:
    """The GeoTIFF of :func:`write_geotiff`, made in memory."""
    g = db.grid
    with MemoryFile() as mem:
        with mem.open(driver="GTiff", width=g.n_cols, height=g.n_rows, count=2, dtype="float32",
                      crs=g.crs.to_wkt(), transform=g.transform, nodata=float("nan"), tiled=True,
                      blockxsize=TIFF_BLOCK_PX, blockysize=TIFF_BLOCK_PX, compress="deflate", predictor=3) as ds:
            ds.write(bands)
            ds.set_band_description(1, "log10 lower posterior")
            ds.set_band_description(2, "log10 upper posterior")
            ds.build_overviews(factors, Resampling.average)
            ds.update_tags(ns="rio_overview", resampling="average")
        return bytes(mem.getbuffer())


def _reads_back(path: Path, bands: np.ndarray, n_overviews: int) -> bool:
    """Whether the GeoTIFF at ``path`` holds ``bands`` exactly (NaN where NaN), and every band its
    ``n_overviews`` overviews, whose smallest reads."""
    try:
        with rasterio.open(path) as ds:
            back = ds.read()
            overviews = [ds.overviews(b) for b in ds.indexes]
            smallest = max(overviews[0]) if overviews[0] else 1
            ds.read(1, out_shape=(max(1, ds.height // smallest), max(1, ds.width // smallest)))
    except Exception:  # noqa: BLE001 - whatever GDAL raises on reading it, the file is not whole
        return False
    return (back.shape == bands.shape and bool(np.array_equal(back, bands, equal_nan=True))
            and all(len(o) == n_overviews for o in overviews))


def _written(tmp: Path, expected: int) -> str:
    try:
        return f"{os.path.getsize(tmp)} bytes written, at least {expected} expected"
    except OSError:
        return "nothing written"


def _write_failure(printed: list[str], tmp: Path, expected: int) -> str:
    """Why a GeoTIFF is not whole: the system's reason the TIFF library printed, and how much was written."""
    size = _written(tmp, expected)
    for code in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EIO, errno.EROFS):
        if os.strerror(code) in printed[0]:
            return f"{describe_os_error(OSError(code, os.strerror(code)))} ({size})"
    return f"the GeoTIFF does not read back as written ({size})"


@contextmanager
def _stderr_captured() -> Iterator[list[str]]:
    """Collect what is printed on file descriptor 2 in the block (C libraries' own messages) into the
    one string of the list yielded, instead of the terminal."""
    printed = [""]
    sys.stderr.flush()
    try:
        sink = tempfile.TemporaryFile()
    except OSError:  # nowhere to collect it: the messages stay on stderr
        yield printed
        return
    saved = os.dup(2)
    with sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield printed
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            printed[0] = sink.read(1 << 16).decode("utf-8", "replace")


def save_png(fig: Figure, path: str | Path, dpi: int) -> None:
    """``fig`` as a PNG of ``dpi`` dots per inch, written atomically."""
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")


def write_png(db: SkylineDatabase, pos: Position, skyline: Skyline, path: str | Path,
              truth: tuple[float, float] | None = None) -> None:
    """The picture of :func:`appliance.outputs.picture.estimate_figure` as a PNG; ``truth`` is (lat, lon)."""
    save_png(estimate_figure(db, pos, skyline, truth), path, dpi=90)
