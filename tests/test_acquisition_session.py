"""Whole simulated sessions on the jacksboro DEM: the log, the estimate, and the faults."""

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
from appliance.acquisition.session import run_field_session
from appliance.acquisition.simulated import SimFaults
from appliance.config import Config, SessionConfig
from appliance.logbook import LogReader
from appliance.logbook import topics as t
from appliance.logbook.summary import great_circle_m, summarize_log

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dem():
    from appliance.terrain.dem import load_dem

    return load_dem("jacksboro")


def small_config() -> Config:
    return Config(session=SessionConfig(search_radius_m=150.0, search_step_m=150.0, truth_duration_s=10.0))


def test_whole_session_logs_everything_and_estimates(tmp_path, dem):
    from appliance.terrain.horizon import render_skyline

    r = run_field_session(small_config(), tmp_path, seed=5, dem=dem)
    assert r.status is Status.OK and r.problems == []
    assert {k: v for k, v in r.outcomes.items() if k != "true_position"} == {
        "level": "ok",
        "compass": "ok",
        "truth": "ok",
        "capture": "ok",
        "estimate": "ok",
    }
    s = summarize_log(r.log_path)
    assert s.complete
    counts = {k: v.count for k, v in s.topics.items()}
    assert counts[t.IMAGE] == 9 and counts[t.CAPTURE] == 9 and counts[t.GPS_TRUTH] == 1
    assert counts[t.GPS_FIX] >= 9 and counts[t.ESTIMATE_FIX] == 1 and counts[t.POSTERIOR] == 1
    # the estimate's error is the distance between the logged estimate and the logged truth
    assert s.error_m == pytest.approx(
        great_circle_m(s.estimate["lat"], s.estimate["lon"], s.truth["lat"], s.truth["lon"]), abs=0.01
    )
    assert s.error_m < 300.0  # a 3x3 grid of 150 m around a prior within 75 m of the truth
    # the skyline detected in the stitched panorama matches the one rendered at the true position
    lat, lon = map(float, r.outcomes["true_position"].split(","))
    ref = render_skyline(dem, lat, lon, 1.5, azimuths_deg=r.skyline.azimuth_deg).elevation_deg
    d = np.abs(r.skyline.elevation_deg - ref)
    assert np.isfinite(d).mean() > 0.6 and float(np.nanmedian(d)) < 0.1
    assert float(np.mean(d[np.isfinite(d)] < 0.3)) > 0.8


def test_unplugged_camera_degrades_and_keeps_frames(tmp_path, dem):
    r = run_field_session(
        small_config(),
        tmp_path,
        seed=6,
        dem=dem,
        faults=SimFaults(camera_unplugged_after=4, gps_silent=True, tilt_unplugged=True),
    )
    assert r.status is Status.DEGRADED
    assert r.outcomes["capture"] == "degraded" and r.outcomes["truth"] == "degraded"
    assert r.outcomes["level"] == "failed" and r.error_m is None
    assert any("unplugged" in p for p in r.problems)
    reader = LogReader(r.log_path)
    images = [msg for msg in reader.messages() if msg.topic == t.IMAGE]
    assert reader.complete and len(images) == 4


def test_stop_request_closes_the_log_with_the_frames_so_far(tmp_path, dem):
    frames = []

    def status(text):
        if text.startswith("capture "):
            frames.append(text)

    r = run_field_session(
        small_config(), tmp_path, seed=7, dem=dem, should_stop=lambda: len(frames) >= 3, on_status=status
    )
    assert r.stopped and r.frames == 3
    s = summarize_log(r.log_path)
    assert s.complete and s.topics[t.IMAGE].count == 3


def test_daemon_notifies_and_finishes_the_file_on_sigterm(tmp_path):
    sock_path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(30.0)
    cfg = tmp_path / "viper.toml"
    cfg.write_text("[session]\nsearch_radius_m = 150.0\nsearch_step_m = 150.0\ninterval_s = 3600.0\n")
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
