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
