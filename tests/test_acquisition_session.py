"""Whole simulated sessions on the jacksboro DEM, on the real drivers over the twins: the log, the
estimate by the real estimator, and the faults."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.acquisition.procedures import Status
from appliance.bodies import geodesic_distance_m
from appliance.config import SimFaultsConfig
from appliance.logbook import LogReader
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.summary import summarize_log
from appliance.sim.field_session import run_field_session
from tests.conftest import small_config

REPO = Path(__file__).resolve().parents[1]


def test_whole_session_logs_everything_and_estimates(tmp_path, dem, window_db):
    from appliance.terrain.horizon import render_skyline

    r, sim_truth = run_field_session(small_config(), tmp_path, seed=5, dem=dem, db=window_db)
    assert r.estimate is not None
    # an estimate that may be wrong never says "ok": the session's status follows the estimate's
    flag = "ambiguous" if r.estimate.result.ambiguous else "ok"
    assert r.status.value == flag
    assert r.outcomes == {
        "level": "ok",
        "compass": "ok",
        "truth": "ok",
        "capture": "ok",
        "estimate": flag,
    }
    expected = [f"estimate: {'; '.join(r.estimate.result.notes)}"] if flag == "ambiguous" else []
    assert r.problems == expected
    s = summarize_log(r.log_path)
    assert s.complete
    counts = {k: v.count for k, v in s.topics.items()}
    assert counts[t.IMAGE] == 9 and counts[t.CAPTURE] == 9 and counts[t.GPS_TRUTH] == 1
    assert counts[t.GPS_FIX] >= 5 and counts[t.ESTIMATE_FIX] == 1 and counts[t.POSTERIOR] == 1
    assert counts[t.REGION] == 1 and counts[t.ESTIMATE_RECORD] == 1 and counts[t.PANORAMA] == 1
    lat, lon = sim_truth.lat_deg, sim_truth.lon_deg
    # the GPS truth averages the twin's fixes (sigma 2 m) around the true position
    assert geodesic_distance_m(s.truth["lat"], s.truth["lon"], lat, lon) < 3.0
    # the estimate's error is the distance between the logged estimate and the logged truth
    assert s.error_m == pytest.approx(
        geodesic_distance_m(s.estimate["lat"], s.estimate["lon"], s.truth["lat"], s.truth["lon"]), abs=0.01
    )
    # the database's nodes are 75 m x 92 m apart: the estimate falls within two nodes of the truth
    assert s.error_m < 150.0
    assert r.estimate is not None and s.estimate["region"]["n_cells"] == r.estimate.result.region_nodes.size
    # the region and the posterior are Foxglove messages of the database's grid
    msgs = {msg.topic: msg for msg in LogReader(r.log_path).messages()}
    grid = m.grid_values(msgs[t.POSTERIOR].decode())
    assert grid.shape == (window_db.grid.n_rows, window_db.grid.n_cols)
    best_row = window_db.grid.n_rows - 1 - r.estimate.result.node // window_db.grid.n_cols
    assert float(grid[best_row, r.estimate.result.node % window_db.grid.n_cols]) == pytest.approx(grid.max())
    assert '"region"' in msgs[t.REGION].decode().geojson
    # the skyline detected in the stitched panorama matches the one rendered at the true position
    ref = render_skyline(dem, lat, lon, 1.5, azimuths_deg=r.skyline.azimuth_deg).elevation_deg
    d = np.abs(r.skyline.elevation_deg - ref)
    assert np.isfinite(d).mean() > 0.6 and float(np.nanmedian(d)) < 0.2
    assert float(np.mean(d[np.isfinite(d)] < 0.4)) > 0.8


def test_unplugged_camera_silent_gps_and_no_inclinometer_degrade_and_keep_frames(tmp_path, dem, window_db):
    faults = SimFaultsConfig(camera_unplug_after=4, gps_unplug_at_s=0.0, gps_replug_after_s=1e6,
                             inclinometer_absent=True)
    r, _ = run_field_session(small_config(), tmp_path, seed=6, dem=dem, db=window_db, faults=faults)
    assert r.status is Status.DEGRADED
    assert r.outcomes["capture"] == "degraded" and r.outcomes["truth"] == "degraded"
    assert r.outcomes["level"] == "degraded" and r.error_m is None
    assert any("unplugged" in p for p in r.problems) and any("no inclinometer" in p for p in r.problems)
    reader = LogReader(r.log_path)
    images = [msg for msg in reader.messages() if msg.topic == t.IMAGE]
    assert reader.complete and len(images) == 4


def test_stop_request_closes_the_log_with_the_frames_so_far(tmp_path, dem, window_db):
    frames = []

    def status(text):
        if text.startswith("capture "):
            frames.append(text)

    r, _ = run_field_session(
        small_config(), tmp_path, seed=7, dem=dem, db=window_db, should_stop=lambda: len(frames) >= 3,
        on_status=status,
    )
    assert r.stopped and r.frames == 3
    s = summarize_log(r.log_path)
    assert s.complete and s.topics[t.IMAGE].count == 3


def test_daemon_notifies_and_finishes_the_file_on_sigterm(tmp_path, window_db):
    sock_path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(30.0)
    cfg = tmp_path / "viper.toml"
    cfg.write_text(
        f"[session]\ninterval_s = 3600.0\ntruth_duration_s = 5.0\ndatabase = \"{window_db.path}\"\n"
        "[sim]\ntime_rate = 50.0\n[devices.camera]\nwidth = 160\nheight = 120\n"
    )
    logs = tmp_path / "logs"
    env = dict(os.environ, NOTIFY_SOCKET=sock_path, WATCHDOG_USEC="20000000")
    proc = subprocess.Popen(
        [sys.executable, "-m", "appliance.cli.main", "daemon", "session", "--config", str(cfg), "--log-dir", str(logs)],
        env=env,
        cwd=REPO,
        stderr=subprocess.PIPE,
        text=True,
    )
    got = []
    try:
        while True:
            msg = sock.recv(4096).decode()
            got.append(msg)
            if "STATUS=capture 2" in msg:
                proc.send_signal(signal.SIGTERM)
            if "STOPPING=1" in msg:
                break
        assert proc.wait(timeout=60) == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    assert got[0].startswith("READY=1") and any("WATCHDOG=1" in g for g in got)
    (log,) = logs.glob("viper-*.mcap")
    s = summarize_log(log)
    assert s.complete and 2 <= s.topics[t.IMAGE].count < 9
    logs_text = [m.decode().message for m in LogReader(log).messages() if m.topic == t.LOG]
    assert any("stopped on request" in x for x in logs_text)
