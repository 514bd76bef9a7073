"""The production renderer against the dense, exact reference ray march (tests/reference_render.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from appliance.errors import DemError
from appliance.skyline import read_skyline_csv
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.conftest import data_file
from tests.reference_render import reference_skyline

DEMS = [
    "dem_other/jacksboro_fault_dem.npz",
    "dem_srtm_hgt/N44W072.hgt",
    "dem_usgs_ascii/SainteHelens.dem",
    "dem_usgs_ascii/sanfranciscos.dem",
    "dem_geotiff/msh00_MountStHelens_2000_webmerc.tif",
    "dem_geotiff/gmted2010_clips/denali.tiff",
    "dem_other/msh00_83_MountStHelens_2000.e00",
    "dem_planetary/LDEM_4.LBL",
]


def _random_viewpoints(dem, rng, n):
    """Points strictly between grid nodes, on data, away from the map's edge."""
    rows, cols = dem.shape
    pts = []
    while len(pts) < n:
        r = rng.uniform(0.2 * rows, 0.8 * rows)
        c = rng.uniform(0.2 * cols, 0.8 * cols)
        if dem.body.name.value == "moon":
            r = rng.uniform(0.35 * rows, 0.65 * rows)
        lon, lat = dem.xy_to_lonlat(*dem.pixel_to_xy(c, r))
        if np.isfinite(dem.sample_lonlat(np.atleast_1d(lon), np.atleast_1d(lat))[0]):
            pts.append((float(lat), float(lon)))
    return pts


@pytest.mark.parametrize("rel", DEMS)
def test_render_matches_dense_exact_ray_march(rel):
    dem = load_dem(data_file(rel))
    rng = np.random.default_rng(7)
    az = np.arange(0.0, 360.0, 3.0) + rng.uniform(0, 1)
    errors = []
    for lat, lon in _random_viewpoints(dem, rng, 2):
        ours = render_skyline(dem, lat, lon, 1.5, az, max_range_m=20_000).elevation_deg
        ref = reference_skyline(dem, lat, lon, 1.5, az, max_range_m=20_000)
        assert np.array_equal(np.isfinite(ours), np.isfinite(ref))
        errors.append((ours - ref)[np.isfinite(ref)])
    e = np.concatenate(errors)
    assert np.sqrt(np.mean(e**2)) <= 0.05


def test_curvature_and_refraction_lower_a_distant_peak():
    dem = load_dem(data_file("dem_srtm_hgt/N44W072.hgt"))
    # towards Mount Washington, about 37 km south-west: there the drop d^2/2R is ~ 100 m
    lat, lon = 44.55, -71.05
    az = np.array([dem.geod.inv(lon, lat, -71.303, 44.271)[0] % 360.0])
    flat = render_skyline(dem, lat, lon, 1.5, az, refraction=1.0 - 1e-9).elevation_deg[0]
    earth = render_skyline(dem, lat, lon, 1.5, az).elevation_deg[0]
    no_refr = render_skyline(dem, lat, lon, 1.5, az, refraction=0.0).elevation_deg[0]
    assert flat > earth > no_refr
    ref = reference_skyline(dem, lat, lon, 1.5, az)[0]
    assert earth == pytest.approx(ref, abs=0.02)


def test_render_cli_writes_one_row_per_degree(tmp_path):
    out = tmp_path / "sky.csv"
    proc = subprocess.run(
        [sys.executable, "-m", "appliance.cli.main", "render", "jacksboro", "--lat", "36.6", "--lon", "-84.25",
         "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    sky = read_skyline_csv(out)
    assert np.array_equal(sky.azimuth_deg, np.arange(360.0))
    dem = load_dem("jacksboro")
    direct = render_skyline(dem, 36.6, -84.25).elevation_deg
    assert np.allclose(sky.elevation_deg, direct, atol=1e-4)


def test_viewpoint_off_the_map_is_an_error():
    dem = load_dem("jacksboro")
    with pytest.raises(DemError, match="off the map"):
        render_skyline(dem, 40.0, -84.25)
