"""sd_notify against a real AF_UNIX datagram socket, as systemd listens."""

from __future__ import annotations

import os
import socket
import time
import types

import numpy as np
import pytest

from appliance.acquisition.notify import Notifier
from appliance.errors import DeviceError


@pytest.fixture
def listener(tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def test_ready_watchdog_status_stopping_arrive_as_datagrams(listener):
    path, sock = listener
    n = Notifier.from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "30000000"})
    assert n.enabled and n.watchdog_interval_s == pytest.approx(15.0)
    n.ready(status="idle, next session in 60 s")
    n.watchdog()
    n.status("capture 3/12")
    n.stopping()
    got = [sock.recv(4096).decode() for _ in range(4)]
    n.close()
    assert got == [
        "READY=1\nSTATUS=idle, next session in 60 s",
        "WATCHDOG=1",
        "STATUS=capture 3/12",
        "STOPPING=1",
    ]


def test_abstract_socket_address():
    name = f"viper-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        Notifier(f"@{name}").ready()
        assert sock.recv(100) == b"READY=1"
    finally:
        sock.close()


def test_without_systemd_everything_is_a_no_op_and_foreign_watchdog_is_ignored():
    n = Notifier.from_environment({})
    assert not n.enabled and n.watchdog_interval_s is None
    n.ready()
    n.watchdog()
    other = Notifier.from_environment(
        {"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}, pid=2
    )
    assert other.watchdog_interval_s is None


def test_errors_are_device_errors(tmp_path):
    with pytest.raises(DeviceError, match="cannot send"):
        Notifier(str(tmp_path / "nobody-listens.sock")).ready()
    with pytest.raises(DeviceError, match="one line"):
        Notifier(str(tmp_path / "x")).status("two\nlines")
    with pytest.raises(DeviceError, match="WATCHDOG_USEC"):
        Notifier.from_environment({"WATCHDOG_USEC": "soon"})


class RecordingNotifier:
    """The Notifier's interface, recording when each field was sent."""

    def __init__(self, interval_s: float) -> None:
        self.watchdog_interval_s = interval_s
        self.sent: list[tuple[float, dict]] = []

    def notify(self, **fields) -> None:
        self.sent.append((time.monotonic(), fields))

    def ready(self, status=None) -> None:
        self.notify(READY=1)

    def watchdog(self) -> None:
        self.notify(WATCHDOG=1)

    def stopping(self, status=None) -> None:
        self.notify(STOPPING=1)


def run_daemon_with_a_silent_step(monkeypatch, tmp_path, step_s: float, step_timeout_s: float):
    import appliance.acquisition.daemon as daemon_mod
    from appliance.acquisition.daemon import SessionDaemon
    from appliance.config import Config, SessionConfig

    def long_session(config, log_dir, should_stop, on_status, publisher=None):
        on_status("estimate...")
        start = time.monotonic()
        time.sleep(step_s)  # a long step that reports nothing (building a database, say)
        return types.SimpleNamespace(error_m=None, frames=0, status=types.SimpleNamespace(value="ok"),
                                     log_path=tmp_path / "x.mcap", start=start)

    monkeypatch.setattr(daemon_mod, "run_one_session", long_session)
    notifier = RecordingNotifier(0.05)
    cfg = Config(session=SessionConfig(max_sessions=1, step_timeout_s=step_timeout_s))
    d = SessionDaemon(cfg, tmp_path, notifier)  # type: ignore[arg-type]
    assert d.run() == 0
    status_t = next(t for t, f in notifier.sent if f.get("STATUS") == "estimate...")
    return [t - status_t for t, f in notifier.sent if f == {"WATCHDOG": 1}]


def test_heartbeat_feeds_the_watchdog_through_a_long_step(monkeypatch, tmp_path):
    pings = run_daemon_with_a_silent_step(monkeypatch, tmp_path, step_s=1.0, step_timeout_s=60.0)
    during = [p for p in pings if 0 < p < 1.0]
    # every 0.05 s for 1 s: about 20 pings, none more than a few intervals apart
    assert len(during) >= 10 and max(np.diff([0.0, *during, 1.0])) < 0.5


def test_heartbeat_stops_when_a_step_hangs_beyond_its_timeout(monkeypatch, tmp_path):
    pings = run_daemon_with_a_silent_step(monkeypatch, tmp_path, step_s=1.0, step_timeout_s=0.2)
    during = [p for p in pings if 0 < p < 1.0]
    assert during and max(during) < 0.35  # fed for 0.2 s of silence, then left to expire
