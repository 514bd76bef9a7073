"""viper estimate end to end on a real map: outputs, fusion, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import rasterio

from appliance.cli.main import main
from appliance.skyline import Skyline, write_skyline_csv
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.reference_render import reference_skyline

WINDOW = (-84.30, 36.55, -84.24, 36.60)


@pytest.fixture(scope="module")
def db_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("db") / "j.viperdb"
    build_database(load_dem("jacksboro"), path, search_bounds=WINDOW, max_range_m=15_000, progress=None)
    return path


def _skyline_at(tmp_path, name, lat, lon, correction=0.0, seed=0, reference=False):
    dem = load_dem("jacksboro")
    truth = (reference_skyline(dem, lat, lon, max_range_m=15_000) if reference
             else render_skyline(dem, lat, lon, max_range_m=15_000).elevation_deg)
    rng = np.random.default_rng(seed)
    az = np.arange(360.0)
    el = np.interp((az + correction) % 360, az, truth, period=360) + rng.normal(0, 0.2, 360)
    el[rng.integers(0, 300) + np.arange(25)] = np.nan
    path = tmp_path / name
    write_skyline_csv(Skyline(az, el), path)
    return path


def _run(*args):
    return subprocess.run([sys.executable, "-m", "appliance.cli.main", *args], capture_output=True, text=True)


def test_json_estimate_within_two_cells_between_nodes(db_path, tmp_path, capsys):
    lat, lon = 36.5731, -84.2687  # between nodes
    sky = _skyline_at(tmp_path, "a.csv", lat, lon, correction=2.3, reference=True)
    assert main(["estimate", str(db_path), str(sky), "--json", "--sigma", "0.3,1.2",
                 "--truth", f"{lat},{lon}", "--report", str(tmp_path / "rep")]) == 0
    rec = json.loads(capsys.readouterr().out.strip())
    for key in ("lat", "lon", "x", "y", "crs", "heading_correction_deg", "lower", "upper", "region"):
        assert key in rec
    assert set(rec["region"]) >= {"area_m2", "cell_size_m", "cells"}
    db = load_database(db_path)
    cell = float(np.hypot(db.grid.dx_m, db.grid.dy_m)) / np.sqrt(2)
    assert rec["truth"]["error_m"] <= 2 * cell
    assert rec["heading_correction_deg"] == pytest.approx(2.3, abs=1.0)
    assert rec["crs"] == "EPSG:4326"
    # the 95 % region is the answer's covariance ellipse (no rival place here), its radius the major axis
    cov = np.array(rec["covariance_m2"])
    assert rec["status"] == "ok" and cov.shape == (2, 2)
    assert rec["region"]["area_m2"] == pytest.approx(np.pi * 5.991 * np.sqrt(np.linalg.det(cov)), rel=1e-2)
    assert rec["radius95_m"] == pytest.approx(np.sqrt(5.991 * np.linalg.eigvalsh(cov)[-1]), rel=1e-2)
    assert 0.0 <= rec["lower"] <= rec["upper"] <= 1.0
    # the report opens as what it claims to be
    rep = tmp_path / "rep"
    with rasterio.open(next(rep.glob("*-posterior.tif"))) as ds:
        assert ds.count == 2 and ds.crs.to_epsg() == 4326
        assert ds.dtypes == ("float32", "float32") and np.isnan(ds.nodata)
        lower = ds.read(1, masked=True)
        # nodata is outside the data: every finite value is data, and the masked cells are exactly the NaNs
        assert np.array_equal(np.ma.getmaskarray(lower), np.isnan(ds.read(1)))
        assert float(lower.max()) == pytest.approx(np.log10(max(rec["lower"], 1e-300)), abs=0.5) \
            or rec["lower"] == 0.0
    region = json.loads(next(rep.glob("*-region.geojson")).read_text())
    assert [f["geometry"]["type"] for f in region["features"]] == ["MultiPolygon"]
    assert region["features"][0]["properties"]["n_cells"] == rec["region"]["n_cells"]
    points = json.loads(next(rep.glob("*-points.geojson")).read_text())
    assert [f["properties"]["kind"] for f in points["features"]] == ["estimate", "truth"]
    assert points["features"][0]["geometry"]["coordinates"] == pytest.approx([rec["lon"], rec["lat"]], abs=1e-6)
    assert points["features"][1]["geometry"]["coordinates"] == pytest.approx([lon, lat])
    assert next(rep.glob("*.png")).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # one page shows them all, named relative to the report folder
    page = (rep / "report.html").read_text()
    assert str(tmp_path) not in page and "<title>Viper estimate</title>" in page
    for name in ("01-a.png", "01-a-posterior.tif", "01-a-region.geojson"):
        assert f'href="{name}"' in page and (rep / name).is_file()
    assert f"{rec['truth']['error_m']:.1f} m from the truth" in page


def test_several_skylines_share_one_load_and_fuse(db_path, tmp_path, capsys):
    a = _skyline_at(tmp_path, "a.csv", 36.5700, -84.2800, seed=1)
    b = _skyline_at(tmp_path, "b.csv", 36.5745, -84.2650, seed=2)
    assert main(["estimate", str(db_path), str(a), str(b), "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    # the displacement a -> b, in metres east and north
    geod = load_dem("jacksboro").geod
    az, _, dist = geod.inv(-84.2800, 36.5700, -84.2650, 36.5745)
    east, north = dist * np.sin(np.radians(az)), dist * np.cos(np.radians(az))
    assert main(["estimate", str(db_path), str(a), str(b), "--json", "--fuse", "--move",
                 f"{east:.1f},{north:.1f},50", "--truth", "36.5700,-84.2800", "--truth", "36.5745,-84.2650"]) == 0
    fused = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert fused[1]["truth"]["error_m"] < 150.0


@pytest.mark.parametrize("content,message", [
    ("", "empty skyline"),
    ("az,el\n0,1\n", "expected header"),
    ("azimuth_deg,elevation_deg\n0,abc\n", "not a number"),
    ("azimuth_deg,elevation_deg\n0,95\n", "outside [-90, 90]"),
    ("azimuth_deg,elevation_deg\n" + "".join(f"{a},{'1' if a < 15 else ''}\n" for a in range(360)),
     "below [estimator] min_valid_fraction 6%"),
])
def test_bad_skylines_are_one_line_errors(db_path, tmp_path, content, message):
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    proc = _run("estimate", str(db_path), str(bad))
    assert proc.returncode == 2
    assert message in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_an_old_format_database_names_the_versions_and_the_rebuild(db_path, tmp_path):
    raw = bytearray(db_path.read_bytes())
    i = raw.index(b'"format_version": 3')
    raw[i : i + len(b'"format_version": 3')] = b'"format_version": 1'
    old = tmp_path / "old.viperdb"
    old.write_bytes(bytes(raw))
    sky = _skyline_at(tmp_path, "a.csv", 36.57, -84.27)
    proc = _run("estimate", str(old), str(sky))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1 and "Traceback" not in proc.stderr
    assert "format version 1, this viper reads version 3" in lines[0]
    assert "viper precompute" in lines[0] and "--out old.viperdb" in lines[0]


def test_a_skyline_from_elsewhere_is_not_confident(db_path, tmp_path, capsys):
    rng = np.random.default_rng(5)
    foreign = tmp_path / "foreign.csv"
    write_skyline_csv(Skyline(np.arange(360.0), 8.0 + 6.0 * np.sin(np.radians(3 * np.arange(360.0)))
                              + rng.normal(0, 0.2, 360)), foreign)
    assert main(["estimate", str(db_path), str(foreign), "--json", "--sigma", "0.2,0.6"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["ambiguous"] or any("poor match" in n for n in rec["notes"])
    assert rec["region"]["n_cells"] > 25 or any("poor match" in n for n in rec["notes"])


def test_the_readme_python_api_snippet_locates_a_skyline(db_path, tmp_path, monkeypatch):
    import re
    import shutil
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("## Python API", 1)[1]
    snippet = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert len(snippet.strip().splitlines()) <= 7
    lat, lon = 36.5731, -84.2687
    shutil.copy(db_path, tmp_path / "map.viperdb")
    sky = _skyline_at(tmp_path, "s.csv", lat, lon, seed=3)
    from appliance.skyline import read_skyline_csv

    np.save(tmp_path / "elevation.npy", read_skyline_csv(sky).elevation_deg)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(snippet, "README.md", "exec"), scope)
    pos = scope["pos"]
    db = scope["db"]
    cell = float(np.hypot(db.grid.dx_m, db.grid.dy_m)) / np.sqrt(2)
    geod = load_dem("jacksboro").geod
    assert geod.inv(pos.lon, pos.lat, lon, lat)[2] <= 2 * cell


def test_a_large_region_is_written_truncated_with_its_full_count(db_path, tmp_path, monkeypatch):
    """The JSON record keeps the region's first cells only, names its full size, and says so."""
    import dataclasses

    from appliance.locating import position
    from appliance.skyline import read_skyline_csv

    db = load_database(db_path)
    sky = read_skyline_csv(_skyline_at(tmp_path, "a.csv", 36.5731, -84.2687))
    pos = position.locate(db, sky, (0.3, 1.2), 4.0)
    nodes = np.arange(0, 60, 5)  # twelve cells
    big = dataclasses.replace(pos, estimate=dataclasses.replace(pos.result, region_nodes=nodes))
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(nodes))
    monkeypatch.setattr(position, "MAX_REGION_CELLS_IN_JSON", 5)
    region = big.to_json(db)["region"]
    assert region["n_cells"] == 12 and region["cells_truncated"] is True
    assert np.allclose(region["cells"], np.column_stack([lat, lon])[:5], atol=1e-7)
    monkeypatch.setattr(position, "MAX_REGION_CELLS_IN_JSON", 12)
    region = big.to_json(db)["region"]
    assert region["cells_truncated"] is False and np.allclose(region["cells"], np.column_stack([lat, lon]), atol=1e-7)


@pytest.mark.parametrize("extra,message", [
    (["--truth", "nan,nan"], "--truth 'nan,nan': expected 2 comma-separated finite numbers"),
    (["--truth", "95,10"], "--truth '95,10': expected LAT,LON in degrees"),
    (["--sigma", "1e-300,1e-299"], "estimator.sigma_deg"),
    (["--sigma", "0.3,inf"], "--sigma '0.3,inf': expected 2 comma-separated finite numbers"),
    (["--fuse", "--move", "nan,0,1"], "--move 'nan,0,1': expected 3 comma-separated finite numbers"),
    (["--fuse", "--move", "10,0,-1"], "--move '10,0,-1': its sigma must be >= 0 m"),
])
def test_unphysical_options_are_one_line_errors(db_path, tmp_path, extra, message):
    sky = _skyline_at(tmp_path, "a.csv", 36.5731, -84.2687)
    skylines = [str(sky), str(sky)] if "--fuse" in extra else [str(sky)]
    out = subprocess.run([sys.executable, "-m", "appliance.cli.main", "estimate", str(db_path), *skylines, *extra],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and out.stdout == ""
    assert out.stderr.count("\n") == 1 and message in out.stderr and "Traceback" not in out.stderr
