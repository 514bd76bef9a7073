"""sd_notify against a real AF_UNIX datagram socket, as systemd listens."""

from __future__ import annotations

import os
import socket

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
    assert n.enabled and n.watchdog_s == pytest.approx(30.0)
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


def _nothing_arrived(sock: socket.socket) -> bool:
    sock.setblocking(False)
    try:
        sock.recv(4096)
    except BlockingIOError:
        return True
    finally:
        sock.settimeout(2.0)
    return False


def test_without_systemd_everything_is_a_no_op_and_foreign_watchdog_is_ignored(listener, monkeypatch):
    path, sock = listener
    # the process's own environment names a listening socket: an explicit empty one must not fall back to it
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "30000000")
    n = Notifier.from_environment({})
    assert not n.enabled and n.watchdog_s is None
    n.ready(status="idle")
    n.watchdog()
    n.status("capture 1/2")
    n.stopping()
    assert n._sock is None  # no socket was even opened
    assert _nothing_arrived(sock)

    # a watchdog meant for another process (WATCHDOG_PID) is ignored; the notifications still go out
    foreign = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}
    other = Notifier.from_environment(foreign, pid=2)
    assert other.enabled and other.watchdog_usec is None and other.watchdog_s is None
    other.ready()
    assert sock.recv(4096) == b"READY=1"
    other.close()
    assert _nothing_arrived(sock)
    assert Notifier.from_environment(foreign, pid=1).watchdog_s == pytest.approx(0.001)  # ours: kept


def test_errors_are_device_errors(tmp_path):
    with pytest.raises(DeviceError, match="cannot send"):
        Notifier(str(tmp_path / "nobody-listens.sock")).ready()
    with pytest.raises(DeviceError, match="one line"):
        Notifier(str(tmp_path / "x")).status("two\nlines")
    with pytest.raises(DeviceError, match="WATCHDOG_USEC"):
        Notifier.from_environment({"WATCHDOG_USEC": "soon"})


class RecordingNotifier:
    """The Notifier's interface, recording what was sent."""

    def __init__(self, watchdog_s: float | None) -> None:
        self.watchdog_s = watchdog_s
        self.sent: list[dict] = []

    def notify(self, **fields) -> None:
        self.sent.append(fields)

    def ready(self, status=None) -> None:
        self.notify(READY=1)

    def watchdog(self) -> None:
        self.notify(WATCHDOG=1)

    def stopping(self, status=None) -> None:
        self.notify(STOPPING=1)


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def silent_daemon(tmp_path, step_timeout_s: float, watchdog_margin: float = 0.5):
    from appliance.acquisition.daemon import SessionDaemon
    from appliance.config import Config, SessionConfig

    cfg = Config(session=SessionConfig(max_sessions=1, step_timeout_s=step_timeout_s,
                                       watchdog_margin=watchdog_margin))
    clock, notifier = FakeClock(), RecordingNotifier(20.0)

    def never_called(*_):
        raise AssertionError("no session runs in this test")

    d = SessionDaemon(cfg, tmp_path, notifier, never_called, clock=clock)  # type: ignore[arg-type]
    return d, clock, notifier


def test_heartbeat_feeds_the_watchdog_while_a_step_is_within_its_timeout(tmp_path):
    d, clock, notifier = silent_daemon(tmp_path, step_timeout_s=60.0)
    d._status("estimate...")  # the session's last word before a long silent step
    for silent_s in (0.0, 10.0, 59.999, 60.0):
        clock.now_s = 1000.0 + silent_s
        assert d.feed_watchdog(), silent_s
    assert notifier.sent.count({"WATCHDOG": 1}) == 4


def test_heartbeat_stops_when_a_step_hangs_beyond_its_timeout(tmp_path):
    d, clock, notifier = silent_daemon(tmp_path, step_timeout_s=0.2)
    d._status("estimate...")
    clock.now_s = 1000.0 + 0.2 + 1e-6
    assert not d.feed_watchdog()
    assert {"WATCHDOG": 1} not in notifier.sent
    # progress reported again: the watchdog is fed again
    d._status("capture 3")
    assert d.feed_watchdog()


def test_heartbeat_period_is_the_margin_of_systemds_timeout(tmp_path):
    d, _, _ = silent_daemon(tmp_path, step_timeout_s=60.0, watchdog_margin=0.25)
    assert d.watchdog_interval_s == pytest.approx(0.25 * 20.0)
    d.notifier.watchdog_s = None
    assert d.watchdog_interval_s is None
