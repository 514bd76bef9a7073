"""viper dem info, render and precompute on every DEM in ../shared/data; the rendered skyline against
the dense, exact reference ray march (tests/reference_render.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from appliance.cli.main import main
from appliance.skyline import read_skyline_csv
from appliance.terrain.database import load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import DEFAULT_HEIGHT_M
from tests.conftest import SHARED_DATA
from tests.reference_render import reference_skyline

SUFFIXES = {".dem", ".hgt", ".tif", ".tiff", ".lbl", ".img", ".npz", ".e00"}
EVERY = sorted(p for p in SHARED_DATA.rglob("*") if p.suffix.lower() in SUFFIXES) if SHARED_DATA.is_dir() else []
# the Finse DSM carries no CRS tag; its MANIFEST entry gives EPSG:32632
CRS_OF = {"time_lapse_finse_DSM_midfilled.tif": "EPSG:32632", "viewshed.tif": "EPSG:32632"}
#: RMS bound (deg) of the rendered skyline against the reference, as in tests/test_terrain_render.py
RENDER_RMS_DEG = 0.05


def _ids(paths: list[Path]) -> list[str]:
    return [str(p.relative_to(SHARED_DATA)) for p in paths]


@pytest.mark.skipif(not EVERY, reason=f"real data folder {SHARED_DATA} is absent")
@pytest.mark.parametrize("path", EVERY, ids=_ids(EVERY))
def test_info_render_precompute(path, tmp_path, capsys):
    extra = ["--crs", CRS_OF[path.name]] if path.name in CRS_OF else []
    if path.name == "viewshed.tif":
        pytest.skip("viewshed.tif is a visibility mask, not an elevation model")
    assert main(["dem", "info", str(path), "--json", *extra]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["shape"][0] > 1 and info["elevation_max_m"] > info["elevation_min_m"]

    dem = load_dem(path, crs=extra[1] if extra else None)
    rows, cols = dem.shape
    ok = np.isfinite(dem.elevation_m)
    inner = ok[1:-1, 1:-1] & ok[:-2, 1:-1] & ok[2:, 1:-1] & ok[1:-1, :-2] & ok[1:-1, 2:]
    finite = np.argwhere(inner) + 1
    r, c = finite[len(finite) // 2]
    lon, lat = dem.xy_to_lonlat(*dem.pixel_to_xy(float(c) + 0.3, float(r) + 0.4))
    if not np.isfinite(dem.sample_lonlat(np.atleast_1d(lon), np.atleast_1d(lat))[0]):
        lon, lat = dem.xy_to_lonlat(*dem.pixel_to_xy(float(c), float(r)))
    out = tmp_path / "sky.csv"
    lat_text, lon_text = f"{float(lat):.7f}", f"{float(lon):.7f}"
    assert main(["render", str(path), "--lat", lat_text, "--lon", lon_text,
                 "--max-range", "10000", "--out", str(out), *extra]) == 0
    sky = read_skyline_csv(out)
    assert sky.azimuth_deg.size == 360 and np.isfinite(sky.elevation_deg).mean() > 0.2
    # every tenth azimuth against the reference (its dense march costs seconds an azimuth on metre grids)
    az, ours = sky.azimuth_deg[::10], sky.elevation_deg[::10]
    ref = reference_skyline(dem, float(lat_text), float(lon_text), DEFAULT_HEIGHT_M, az, max_range_m=10_000.0)
    assert np.array_equal(np.isfinite(ours), np.isfinite(ref))
    diff = (ours - ref)[np.isfinite(ref)]
    assert np.sqrt(np.mean(diff**2)) <= RENDER_RMS_DEG

    res = dem.resolution_m()
    half_deg = 3 * max(res) / 111_000.0 / max(np.cos(np.radians(float(lat))), 0.1)
    if dem.body.name.value != "earth":
        half_deg *= 111_000.0 * 6.371e6 / 1.7374e6 / 111_000.0
    bounds = f"{float(lon) - half_deg},{float(lat) - half_deg},{float(lon) + half_deg},{float(lat) + half_deg}"
    db = tmp_path / "db.viperdb"
    # the sweep's range must span a few of the grid's diagonals (it refuses less), so coarse maps
    # (topobathy's 3.4 km cells, the Moon's 7.6 km) get a longer one than 10 km
    max_range_m = max(10_000.0, 4.0 * float(np.hypot(*res)))
    assert main(["precompute", str(path), "--out", str(db), f"--search-bounds={bounds}",
                 "--max-range", f"{max_range_m:.0f}", *extra]) == 0
    loaded = load_database(db, dem)
    assert loaded.grid.n_nodes >= 4
    assert np.isfinite(loaded.offset_deg).any()
