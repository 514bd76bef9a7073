"""A PTU that does not answer at boot: the session daemon stays up in a degraded state, retries with a
doubling wait, reports it (STATUS=, one stderr line when the fault starts and ends, the next session's
log) and runs sessions once the unit answers.  The unit is the PTU twin on a real pty, the driver the
real one, the daemon the real ``viper daemon session`` (or :class:`SessionDaemon` in this process)."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from appliance.acquisition.daemon import SessionDaemon
from appliance.acquisition.notify import Notifier
from appliance.cli._platform import session_runner
from appliance.config import SimConfig, load_config
from appliance.logbook import LogReader
from appliance.logbook import topics as t
from appliance.sim.platform import make_world
from appliance.sim.ptu_twin import PtuTwin
from appliance.sim.pty_port import PtyPort

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def silent_ptu(tmp_path):
    """A PTU twin on a pty that answers nothing until its ``silent`` flag is cleared (a unit powering up)."""
    port = PtyPort(tmp_path / "ptu")
    twin = PtuTwin(make_world(SimConfig(ground_elevation_m=300.0)), port, silent=True)
    twin.start()
    yield twin
    twin.stop()
    port.close()


def hardware_config(tmp_path: Path, stage_source: Path, extra: str = "") -> Path:
    """A hardware platform with only the stage; no I2C bus, GPS or camera (their absence degrades the session)."""
    cfg = tmp_path / "viper.toml"
    cfg.write_text(
        '[platform]\nkind = "hardware"\n[session]\ninterval_s = 3600.0\n' + extra +
        f'[devices.stage]\nsource = "{stage_source}"\ntimeout_s = 0.3\n'
        '[devices.compass]\nkind = "nmea"\n[devices.inclinometer]\nkind = "nmea"\n'
    )
    return cfg


@pytest.fixture
def notify_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(30.0)
    yield path, sock
    sock.close()


def statuses_until(sock: socket.socket, pattern: str, seen: list[str]) -> str:
    """Receive datagrams (kept in ``seen``) until a STATUS= matches ``pattern``; returns that status."""
    while True:
        for line in sock.recv(4096).decode().splitlines():
            if line.startswith("STATUS="):
                seen.append(line[7:])
                if re.search(pattern, line[7:]):
                    return line[7:]


def log_lines(path: Path) -> list[str]:
    return [m.decode().message for m in LogReader(path).messages() if m.topic == t.LOG]


def test_daemon_waits_for_a_silent_ptu_then_runs_sessions(tmp_path, silent_ptu, notify_socket):
    sock_path, sock = notify_socket
    cfg = hardware_config(tmp_path, silent_ptu.port.path)
    logs = tmp_path / "logs"
    env = dict(os.environ, NOTIFY_SOCKET=sock_path, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "appliance.cli.main", "daemon", "session", "--config", str(cfg), "--log-dir", str(logs)],
        env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    seen: list[str] = []
    try:
        degraded = statuses_until(sock, r"^degraded", seen)
        assert "PTU: no answer within 0.3 s" in degraded and "attempt 1 failed, next in 2 s" in degraded
        assert proc.poll() is None  # the silent unit did not end the daemon
        assert not list(logs.glob("*.mcap"))  # no session ran: no log
        silent_ptu.silent = False  # the unit has powered up
        done = statuses_until(sock, r"^session 1 \w+ \(", seen)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and out == ""
    # the session ran on the stage (no compass, GPS or camera here: degraded, but logged)
    (log,) = logs.glob("viper-*.mcap")
    assert done.endswith(log.name) and "session 1 degraded" in done
    first = log_lines(log)[0]
    assert re.fullmatch(r"devices: did not answer for \d+ s before this session \(1 failed attempt\); "
                        r"last: PTU: no answer within 0\.3 s", first), first
    # one line when the fault began, one when it ended; nothing else from the daemon
    lines = err.splitlines()
    assert [x for x in lines if "devices" in x] == [
        "devices do not answer: PTU: no answer within 0.3 s; degraded, trying again after 2 s, then up to every 60 s",
        lines[-1],
    ]
    assert re.fullmatch(r"devices answer again after \d+ s \(1 failed attempt\); sessions resume", lines[-1])


def test_the_wait_between_attempts_doubles_up_to_its_cap(tmp_path, silent_ptu, notify_socket):
    sock_path, sock = notify_socket
    config = load_config(hardware_config(tmp_path, silent_ptu.port.path, "max_sessions = 1\n"))
    daemon = SessionDaemon(config, tmp_path / "logs", Notifier(sock_path), session_runner(config),
                           retry_s=(0.05, 0.2))
    exit_code: list[int] = []
    thread = threading.Thread(target=lambda: exit_code.append(daemon.run()), daemon=True)
    thread.start()
    seen: list[str] = []
    try:
        statuses_until(sock, r"attempt 5 failed", seen)
        assert thread.is_alive() and daemon.outage is not None and daemon.outage.attempts == 5
        silent_ptu.silent = False
        statuses_until(sock, r"^session 1 \w+ \(", seen)
    finally:
        daemon.request_stop()
        thread.join(timeout=30)
    waits = [float(w) for s in seen for w in re.findall(r"next in ([0-9.]+) s", s)]
    # a busy machine may fail one more attempt before the unit's answer arrives
    assert waits[:5] == [0.05, 0.1, 0.2, 0.2, 0.2] and set(waits[5:]) <= {0.2}
    assert exit_code == [0] and daemon.outage is None and len(daemon.results) == 1
    note = log_lines(daemon.results[0].log_path)[0]
    assert re.fullmatch(rf"devices: did not answer for \d+ s before this session \({len(waits)} failed attempts\); "
                        r"last: PTU: no answer within 0\.3 s", note), note
