"""``viper replay`` of a traverse's log: stop by stop, each stop's own frames and truth, fused through the
odometry as on board; the odometry from a PX4 ULog instead; ``--json`` on replay and capture."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import re

import numpy as np
import pytest
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from mcap.reader import make_reader

from appliance.acquisition.replay import replay_logs
from appliance.acquisition.replay_traverse import read_traverse
from appliance.cli.main import main
from appliance.config import EstimatorConfig
from appliance.drivers.ulog_position import LocalPositions, displacements, read_local_positions, ulog_problem
from appliance.errors import InputError
from appliance.logbook import topics as t
from tests.conftest import data_file

STOPS = 3
PX4_SAMPLE = "imu_magnetometer/px4_sample.ulg"


@pytest.fixture(scope="module")
def traverse(field_traverse):
    """What ``viper demo --traverse 3`` runs (:func:`run_field_traverse`), at the tests' quick settings."""
    result, _, _ = field_traverse
    assert len(result.stops) == STOPS and all(s.position is not None for s in result.stops)
    return result


@pytest.fixture(scope="module")
def replayed(traverse, window_db, tmp_path_factory):
    """``viper replay LOG --json`` of the traverse: the object printed."""
    out = tmp_path_factory.mktemp("replay-json")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["replay", str(traverse.log_path), "--db", str(window_db.path), "--out", str(out), "--json"])
    assert code == 0
    text = buf.getvalue()
    assert len(text.strip().splitlines()) == 1  # one JSON object, nothing else on stdout
    return json.loads(text), out


def test_the_log_is_read_stop_by_stop(traverse):
    log = read_traverse(traverse.log_path)
    assert log.is_traverse and len(log.stops) == STOPS
    for logged, onboard in zip(log.stops, traverse.stops, strict=True):
        assert len(logged.data.frames) == onboard.session.frames > 0
        assert logged.data.truth == pytest.approx(onboard.truth)
        assert logged.session_id == onboard.session.session_id
    assert [len(s.odometry) for s in log.stops] == [0, 1, 1]
    assert [s.odometry[0].stop_id for s in log.stops[1:]] == [1, 2]


def test_each_replayed_stop_matches_its_onboard_error_within_a_metre(traverse, replayed):
    obj, out = replayed
    assert obj["traverse"] is True and len(obj["stops"]) == STOPS
    for stop, onboard in zip(obj["stops"], traverse.stops, strict=True):
        assert stop["fused"] == onboard.fused
        assert stop["truth"] == {"lat": pytest.approx(onboard.truth[0]), "lon": pytest.approx(onboard.truth[1])}
        # the onboard error of the traverse that ran, not what the replay read of it
        assert abs(stop["position"]["error_m"] - onboard.error_m) < 1.0
        assert abs(stop["alone"]["error_m"] - onboard.error_alone_m) < 1.0
        if onboard.odometry is not None:
            assert stop["odometry"]["east_m"] == pytest.approx(onboard.odometry.east_m)
            assert stop["odometry"]["north_m"] == pytest.approx(onboard.odometry.north_m)
    # the results log holds the fused stops on the onboard topics
    with open(out / f"{traverse.log_path.stem}.replay.mcap", "rb") as f:
        msgs = [(ch.topic, m.data) for _, ch, m in make_reader(f).iter_messages()]
    fixes = [LocationFix.FromString(d) for topic, d in msgs if topic == t.ESTIMATE_FIX]
    assert [f.latitude for f in fixes] == pytest.approx([s["position"]["lat"] for s in obj["stops"]])
    assert [f.longitude for f in fixes] == pytest.approx([s["position"]["lon"] for s in obj["stops"]])
    assert sum(topic == t.TRAVERSE_STOP for topic, _ in msgs) == STOPS


def test_the_report_says_traverse_and_lists_each_stops_coordinates(replayed):
    obj, out = replayed
    html = (out / "report.html").read_text()
    assert "a traverse of 3 stops" in html and 'src="track.png"' in html
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == STOPS
    for row, stop in zip(rows, obj["stops"], strict=True):
        assert float(row["lat"]) == pytest.approx(stop["position"]["lat"], abs=1e-6)
        assert float(row["lon"]) == pytest.approx(stop["position"]["lon"], abs=1e-6)
        assert float(row["truth_lat"]) == pytest.approx(stop["truth"]["lat"], abs=1e-6)
        assert float(row["onboard: error (m)"]) == pytest.approx(stop["onboard_error_m"], abs=0.051)


def test_the_text_output_says_what_the_json_says(traverse, window_db, replayed, tmp_path, capsys):
    obj, _ = replayed
    code = main(["replay", str(traverse.log_path), "--db", str(window_db.path), "--out", str(tmp_path / "text")])
    out = capsys.readouterr().out
    assert code == 0 and "a traverse of 3 stops, replayed stop by stop" in out
    for stop in obj["stops"]:
        line = next(x for x in out.splitlines() if f": stop {stop['stop']}: " in x)
        p = stop["position"]
        assert f"{p['lat']:.6f}, {p['lon']:.6f}" in line and f"error {p['error_m']:.1f} m" in line
        assert f"(onboard {stop['onboard_error_m']:.1f} m)" in line and p["status"] in line


def test_a_traverse_among_other_logs_is_not_blended(traverse, window_db, tmp_path):
    results, _ = replay_logs([traverse.log_path, traverse.log_path], window_db, EstimatorConfig(), tmp_path)
    assert all(r.position is None and "replay it on its own" in (r.failure or "") for r in results)


# ------------------------------------------------------------------------------------------- PX4 ULog
def test_the_ulog_positions_are_pyulogs_own():
    from pyulog import ULog

    path = data_file(PX4_SAMPLE)
    pos = read_local_positions(path)
    ds = ULog(str(path)).get_dataset("vehicle_local_position")
    stamps = ds.data["timestamp"]
    assert len(pos.time_us) == len(stamps) == 678
    assert pos.span_us == (int(stamps[0]), int(stamps[-1]))
    np.testing.assert_array_equal(pos.eph_m, ds.data["eph"].astype(float))
    assert pos.boot_utc_us is None  # a bench log: no GPS time


def test_a_truncated_ulog_is_one_line_and_non_zero(traverse, window_db, tmp_path, capsys):
    whole = data_file(PX4_SAMPLE).read_bytes()
    assert ulog_problem(whole) is None
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(whole[:2_000_000])
    out = tmp_path / "out"
    code = main(["replay", str(traverse.log_path), "--db", str(window_db.path), "--out", str(out),
                 "--odometry-log", str(cut), "--odometry-time-offset", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "cut.ulg" in err[0] and "truncated" in err[0]
    assert not out.exists()


def test_a_ulog_without_valid_positions_is_refused_in_one_line(traverse, window_db, tmp_path, capsys):
    """The sample is a bench log: its local position never valid; the first stop placed 150 s after boot."""
    first_ns = read_traverse(traverse.log_path).stops[0].time_ns
    code = main(["replay", str(traverse.log_path), "--db", str(window_db.path), "--out", str(tmp_path / "o"),
                 "--odometry-log", str(data_file(PX4_SAMPLE)), "--odometry-time-offset", f"{first_ns / 1e9 - 150:.6f}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "xy_valid false" in err[0]


def _positions(north, east, eph, valid=None, reset=None) -> LocalPositions:
    n = len(north)
    return LocalPositions(data_file(PX4_SAMPLE), np.arange(n, dtype=np.int64) * 1_000_000, np.array(north, float),
                          np.array(east, float), np.array(eph, float),
                          np.ones(n, bool) if valid is None else np.array(valid, bool),
                          np.zeros(n, np.int64) if reset is None else np.array(reset, np.int64), None)


def test_displacements_between_stop_times_interpolate_the_local_position():
    # samples at 0, 1, 2, 3 s after boot; NED: x north, y east
    pos = _positions([0.0, 10.0, 30.0, 30.0], [0.0, 0.0, 40.0, 100.0], [3.0, 3.0, 4.0, 4.0])
    boot_ns = 1_700_000_000 * 10**9
    legs = displacements(pos, [boot_ns, boot_ns + 1_500_000_000, boot_ns + 3_000_000_000], boot_ns)
    assert [leg.stop_id for leg in legs] == [1, 2]
    # at 1.5 s: north 20, east 20, eph 3.5
    assert (legs[0].north_m, legs[0].east_m) == pytest.approx((20.0, 20.0))
    assert legs[0].sigma_m == pytest.approx(np.hypot(3.0, 3.5))
    assert (legs[1].north_m, legs[1].east_m) == pytest.approx((10.0, 80.0))
    assert legs[1].receive_time_ns == boot_ns + 3_000_000_000
    with pytest.raises(InputError, match="outside its vehicle_local_position samples"):
        displacements(pos, [boot_ns, boot_ns + 4_000_000_000], boot_ns)
    with pytest.raises(InputError, match="reset between stop 0 and stop 1"):
        displacements(_positions([0, 1, 2, 3], [0, 0, 0, 0], [1] * 4, reset=[0, 0, 1, 1]),
                      [boot_ns, boot_ns + 3_000_000_000], boot_ns)
    with pytest.raises(InputError, match="xy_valid false"):
        displacements(_positions([0, 1, 2, 3], [0, 0, 0, 0], [1] * 4, valid=[1, 0, 1, 1]),
                      [boot_ns + 500_000_000, boot_ns + 3_000_000_000], boot_ns)


# ------------------------------------------------------------------------------------------- capture
def test_capture_json_is_one_object_with_the_logs_estimate(tmp_path, capsys, window_db):
    cfg = tmp_path / "sim.toml"
    cfg.write_text(
        '[platform]\nkind = "sim"\n'
        f'[session]\ndatabase = "{window_db.path}"\ntruth_duration_s = 10.0\nsettle_s = 0.2\n'
        "[devices.camera]\nwidth = 320\nheight = 240\n[sim]\ntime_rate = 50.0\n"
    )
    code = main(["capture", "--config", str(cfg), "--log-dir", str(tmp_path / "logs"), "--seed", "5", "--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 0 and len(out) == 1
    obj = json.loads(out[0])
    (log,) = (tmp_path / "logs").glob("*.mcap")
    assert obj["log"] == str(log) and obj["status"] in ("ok", "ambiguous") and obj["frames"] > 0
    with open(log, "rb") as f:
        fix = next(LocationFix.FromString(m.data) for _, ch, m in make_reader(f).iter_messages()
                   if ch.topic == t.ESTIMATE_FIX)
    assert (obj["estimate"]["lat"], obj["estimate"]["lon"]) == pytest.approx((fix.latitude, fix.longitude))
    assert obj["estimate"]["error_m"] == pytest.approx(obj["error_m"])
    assert re.fullmatch(r"[0-9a-f]{8}", obj["session_id"])
