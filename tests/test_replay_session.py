"""``viper replay``: the estimate rerun from a session log's raw data, the report, and bad logs."""

from __future__ import annotations

import csv

import pytest

from appliance.acquisition.replay import read_session, replay_logs, replay_session
from appliance.bodies import geodesic_distance_m
from appliance.cli.main import main
from appliance.config import EstimatorConfig
from appliance.logbook import topics as t
from appliance.logbook.summary import summarize_log
from appliance.sim.field_session import run_field_session
from tests.conftest import small_config


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


def test_many_logs_give_a_table_and_a_page_and_bad_logs_a_reason(session_log, window_db, tmp_path):
    raw = session_log.log_path.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(raw[: len(raw) // 2])
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all\n")
    results, page = replay_logs([session_log.log_path, truncated, junk], window_db,
                                EstimatorConfig(sigma_deg=(0.3, 0.8)), tmp_path / "out")
    ok, cut, bad = results
    assert ok.position is not None and ok.position.result.sigma_deg == (0.3, 0.8)
    # the truncated log gives what it holds, and says so
    assert not cut.data.complete and 0 < len(cut.data.frames) < 9
    assert "incomplete" in cut.notes[0]
    assert bad.failure is not None and "not a readable MCAP log" in bad.failure and "\n" not in bad.failure
    rows = list(csv.DictReader((tmp_path / "out" / "summary.csv").open()))
    assert [r["log"] for r in rows] == [str(session_log.log_path), str(truncated), str(junk)]
    assert float(rows[0]["error_m"]) == pytest.approx(ok.error_m, abs=0.05)
    text = page.read_text()
    assert "summary.csv" in text and f"{ok.error_m:.1f} m" in text
    for pic in ok.pictures:
        assert pic.stat().st_size > 10_000 and pic.name in text


def test_cli_replay_prints_the_error_and_fails_cleanly_on_junk(session_log, window_db, tmp_path, capsys):
    code = main(["replay", str(session_log.log_path), "--db", window_db.path, "--sigma", "0.2,0.5",
                 "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0 and "error" in out and (tmp_path / "report.html").exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n garbage")
    assert main(["replay", str(junk), "--db", window_db.path, "--out", str(tmp_path / "j")]) == 1
    assert "not a readable MCAP log" in capsys.readouterr().out
    assert main(["replay", str(junk), "--db", window_db.path, "--sigma", "x"]) != 0
    assert "--sigma" in capsys.readouterr().err
