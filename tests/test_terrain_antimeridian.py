"""A map across the antimeridian: the rendered skyline against the reference ray march
(tests/reference_render.py) and against the same terrain moved to 10 degrees east, and a longitude
written in either turn (-180..180 or 0..360) landing on the same place for render, sampling and
precompute."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import from_origin

from appliance.skyline import read_skyline_csv
from appliance.terrain.database import load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.reference_render import reference_skyline

#: RMS bound (deg) of the rendered skyline against the reference, as in tests/test_terrain_render.py
RENDER_RMS_DEG = 0.05
LAT = -16.975
RES_DEG = 0.0002
SIDE = 250  # 0.05 degrees: 179.98..180.03 E
RANGE_M = 8000.0


def _heights(cols: int, rows: int) -> np.ndarray:
    """A ridge running across the map, a round hill and a gentle swell (m)."""
    u, v = np.meshgrid(np.arange(cols) / cols, np.arange(rows) / rows)
    ridge = 200.0 * np.exp(-(((u - 0.6 * v - 0.2) / 0.08) ** 2))
    hill = 120.0 * np.exp(-((u - 0.7) ** 2 + (v - 0.3) ** 2) / 0.02)
    return 300.0 + ridge + hill + 40.0 * np.sin(6.0 * u) * np.cos(4.0 * v)


def _write(path: Path, west: float, north: float, res: float, crs: str) -> Path:
    z = _heights(SIDE, SIDE).astype("float32")
    with rasterio.open(path, "w", driver="GTiff", width=SIDE, height=SIDE, count=1, dtype="float32", crs=crs,
                       transform=from_origin(west, north, res, res)) as ds:
        ds.write(z, 1)
    return path


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("antimeridian")
    north = LAT + SIDE * RES_DEG / 2
    x0, y0 = Transformer.from_crs(4326, 32760, always_xy=True).transform(179.98, north)
    return {
        "east": _write(d / "east.tif", 179.98, north, RES_DEG, "EPSG:4326"),  # columns 179.98..180.03
        "west": _write(d / "west.tif", -180.02, north, RES_DEG, "EPSG:4326"),  # columns -180.02..-179.97
        "moved": _write(d / "moved.tif", 9.98, north, RES_DEG, "EPSG:4326"),  # the same terrain at 10 E
        "utm": _write(d / "utm.tif", x0, y0, 20.0, "EPSG:32760"),  # UTM zone 60 S, across 180
    }


def test_skyline_at_the_antimeridian_matches_the_reference(maps):
    dem = load_dem(maps["east"])
    ours = render_skyline(dem, LAT, 180.0, max_range_m=RANGE_M).elevation_deg
    ref = reference_skyline(dem, LAT, 180.0, max_range_m=RANGE_M)
    assert np.isfinite(ref).all()
    assert np.array_equal(np.isfinite(ours), np.isfinite(ref))
    assert np.sqrt(np.mean((ours - ref) ** 2)) <= RENDER_RMS_DEG
    # the same terrain away from the antimeridian gives the same skyline
    moved = render_skyline(load_dem(maps["moved"]), LAT, 10.0, max_range_m=RANGE_M).elevation_deg
    assert np.allclose(ours, moved, atol=1e-6)


@pytest.mark.parametrize("name", ["east", "west"])
def test_a_longitude_in_either_turn_samples_the_same_place(maps, name):
    dem = load_dem(maps[name])
    lat = np.full(4, LAT)
    same = dem.sample_lonlat(np.array([-179.99, 180.01, 540.01, -539.99]), lat)
    assert np.isfinite(same).all() and np.ptp(same) < 1e-6
    off = dem.sample_lonlat(np.array([179.9, -179.9]), lat[:2])
    assert np.isnan(off).all()


def _render_cli(dem: Path, lon: str, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "appliance.cli.main", "render", str(dem), "--lat", str(LAT),
                           "--lon", lon, "--max-range", str(RANGE_M), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)


def test_render_takes_the_place_in_either_turn(maps, tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for lon, out in (("-179.995", a), ("180.005", b)):
        proc = _render_cli(maps["east"], lon, out)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert a.read_bytes() == b.read_bytes()
    sky = read_skyline_csv(a)
    assert sky.azimuth_deg.size == 360 and np.isfinite(sky.elevation_deg).all()
    moved = render_skyline(load_dem(maps["moved"]), LAT, 10.005, max_range_m=RANGE_M).elevation_deg
    assert np.allclose(sky.elevation_deg, moved, atol=1e-4)


def test_a_projected_map_across_the_antimeridian_keeps_one_turn(maps):
    dem = load_dem(maps["utm"])
    west, _, east, _ = dem.bounds_lonlat()
    assert 179.97 < west < 180.0 < east < 180.04
    sky = render_skyline(dem, LAT, -179.995, max_range_m=RANGE_M).elevation_deg
    assert np.isfinite(sky).all()


def test_precompute_takes_search_bounds_in_either_turn(maps, tmp_path):
    dem = load_dem(maps["east"])
    dbs = []
    for bounds in ("-179.995,-16.99,-179.985,-16.96", "180.005,-16.99,180.015,-16.96"):
        out = tmp_path / f"{len(dbs)}.viperdb"
        proc = subprocess.run([sys.executable, "-m", "appliance.cli.main", "precompute", str(maps["east"]),
                               "--out", str(out), f"--search-bounds={bounds}", "--max-range", "5000"],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        dbs.append(load_database(out, dem))
    a, b = dbs
    assert a.grid == b.grid and a.grid.n_nodes == 150 * 50
    assert 180.0 < a.grid.x0 < 180.03
    assert np.array_equal(a.codes, b.codes) and np.isfinite(a.offset_deg).any()
