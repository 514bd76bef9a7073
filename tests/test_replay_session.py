"""``viper replay``: the estimate rerun from a session log's raw data, the report, and bad logs."""

from __future__ import annotations

import csv
import datetime as dt
import json
from html.parser import HTMLParser
from urllib.parse import quote, unquote

import numpy as np
import pytest

from appliance.acquisition.replay import read_session, replay_logs, replay_session, session_report
from appliance.bodies import geodesic_distance_m
from appliance.cli.main import main
from appliance.config import EstimatorConfig
from appliance.logbook import topics as t
from appliance.logbook.reader import LogReader
from appliance.logbook.summary import summarize_log
from appliance.outputs.files import MAP_LAYER_SUFFIXES
from appliance.outputs.grid_refs import mgrs_ref
from appliance.sim.field_session import run_field_session
from tests.conftest import small_config
from tests.test_gis_outputs import check_layers


@pytest.fixture(scope="module")
def session_log(tmp_path_factory, dem, window_db):
    r, _ = run_field_session(small_config(), tmp_path_factory.mktemp("logs"), seed=5, dem=dem, db=window_db)
    assert r.error_m is not None
    return r


def test_replay_reproduces_the_onboard_estimate(session_log, window_db, tmp_path):
    data = read_session(session_log.log_path)
    assert data.complete and len(data.frames) == 9 and data.intrinsics is not None
    assert (data.intrinsics.width, data.intrinsics.height) == (320, 240)
    assert data.onboard_error_m == pytest.approx(session_log.error_m)
    res = replay_session(data, window_db, EstimatorConfig(), tmp_path)
    assert res.position is not None and res.error_m is not None
    # the frames went through JPEG: the replayed estimate lands within one node of the onboard one
    onboard = session_log.estimate
    assert geodesic_distance_m(res.position.lat, res.position.lon, onboard.lat, onboard.lon) < 120.0
    assert res.error_m < 150.0
    s = summarize_log(res.results_log)
    assert s.complete and s.topics[t.ESTIMATE_FIX].count == 1 and s.topics[t.POSTERIOR].count == 1
    assert s.error_m == pytest.approx(res.error_m, abs=0.01)


class Page(HTMLParser):
    """A report page as what a reader sees (text) and what the browser fetches (links)."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.title = ""
        self.texts: list[str] = []
        self.links: list[str] = []
        self.tables: list[list[list[str]]] = []
        self._tag = ""
        self._in_cell = False
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self._tag = tag
        self.links += [v for k, v in attrs if k in ("href", "src") and v is not None]
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self.tables[-1][-1].append("")
            self._in_cell = True

    def handle_data(self, data):
        self.texts.append(data)
        if self._tag == "title":
            self.title += data
        if self._in_cell:
            self.tables[-1][-1][-1] += data

    def handle_endtag(self, tag):
        self._tag = ""
        if tag in ("td", "th"):
            self._in_cell = False

    def facts(self) -> list[dict[str, str]]:
        """The two-column tables of a log's facts as name -> value, in page order."""
        return [t for t in self.two_columns() if "frames" in t]

    def positions(self) -> list[dict[str, str]]:
        """The two-column tables of where an estimate is (lat/lon, UTM, MGRS, altitude), in page order."""
        return [t for t in self.two_columns() if "MGRS" in t]

    def two_columns(self) -> list[dict[str, str]]:
        return [{row[0]: row[1] for row in tab} for tab in self.tables if tab and len(tab[0]) == 2]

    def summary(self) -> list[dict[str, str]]:
        tab = self.tables[0]
        return [dict(zip(tab[0], row, strict=True)) for row in tab[1:]]


def test_many_logs_give_a_table_and_a_page_and_bad_logs_a_reason(session_log, window_db, tmp_path):
    raw = session_log.log_path.read_bytes()
    logs = tmp_path / "logs"
    logs.mkdir()
    odd = logs / "field #1 a.mcap"  # a space and a '#' in the name: the links must be quoted
    odd.write_bytes(raw)
    truncated = logs / "truncated.mcap"
    truncated.write_bytes(raw[: len(raw) // 2])
    junk = logs / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all\n")
    out = tmp_path / "the report"
    results, page = replay_logs([odd, truncated, junk], window_db, EstimatorConfig(sigma_deg=(0.3, 0.8)), out)
    ok, cut, bad = results
    # sigma is learned from the skyline within the interval the search was given
    assert ok.position is not None and 0.0 < ok.position.result.sigma_deg[0] <= ok.position.result.sigma_deg[1] <= 0.8
    # the truncated log gives what it holds, and says so
    assert not cut.data.complete and 0 < len(cut.data.frames) < 9
    assert "incomplete" in cut.notes[0]
    # and estimates from the frames it has: the columns no frame covers are missing, the rest found
    n = len(cut.data.frames)
    assert cut.skyline is not None and cut.position is not None and cut.error_m is not None
    assert n / 9 - 0.12 < cut.skyline.valid_fraction < n / 9 + 0.12
    assert geodesic_distance_m(cut.position.lat, cut.position.lon, ok.position.lat, ok.position.lon) < 120.0
    assert bad.failure is not None and "not a readable MCAP log" in bad.failure and "\n" not in bad.failure
    rows = list(csv.DictReader((out / "summary.csv").open()))
    # the logs named from the table's folder, so that the folder can be moved with its logs
    assert [r["log"] for r in rows] == ["../logs/field #1 a.mcap", "../logs/truncated.mcap", "../logs/junk.mcap"]
    assert all((out / r["log"]).resolve() == p.resolve() for r, p in zip(rows, [odd, truncated, junk], strict=True))
    assert float(rows[0]["error_m"]) == pytest.approx(ok.error_m, abs=0.05)
    assert rows[0]["valid_azimuths"] == str(int(ok.skyline.valid.sum())) and int(rows[0]["valid_azimuths"]) > 300
    text = page.read_text()
    html_page = Page(text)
    assert html_page.title == "Viper replay of 3 logs"
    assert f"{ok.error_m:.1f} m" in text
    # no absolute path anywhere: the logs outside the report folder by their names alone
    assert str(tmp_path) not in text and "/tmp" not in text
    assert [r["log"] for r in html_page.summary()] == ["field #1 a.mcap", "truncated.mcap", "junk.mcap"]
    files = [link for link in html_page.links if not link.startswith("#")]
    assert "summary.csv" in files
    assert quote("field #1 a.map.png") in files and quote("field #1 a.panorama.png") in files
    assert "field%20%231%20a.replay.mcap" in files
    for link in files:  # every link opens a file of the report folder
        assert "/" not in link and " " not in link and "#" not in link
        assert (out / unquote(link)).is_file()
    for pic in ok.pictures:
        assert pic.stat().st_size > 10_000
    # the session's facts as the log holds them; the truncated log's as far as it goes; none of the junk
    full, part = html_page.facts()
    assert full["frames"] == "9" and full["level"] == "ok" and 0 < int(part["frames"]) < 9
    # where each estimate is, as the summary places it: its MGRS grid reference
    assert [p["MGRS"] for p in html_page.positions()] == [mgrs_ref(r.position.lat, r.position.lon) for r in (ok, cut)]
    assert all(p["altitude"].endswith(" m (the map's vertical datum)") for p in html_page.positions())


def test_the_demos_report_has_its_title_the_frames_and_the_sessions_facts(session_log, window_db, tmp_path):
    title = "Viper demo: a simulated field session"
    page = session_report(session_log, window_db, tmp_path, title)
    doc = Page(page.read_text())
    assert doc.title == title and "Viper replay" not in page.read_text()
    assert str(tmp_path) not in page.read_text()
    (row,) = doc.summary()
    assert row["log"] == session_log.log_path.name
    assert session_log.frames == 9 and row["frames"] == "9"
    assert row["valid_azimuths"] == str(int(session_log.skyline.valid.sum()))
    # the facts against the log read here on its own
    msgs = list(LogReader(session_log.log_path).messages())
    procedures = {m.decode()["procedure"]: m.decode() for m in msgs if m.topic == t.PROCEDURE}
    (facts,) = doc.facts()
    for name in ("level", "compass", "truth"):
        assert facts[name].split(":")[0] == procedures[name]["status"]
    n_fixes = sum(m.topic == t.GPS_FIX for m in msgs)
    truth = procedures["truth"]
    assert n_fixes > 3
    assert facts["GPS fixes"] == f"{n_fixes} received, {truth['used']} averaged, σ {truth['sigma_m']:.1f} m"
    assert truth["sigma_m"] == pytest.approx(session_log.truth.sigma_m)
    first, last = min(m.log_time_ns for m in msgs), max(m.log_time_ns for m in msgs)
    start = dt.datetime.fromtimestamp(first / 1e9, tz=dt.timezone.utc)
    assert facts["session time"] == f"{start:%Y-%m-%d %H:%M:%S} UTC, {(last - first) / 1e9:.0f} s"
    detected = next(m.decode() for m in msgs if m.topic == t.SKYLINE_DETECTED)
    n_valid = sum(v is not None for v in detected["elevation_deg"])
    assert facts["valid azimuths (on board)"] == f"{n_valid} of {len(detected['elevation_deg'])}"
    stem = session_log.log_path.stem
    check_layers(tmp_path, stem, window_db, with_truth=True)
    assert [link for link in doc.links if not link.startswith("#")] == [
        "summary.csv", *(quote(stem + e) for e in MAP_LAYER_SUFFIXES),
        quote(session_log.log_path.name), quote(f"{session_log.log_path.stem}.map.png"),
        quote(f"{session_log.log_path.stem}.map.png"), quote(f"{session_log.log_path.stem}.panorama.png"),
        quote(f"{session_log.log_path.stem}.panorama.png")]


def _degrees(label: str) -> float:
    """'36.580°N' -> 36.58, '84.28°W' -> -84.28."""
    number, hemisphere = label.split("°")
    return float(number) * (-1.0 if hemisphere in ("S", "W") else 1.0)


def test_the_picture_is_in_degrees_with_a_scale_and_a_zoom_on_the_estimate_and_truth(session_log, window_db):
    from matplotlib.offsetbox import AnchoredOffsetbox

    from appliance.outputs.picture import estimate_figure, map_scale

    pos, g = session_log.estimate, window_db.grid
    # a truth 6 m north-east of the estimate: the zoom must show it apart
    scale = map_scale(window_db, pos.lat, pos.lon)
    truth = (pos.lat + 4.24 / scale.m_per_deg_lat, pos.lon + 4.24 / scale.m_per_deg_lon)
    fig = estimate_figure(window_db, pos, session_log.skyline, truth)
    fig.canvas.draw()
    axes = {ax.get_label(): ax for ax in fig.axes}
    rows, cols = np.mgrid[0:g.n_rows, 0:g.n_cols]
    lon, lat = g.xy_to_lonlat(*g.rc_to_xy(rows.ravel(), cols.ravel()))
    main, zoom = axes["map"], axes["zoom"]
    assert main.get_xlim() == pytest.approx((lon.min(), lon.max()))
    assert main.get_ylim() == pytest.approx((lat.min(), lat.max()))
    for ax in (main, zoom):
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        xs = [_degrees(t.get_text()) for t in ax.get_xticklabels() if x0 <= t.get_position()[0] <= x1]
        ys = [_degrees(t.get_text()) for t in ax.get_yticklabels() if y0 <= t.get_position()[1] <= y1]
        assert len(xs) >= 2 and len(ys) >= 2
        # the labels say the tick's own longitude and latitude, inside the map
        assert all(lon.min() - 1e-9 <= x <= lon.max() + 1e-9 for x in xs)
        assert all(lat.min() - 1e-9 <= y <= lat.max() + 1e-9 for y in ys)
        ticks = [t.get_position()[0] for t in ax.get_xticklabels() if x0 <= t.get_position()[0] <= x1]
        assert xs == pytest.approx(ticks, abs=1e-6)
        assert ax.get_xlabel() == "longitude" and ax.get_ylabel() == "latitude"
        bars = [a for a in ax.artists if isinstance(a, AnchoredOffsetbox)]
        assert len(bars) == 1
    (zx0, zx1), (zy0, zy1) = zoom.get_xlim(), zoom.get_ylim()
    for la, lo in ((pos.lat, pos.lon), truth):
        assert zx0 < lo < zx1 and zy0 < la < zy1
    zoom_span_m = (zx1 - zx0) * scale.m_per_deg_lon
    assert zoom_span_m == pytest.approx((zy1 - zy0) * scale.m_per_deg_lat, rel=1e-3)  # square on the ground
    assert 300.0 < zoom_span_m < 1500.0
    assert (zx1 - zx0) < 0.2 * (lon.max() - lon.min())
    assert "6.0 m from the truth" in zoom.get_title()
    # the region's cells drawn in the zoom, each around its own node
    (cells,) = [c for c in zoom.collections if type(c).__name__ == "PolyCollection"]
    paths = cells.get_paths()
    assert len(paths) == pos.result.region_nodes.size
    node_lon, node_lat = g.xy_to_lonlat(*g.node_xy(pos.result.region_nodes))
    for path, x, y in zip(paths, np.ravel(node_lon), np.ravel(node_lat), strict=True):
        assert path.contains_point((x, y))
        assert np.ptp(path.vertices[:, 0]) * scale.m_per_deg_lon == pytest.approx(g.dx_m, rel=0.05)


@pytest.mark.parametrize(("span_m", "bar_m"), [(400.0, 100.0), (5_000.0, 1_000.0), (9_000.0, 2_000.0),
                                                 (45_000.0, 10_000.0), (30.0, 5.0)])
def test_the_scale_bar_is_a_round_length_near_a_quarter_of_the_span(span_m, bar_m):
    from appliance.outputs.picture import length_label, nice_length_m

    assert nice_length_m(span_m) == pytest.approx(bar_m)
    assert length_label(2_000.0) == "2 km" and length_label(500.0) == "500 m"


def test_cli_replay_prints_the_error_and_fails_cleanly_on_junk(session_log, window_db, tmp_path, capsys):
    code = main(["replay", str(session_log.log_path), "--db", window_db.path, "--sigma", "0.2,0.5",
                 "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0 and "error" in out and (tmp_path / "report.html").exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n garbage")
    assert main(["replay", str(junk), "--db", window_db.path, "--out", str(tmp_path / "j")]) == 1
    assert "not a readable MCAP log" in capsys.readouterr().out
    # the replayed log is marked for retention's keep_unreplayed; the unreadable one is not
    marker = session_log.log_path.with_name(session_log.log_path.name + ".replayed")
    assert marker.read_text() == f"replayed into {tmp_path.absolute()}\n"
    assert not junk.with_name("junk.mcap.replayed").exists()
    assert main(["replay", str(junk), "--db", window_db.path, "--sigma", "x"]) != 0
    assert "--sigma" in capsys.readouterr().err


def test_cli_replay_json_is_one_object_that_says_what_the_text_says(session_log, window_db, tmp_path, capsys):
    args = ["replay", str(session_log.log_path), "--db", window_db.path, "--out"]
    assert main([*args, str(tmp_path / "text")]) == 0
    text = capsys.readouterr().out
    assert main([*args, str(tmp_path / "json"), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    obj = json.loads(out[0])
    (log,) = obj["logs"]
    assert log["traverse"] is False and log["frames"] == 9 and log["failure"] is None
    e = log["estimate"]
    line = next(x for x in text.splitlines() if x.startswith(f"{session_log.log_path}: "))
    assert f"{e['lat']:.6f}, {e['lon']:.6f}" in line and f"error {log['error_m']:.1f} m" in line
    assert f"(onboard {log['onboard_error_m']:.1f} m)" in line and log["status"] in line
    assert e["error_m"] == pytest.approx(log["error_m"])
    assert log["onboard_error_m"] == pytest.approx(session_log.error_m)
    assert obj["report"] == str(tmp_path / "json" / "report.html") and (tmp_path / "json" / "report.html").exists()
