"""A rover's traverse on the simulated platform: the rover twin drives between stops and sends its
odometry over a real pty, each stop after the first is fused with the previous stop's transported
posterior, and the log, read back by the independent ``mcap`` reader, holds the whole track."""

from __future__ import annotations

import datetime as dt
import json
import math
import time

import numpy as np
import pytest
from foxglove_schemas_protobuf.GeoJSON_pb2 import GeoJSON
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from mcap.reader import make_reader

from appliance.acquisition.platform import Platform
from appliance.acquisition.session import Session, SessionResult
from appliance.acquisition.session_facts import read_session_facts
from appliance.acquisition.traverse import Traverse, TraverseResult, estimate_flag
from appliance.cli.main import main
from appliance.config import Config, TraverseConfig
from appliance.drivers.odometry import OdometryReport, format_line
from appliance.drivers.odometry_reader import open_odometry
from appliance.estimator import transport_prior
from appliance.locating.position import truth_error_m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimClock
from tests.conftest import rover_config_text
from tests.test_gis_outputs import check_layers

jsonschema = pytest.importorskip("jsonschema")

STOPS = 3


@pytest.fixture(scope="module")
def traverse(field_traverse, window_db):
    result, truths, out = field_traverse
    assert len(result.stops) == STOPS
    return result, truths, window_db, out


def _messages(path):
    with open(path, "rb") as f:
        yield from make_reader(f).iter_messages()


def test_every_stop_is_estimated_and_fused_after_the_first(traverse):
    r, truths, db, _ = traverse
    assert isinstance(r, TraverseResult) and len(r.stops) == len(truths) == STOPS
    assert [s.fused for s in r.stops] == [False] + [True] * (STOPS - 1)
    assert [s.odometry.stop_id if s.odometry else None for s in r.stops] == [None, 1, 2]
    for s, tr in zip(r.stops, truths, strict=True):
        assert s.position is not None and s.alone is not None
        # the database's nodes are 75 m x 92 m apart: each stop within two nodes of where the rover stood
        assert truth_error_m(db, s.position, (tr.lat_deg, tr.lon_deg)) < 150.0
        assert s.truth is not None and truth_error_m(db, s.position, s.truth) == pytest.approx(s.error_m)
    # the rover really drove: legs of 200-400 m between consecutive true stops
    for a, b in zip(truths, truths[1:]):
        from appliance.bodies import geodesic_distance_m

        assert 190.0 < geodesic_distance_m(a.lat_deg, a.lon_deg, b.lat_deg, b.lon_deg) < 410.0


def test_a_fused_stop_takes_the_previous_posterior_moved_by_the_odometry(traverse):
    r, truths, db, _ = traverse
    g = db.grid
    for prev, s in zip(r.stops, r.stops[1:]):
        odo = s.odometry
        # independently: the previous posterior shifted by the reported move (jacksboro's grid is
        # geographic: grid north is true north) and blurred by its sigma
        expected = transport_prior(prev.position.result.posterior_map, g.n_rows, g.n_cols, g.dx_m, g.dy_m,
                                   odo.east_m, odo.north_m, odo.sigma_m)
        np.testing.assert_allclose(s.log_prior, expected, atol=1e-9)
        # the prior's peak is where the previous estimate lands when moved by the odometry (to a node)
        moved_lat = prev.position.lat + math.degrees(odo.north_m / 6_371_008.8)
        moved_lon = prev.position.lon + math.degrees(odo.east_m / (6_371_008.8 * math.cos(math.radians(moved_lat))))
        from appliance.bodies import geodesic_distance_m

        assert geodesic_distance_m(*s.prior_peak, moved_lat, moved_lon) < math.hypot(g.dx_m, g.dy_m)
        # the prior can only narrow the region, and the estimate alone is kept beside the fused one
        assert s.position.result.region_nodes.size <= s.alone.result.region_nodes.size
        assert s.session.estimate_alone is s.alone and s.error_alone_m is not None
        # the prior weighs: the fused posterior is the alone one times the prior, renormalised
        alone_post, fused_post = s.alone.result.posterior_map, s.position.result.posterior_map
        peak = int(np.argmax(fused_post))
        assert fused_post[peak] >= alone_post[peak] * 0.999


def test_the_log_holds_the_whole_track(traverse):
    r, _, db, _ = traverse
    fixes, alone_fixes, truths, tracks, stops, odometry = [], [], [], [], [], []
    for _schema, channel, message in _messages(r.log_path):
        if channel.topic == t.ESTIMATE_FIX:
            fixes.append(LocationFix.FromString(message.data))
        elif channel.topic == t.ESTIMATE_ALONE_FIX:
            alone_fixes.append(LocationFix.FromString(message.data))
        elif channel.topic == t.GPS_TRUTH:
            truths.append(LocationFix.FromString(message.data))
        elif channel.topic == t.TRAVERSE_TRACK:
            tracks.append(json.loads(GeoJSON.FromString(message.data).geojson))
        elif channel.topic == t.TRAVERSE_STOP:
            stops.append(json.loads(message.data))
        elif channel.topic == t.ODOMETRY:
            odometry.append(json.loads(message.data))
    assert [(f.latitude, f.longitude) for f in fixes] == [(s.position.lat, s.position.lon) for s in r.stops]
    assert [(f.latitude, f.longitude) for f in alone_fixes] == [(s.alone.lat, s.alone.lon) for s in r.stops[1:]]
    assert [(f.latitude, f.longitude) for f in truths] == [s.truth for s in r.stops]
    assert [o["stop_id"] for o in odometry] == [1, 2]
    assert len(tracks) == STOPS - 1  # a line needs two stops
    lines = {f["properties"]["name"]: f for f in tracks[-1]["features"]}
    assert lines["estimates"]["geometry"]["coordinates"] == [[s.position.lon, s.position.lat] for s in r.stops]
    assert lines["truth"]["geometry"]["coordinates"] == [[s.truth[1], s.truth[0]] for s in r.stops]
    for f in tracks[-1]["features"]:
        assert f["geometry"]["type"] == t.GEOJSON_FEATURE_GEOMETRY["track"] and f["properties"]["stops"] == STOPS
        assert not list(jsonschema.Draft202012Validator(t.GEOJSON_FEATURE_PROPERTIES["track"])
                        .iter_errors(f["properties"]))
    # every stop's flag is honest: the region decides it, in the record as in the session's estimate
    for rec, s in zip(stops, r.stops, strict=True):
        assert rec["stop"] == s.stop and rec["fused"] == s.fused
        assert rec["position"]["status"] == estimate_flag(db, s.position, s.truth)
        assert rec["alone"]["status"] == estimate_flag(db, s.alone, s.truth)
        assert rec["position"]["region_cells"] == s.position.result.region_nodes.size
        if s.position.result.ambiguous:
            assert rec["position"]["status"] == "ambiguous"


def test_every_json_message_of_the_traverse_log_matches_its_channel_schema(traverse):
    r, *_ = traverse
    checked: dict[str, int] = {}
    for schema, channel, message in _messages(r.log_path):
        if channel.message_encoding != "json":
            continue
        spec = json.loads(schema.data)
        assert spec["additionalProperties"] is False
        errors = [e.message for e in jsonschema.Draft202012Validator(spec).iter_errors(json.loads(message.data))]
        assert not errors, f"{channel.topic}: {errors}"
        checked[channel.topic] = checked.get(channel.topic, 0) + 1
    assert checked[t.TRAVERSE_STOP] == STOPS and checked[t.ODOMETRY] == STOPS - 1
    assert checked[t.ESTIMATE_RECORD] == STOPS and checked[t.PROCEDURE] >= 5 * STOPS


def test_the_report_shows_the_track_and_every_stop(traverse):
    from appliance.outputs.report import write_traverse_report

    r, _, db, out = traverse
    page = write_traverse_report(r, db, out / "report", "traverse", read_session_facts(r.log_path))
    html = page.read_text()
    assert 'src="track.png"' in html and (out / "report" / "track.png").stat().st_size > 10_000
    for s in r.stops:
        assert f'id="stop-{s.stop}"' in html and (out / "report" / f"stop-{s.stop:02d}.png").exists()
        check_layers(out / "report", f"stop-{s.stop:02d}", db, with_truth=True)
    assert str(out) not in html  # no absolute paths
    # the last stop's status first, before any table or picture
    last = r.stops[-1]
    banner = html.index('<div class="banner ')
    assert banner < html.index("<table") and banner < html.index("<img")
    assert f"stop {last.stop} (the last located): {last.position.lat:.6f}, {last.position.lon:.6f}" in html


def test_the_report_gives_each_stop_its_own_session_facts(traverse):
    from appliance.outputs.report import stop_rows

    r, _, db, _ = traverse
    # each stop's truth procedure, as the log records it, in stop order
    truths = [json.loads(m.data) for _, ch, m in _messages(r.log_path)
              if ch.topic == t.PROCEDURE and json.loads(m.data).get("procedure") == "truth"]
    rows = stop_rows(db, r.stops)
    assert len(truths) == len(rows) == STOPS
    for row, s in zip(rows, r.stops, strict=True):  # where each stop's (fused) estimate is
        assert (float(row["lat"]), float(row["lon"])) == pytest.approx((s.position.lat, s.position.lon), abs=1e-6)
    for row, p in zip(rows, truths, strict=True):
        assert row["truth"] == p["status"]
        assert row["GPS fixes averaged, σ (m)"] == f"{p['used']}, {p['sigma_m']:.1f}"
        assert row["frames"] != "0" and row["valid azimuths"].endswith(" of 360")
    # the log-wide table keeps only what the whole log holds: no one stop's procedures
    facts = dict(read_session_facts(r.log_path).rows(one_session=False))
    assert "truth" not in facts and "level" not in facts and "valid azimuths (on board)" not in facts
    assert int(facts["frames"]) == sum(s.session.frames for s in r.stops)


def _bare_traverse(tmp_path, clock, reader, timeout_s=600.0):
    config = Config(traverse=TraverseConfig(stops=3, odometry_timeout_s=timeout_s))
    platform = Platform(clock, None, None, None, None, None, None, odometry=reader)
    log = Logbook.create(tmp_path / "t.mcap")
    result = TraverseResult(tmp_path / "t.mcap", "test")
    trav = Traverse(platform, log, config, None, result, 3, lambda: False, lambda s: None, lambda i: None)
    head = Session(platform, log, config, None, SessionResult(result.log_path, "test"))
    return trav, head, log


def test_a_lost_odometry_line_breaks_the_fusion_chain(tmp_path):
    from appliance.locating.position import Move

    port = PtyPort(tmp_path / "odometry")
    reader = open_odometry(str(port.path), read_timeout_s=0.05)
    trav, head, log = _bare_traverse(tmp_path, SimClock(dt.datetime(2026, 6, 1)), reader)
    try:
        port.write(format_line(OdometryReport(1, 100.0, 0.0, 10.0)))
        assert trav.next_odometry(head).stop_id == 1 and trav.moved == Move(100.0, 0.0, 10.0)
        port.write(format_line(OdometryReport(3, 0.0, 50.0, 10.0)))  # the line of stop 2 was lost
        assert trav.next_odometry(head).stop_id == 3
        assert trav.moved is None and "stop 2 missing" in trav.note
        stop = trav.prepare_stop(2, None)
        assert not stop.fused and "not fused across the gap" in stop.fusion_note
        # two lines waiting at once (the rover drove on): added up, sigmas in quadrature
        port.write(format_line(OdometryReport(4, 10.0, 0.0, 3.0)) + format_line(OdometryReport(5, 20.0, 5.0, 4.0)))
        time.sleep(0.1)
        rep = trav.next_odometry(head)
        assert (rep.stop_id, rep.east_m, rep.north_m, rep.sigma_m) == (5, 30.0, 5.0, 5.0)
    finally:
        log.close()
        reader.close()
        port.close()


def test_no_odometry_within_the_timeout_ends_the_traverse(tmp_path):
    port = PtyPort(tmp_path / "odometry")
    reader = open_odometry(str(port.path), read_timeout_s=0.05)
    trav, head, log = _bare_traverse(tmp_path, SimClock(dt.datetime(2026, 6, 1), time_rate=100.0), reader,
                                     timeout_s=5.0)
    try:
        assert trav.next_odometry(head) is None
    finally:
        log.close()
        reader.close()
        port.close()
    assert any("no odometry line within 5 s" in p for p in head.result.problems)


@pytest.mark.parametrize("argv,fragment", [
    (["demo", "--traverse", "0"], "--traverse 0: expected a number of stops in 1..1000"),
    (["demo", "--traverse", "2", "--skyline-only"], "cannot be combined with --skyline-only"),
])
def test_bad_traverse_options_are_one_line_and_non_zero(capsys, tmp_path, argv, fragment):
    code = main([*argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and fragment in err[0]


def test_capture_runs_a_rovers_traverse_from_the_command_line(tmp_path, capsys, window_db):
    """`viper capture` with `[traverse] stops = 2` on the simulated platform: one log holding both
    stops, the second fused with the first, as the daemon's sessions run it."""
    cfg = tmp_path / "rover.toml"
    cfg.write_text(rover_config_text(window_db.path))
    logs = tmp_path / "logs"
    code = main(["capture", "--config", str(cfg), "--log-dir", str(logs), "--seed", "3"])
    out = capsys.readouterr().out
    assert code == 0, out
    (log,) = logs.glob("*.mcap")
    assert f"log: {log}" in out
    stops = [json.loads(m.data) for _, ch, m in _messages(log) if ch.topic == t.TRAVERSE_STOP]
    assert [s["stop"] for s in stops] == [0, 1]
    assert [s["fused"] for s in stops] == [False, True]
    assert stops[1]["odometry"]["stop_id"] == 1
    # within two of the database's 75 m x 92 m cells of the GPS truth
    assert all(s["position"] is not None and s["position"]["error_m"] < 150.0 for s in stops)
