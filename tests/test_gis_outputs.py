"""The map's layers from every command that estimates (``viper capture`` beside its log, ``viper replay``
and ``viper demo`` beside their reports): a tiled, compressed GeoTIFF with overviews, nodata and the
map's CRS, GeoJSON drawn in one colour per kind, and the QGIS styles that draw them; and the report's
first lines: the status banner and the position as lat/lon, UTM, MGRS and altitude."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import CRS, Transformer
from rasterio.enums import Compression

from appliance.cli.main import main
from appliance.outputs.files import MAP_LAYER_SUFFIXES
from appliance.outputs.grid_refs import mgrs_ref, utm_ref, utm_zone
from appliance.outputs.status import TRUTH_OUTSIDE, position_facts, status_banner
from tests.conftest import REPO

HEX = "0123456789abcdef"


# ----------------------------------------------------------------------------------------- the checks
def check_geotiff(path: Path, db) -> None:
    """The GeoTIFF opens with the map's CRS, NaN nodata, DEFLATE with the floating-point predictor,
    256-pixel tiles, at least one overview per band, and the grid's size and transform."""
    with rasterio.open(path) as ds:
        assert CRS.from_wkt(ds.crs.to_wkt()).equals(db.grid.crs)
        assert ds.count == 2 and ds.dtypes == ("float32", "float32") and math.isnan(ds.nodata)
        assert ds.compression is Compression.deflate
        assert ds.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "3"
        assert ds.profile["tiled"] and ds.block_shapes == [(256, 256), (256, 256)]
        assert (ds.height, ds.width) == (db.grid.n_rows, db.grid.n_cols)
        assert ds.transform.almost_equals(db.grid.transform)
        for band in (1, 2):
            assert len(ds.overviews(band)) >= 1 and ds.overviews(band)[0] == 2
        lower, upper = ds.read(1), ds.read(2)
        # the overview is the average of the cells: a halved read lies within the full one's range
        half = ds.read(1, out_shape=(ds.height // 2, ds.width // 2))
    assert np.nanmax(half) <= np.nanmax(lower) + 1e-4 and np.nanmin(half) >= np.nanmin(lower) - 1e-4
    finite = np.isfinite(lower) & np.isfinite(upper)
    assert finite.any() and np.all(lower[finite] <= upper[finite] + 1e-5)


def _colour(value: str) -> str:
    assert len(value) == 7 and value[0] == "#" and all(c in HEX for c in value[1:]), value
    return value


def check_geojson(region_path: Path, points_path: Path, with_truth: bool) -> dict[str, str]:
    """The layers' features, one colour per kind (region outline and fill one colour; estimate and truth
    markers others); returns kind -> colour."""
    region = json.loads(region_path.read_text())["features"]
    points = json.loads(points_path.read_text())["features"]
    assert [f["properties"]["kind"] for f in region] == ["region"]
    assert [f["properties"]["kind"] for f in points] == ["estimate", "truth"][:1 + with_truth]
    r = region[0]["properties"]
    assert _colour(r["stroke"]) == _colour(r["fill"]) and 0.0 < r["fill-opacity"] < 1.0 and r["stroke-width"] > 0
    colours = {"region": r["fill"]}
    for f in points:
        p = f["properties"]
        colours[p["kind"]] = _colour(p["marker-color"])
        assert p["marker-symbol"] and "fill" not in p
    assert len(set(colours.values())) == len(colours)
    return colours


def check_qml(path: Path, colours: dict[str, str]) -> list[str]:
    """The QGIS style: a categorized renderer on ``kind`` whose categories draw each kind in the colour
    its GeoJSON features carry; returns the categories' values."""
    text = path.read_text()
    assert text.startswith("<!DOCTYPE qgis")
    root = ET.fromstring(text.split("\n", 1)[1])
    renderer = root.find("renderer-v2")
    assert root.tag == "qgis" and renderer is not None
    assert renderer.get("type") == "categorizedSymbol" and renderer.get("attr") == "kind"
    symbols = {s.get("name"): s for s in renderer.iter("symbol")}
    values = []
    for category in renderer.iter("category"):
        kind, symbol = category.get("value", ""), symbols[category.get("symbol")]
        values.append(kind)
        options = {o.get("name"): o.get("value", "") for o in symbol.iter("Option") if o.get("name")}
        props = {p.get("k"): p.get("v", "") for p in symbol.iter("prop")}
        assert options == props  # the same options for QGIS's readers old and new
        want = colours.get(kind)
        if want is not None:
            rgb = ",".join(str(int(want[i:i + 2], 16)) for i in (1, 3, 5))
            assert options["outline_color"] == f"{rgb},255"
            assert options["color"].startswith(rgb + ",")
        assert symbol.get("type") == ("fill" if kind == "region" else "marker")
    return values


def check_posterior_qml(path: Path, tif: Path) -> None:
    """The GeoTIFF's QGIS style: band 1 as a pseudocolour ramp over the 20 decades below its best cell,
    clipped (cells further down not drawn)."""
    with rasterio.open(tif) as ds:
        best = float(np.nanmax(ds.read(1)))
    root = ET.fromstring(path.read_text().split("\n", 1)[1])
    renderer = root.find("pipe/rasterrenderer")
    assert renderer is not None and renderer.get("type") == "singlebandpseudocolor" and renderer.get("band") == "1"
    shader = renderer.find("rastershader/colorrampshader")
    assert shader is not None and shader.get("clip") == "1"
    lo, hi = float(shader.get("minimumValue", "nan")), float(shader.get("maximumValue", "nan"))
    assert hi == pytest.approx(best, abs=1e-4) and hi - lo == pytest.approx(20.0, abs=1e-4)
    values = [float(item.get("value", "nan")) for item in shader.iter("item")]
    assert values[0] == pytest.approx(lo, abs=1e-4) and values[-1] == pytest.approx(hi, abs=1e-4)
    assert values == sorted(values) and len(values) == 5


def check_layers(folder: Path, stem: str, db, with_truth: bool) -> None:
    tif, tif_qml, region, region_qml, points, points_qml = (folder / f"{stem}{e}" for e in MAP_LAYER_SUFFIXES)
    check_geotiff(tif, db)
    check_posterior_qml(tif_qml, tif)
    colours = check_geojson(region, points, with_truth)
    assert check_qml(region_qml, colours) == ["region"]
    assert check_qml(points_qml, colours) == ["estimate", "truth"]


class Banners(HTMLParser):
    """The page's status banners (class and text) and whether anything but the title came before them."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.banners: list[tuple[str, str]] = []
        self.before: list[str] = []
        self._depth = 0
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        cls = dict(attrs).get("class") or ""
        if tag == "div" and cls.startswith("banner"):
            self.banners.append((cls.split()[1], ""))
            self._depth = 1
        elif self._depth:
            self._depth += tag != "li"
        elif not self.banners and tag in ("p", "table", "h2", "img"):
            self.before.append(tag)

    def handle_endtag(self, tag):
        if self._depth and tag == "div":
            self._depth = 0

    def handle_data(self, data):
        if self._depth:
            cls, text = self.banners[-1]
            self.banners[-1] = (cls, text + data)


# ------------------------------------------------------------------------------------------ the runs
@pytest.fixture(scope="module")
def captured(tmp_path_factory, window_db):
    """`viper capture` of one simulated session on the window's database, and what it printed."""
    folder = tmp_path_factory.mktemp("capture")
    cfg = folder / "sim.toml"
    cfg.write_text('[platform]\nkind = "sim"\n'
                   f'[session]\ndatabase = "{window_db.path}"\ntruth_duration_s = 10.0\nsettle_s = 0.2\n'
                   "[devices.camera]\nwidth = 320\nheight = 240\n[sim]\ntime_rate = 50.0\n")
    logs = folder / "logs"
    return main(["capture", "--config", str(cfg), "--log-dir", str(logs), "--seed", "5"]), logs


def test_capture_writes_the_map_layers_beside_its_log(captured, window_db, capsys):
    code, logs = captured
    assert code == 0
    (log,) = logs.glob("*.mcap")
    names = sorted(p.name for p in logs.iterdir() if not p.name.startswith("."))
    assert names == sorted([log.name, *(log.stem + e for e in MAP_LAYER_SUFFIXES)])
    check_layers(logs, log.stem, window_db, with_truth=True)


def test_the_session_daemon_writes_the_map_layers_beside_each_log(tmp_path, window_db):
    """The unattended path: `viper daemon session` (its own process, as the service runs it) leaves
    the same layers beside every log it writes as `viper capture` does."""
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[platform]\nkind = "sim"\n'
                   f'[session]\ndatabase = "{window_db.path}"\ntruth_duration_s = 10.0\nsettle_s = 0.2\n'
                   "interval_s = 0.05\nmax_sessions = 1\n"
                   "[devices.camera]\nwidth = 320\nheight = 240\n[sim]\ntime_rate = 50.0\n")
    logs = tmp_path / "logs"
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
    out = subprocess.run([sys.executable, "-m", "appliance.cli.main", "daemon", "session", "--config", str(cfg),
                          "--log-dir", str(logs)], env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    (log,) = logs.glob("*.mcap")
    names = sorted(p.name for p in logs.iterdir() if not p.name.startswith("."))
    assert names == sorted([log.name, *(log.stem + e for e in MAP_LAYER_SUFFIXES)])
    check_layers(logs, log.stem, window_db, with_truth=True)


def test_replay_writes_the_map_layers_and_a_banner_first(captured, window_db, tmp_path, capsys):
    _, logs = captured
    (log,) = logs.glob("*.mcap")
    out = tmp_path / "replayed"
    assert main(["replay", str(log), "--db", str(window_db.path), "--out", str(out)]) == 0
    check_layers(out, log.stem, window_db, with_truth=True)
    page = (out / "report.html").read_text()
    for e in MAP_LAYER_SUFFIXES:
        assert f'href="{log.stem}{e}"' in page
    # the banner comes before every table, paragraph and picture, and says what the summary says
    (row,) = csv.DictReader((out / "summary.csv").open())
    doc = Banners(page)
    assert doc.before == [] and len(doc.banners) == 1
    cls, text = doc.banners[0]
    assert cls == row["status"] and text.startswith("ok ± " if row["status"] == "ok" else "AMBIGUOUS")
    # the position: UTM as pyproj puts the table's lat/lon, and the MGRS of that
    lat, lon = float(row["lat"]), float(row["lon"])
    u = utm_ref(lat, lon)
    assert u is not None and f"<td>{u.text()}</td>" in page and f"<td>{mgrs_ref(lat, lon)}</td>" in page
    assert f"MGRS {mgrs_ref(lat, lon)}" in text


def test_the_skyline_only_demo_writes_the_map_layers_beside_its_picture(window_db, tmp_path, capsys, monkeypatch):
    # the demo's own map is the whole jacksboro DEM (a minute to build): the window's database stands in
    import appliance.sim.demo as demo

    monkeypatch.setattr(demo, "demo_database", lambda dem, out: window_db)
    assert main(["demo", "--skyline-only", "--seed", "4", "--out", str(tmp_path)]) == 0
    assert "estimate-posterior.tif" in capsys.readouterr().out
    check_layers(tmp_path, "estimate", window_db, with_truth=True)


# ---------------------------------------------------------------------------------- banner, UTM, MGRS
def test_the_banner_of_an_ok_and_of_an_ambiguous_record():
    ok = status_banner({"status": "ok", "ambiguous": False, "radius95_m": 12.34, "notes": ["a note"]})
    assert (ok.ok, ok.headline, ok.reasons) == (True, "ok ± 12.3 m", ())
    rivals = "41% of the posterior lies at other places (2 of them, up to 3.1 km away)"
    amb = status_banner({"status": "ambiguous", "ambiguous": True, "radius95_m": 40.0,
                         "notes": [f"ambiguous: {rivals}", "the region is 2.1 km^2"]})
    assert (amb.ok, amb.headline, amb.reasons) == (False, "AMBIGUOUS", (rivals, "the region is 2.1 km^2"))
    # ambiguous only because the GPS truth lies outside the region
    outside = status_banner({"status": "ambiguous", "ambiguous": False, "radius95_m": 5.0, "notes": [],
                             "truth": {"lat": 36.6, "lon": -84.3, "error_m": 900.0}})
    assert (outside.ok, outside.reasons) == (False, (TRUTH_OUTSIDE,))


def test_utm_agrees_with_pyproj_and_the_published_values():
    # the White House: 18 N 323394.296 4307395.634 (chrisveness/geodesy's test table)
    lat, lon = 38.8977, -77.0365
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:32618", always_xy=True).transform(lon, lat)
    u = utm_ref(lat, lon)
    assert u is not None and (u.zone, u.band, u.hemisphere, u.epsg) == (18, "S", "N", 32618)
    assert (u.easting_m, u.northing_m) == pytest.approx((e, n), abs=1e-6)
    assert (u.easting_m, u.northing_m) == pytest.approx((323394.296, 4307395.634), abs=1e-3)
    # south: Rio's Christ, 23 S 683466.254 7460687.433 (the 10,000 km false northing)
    s = utm_ref(-22.9519, -43.2106)
    assert s is not None and (s.zone, s.hemisphere, s.epsg) == (23, "S", 32723)
    assert (s.easting_m, s.northing_m) == pytest.approx((683466.254, 7460687.433), abs=1e-3)
    # the zones' exceptions and the polar caps
    assert utm_zone(60.39135, 5.3249) == 32 and utm_zone(60.0, 2.9) == 31 and utm_zone(78.0, 10.0) == 33
    assert utm_zone(0.0, 180.0) == 1 and utm_zone(0.0, 179.9) == 60
    assert utm_ref(84.5, 10.0) is None and utm_ref(-80.5, 10.0) is None and mgrs_ref(-85.0, 0.0) is None


@pytest.mark.parametrize(("lat", "lon", "mgrs"), [
    # chrisveness/geodesy's test table, and the mgrs package's README (42 N 93 W)
    (48.8583, 2.2945, "31U DQ 48251 11943"),
    (-33.857, 151.215, "56H LH 34873 52266"),
    (38.8977, -77.0365, "18S UJ 23394 07395"),
    (-22.9519, -43.2106, "23K PQ 83466 60687"),
    (60.39135, 5.3249, "32V KN 97508 00645"),
    (1.0, 1.0, "31N BB 77438 10597"),
    (-1.0, -1.0, "30M YD 22561 89402"),
    (0.0, 0.0, "31N AA 66021 00000"),
    (42.0, -93.0, "15T WG 00000 49776"),
])
def test_mgrs_matches_the_published_values(lat, lon, mgrs):
    assert mgrs_ref(lat, lon) == mgrs


def test_the_position_facts_read_the_record():
    record = {"lat": -22.9519, "lon": -43.2106, "altitude_m": 702.46}
    facts = dict(position_facts(record))
    assert facts["latitude, longitude"] == "-22.951900, -43.210600 (22.951900° S, 43.210600° W)"
    assert facts["UTM (WGS 84)"] == "23K 683466 E 7460687 N" and facts["MGRS"] == "23K PQ 83466 60687"
    assert facts["altitude"] == "702.5 m (the map's vertical datum)"
    moon = dict(position_facts({**record, "altitude_m": None}, "moon"))
    assert moon["UTM, MGRS"] == "none on the Moon" and moon["altitude"] == "off the map"


def test_the_pictures_colour_scale_is_the_posterior_relative_to_the_best(window_db, dem):
    from appliance import locate
    from appliance.outputs.picture import POSTERIOR_DECADES, POSTERIOR_LABEL, estimate_figure
    from appliance.skyline import Skyline
    from appliance.terrain.horizon import render_skyline

    sky = render_skyline(dem, 36.585, -84.26, height_m=1.5)
    pos = locate(window_db, Skyline(sky.azimuth_deg, sky.elevation_deg), (0.2, 0.6), 5.0)
    fig = estimate_figure(window_db, pos, sky)
    (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bar.get_ylabel() == POSTERIOR_LABEL and "relative to the best" in POSTERIOR_LABEL
    mesh = next(m for m in fig.axes[0].collections if m.get_cmap().name == "magma")
    assert mesh.get_clim() == (-POSTERIOR_DECADES, 0.0)
    shown = mesh.get_array()
    # 0 at the cell of the highest lower posterior, nothing above it
    assert float(shown.max()) == 0.0
    lower = np.asarray(pos.result.log_lower_map)
    assert int(np.argmax(np.where(np.isfinite(lower), lower, -np.inf))) == int(np.argmax(shown.filled(-np.inf)))
