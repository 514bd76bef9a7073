"""The live view's edges without a session (a whole session's delivery is in test_live_view.py): a real
client offering only the old subprotocol, and the log lines its retries cause; the kernel's count of
unacknowledged bytes the server's linger waits on; the linger option's bad value."""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from pathlib import Path

from appliance.cli.main import main
from appliance.logbook import live as live_mod
from appliance.logbook.live import SDK_LOGGERS, ClientTextGuard, LiveServer
from appliance.logbook.live_drain import unsent_bytes, wait_drained
from tests.live_client import StrictClient

REPO = Path(__file__).resolve().parents[1]


def _wait(condition, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    return condition()


def test_a_client_offering_only_the_old_subprotocol_is_refused_once_in_the_log_and_the_readme_says_so(
        caplog, monkeypatch):
    import websockets

    guard = ClientTextGuard()
    for name in SDK_LOGGERS:
        monkeypatch.setattr(logging.getLogger(name), "handlers", [guard])
    monkeypatch.setattr(live_mod, "_GUARD", guard)
    attempts = 30

    async def old_client(port: int) -> int:
        try:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"]):
                return 101
        except websockets.InvalidStatus as exc:
            return exc.response.status_code

    with caplog.at_level(logging.INFO, logger="appliance.logbook.live"):
        server = LiveServer("127.0.0.1", 0, linger_s=0.0, channels=[])
        codes = [asyncio.run(old_client(server.port)) for _ in range(attempts)]
        _wait(lambda: guard.received >= attempts, 30.0)
        server.close()
    assert codes == [400] * attempts
    lines = [r.getMessage() for r in caplog.records if "handshake failed" in r.getMessage()]
    assert len(lines) == 2, lines
    assert lines[0].startswith("live view: Dropping client 127.0.0.1:") and "foxglove.sdk.v1" in lines[0]
    assert lines[1].startswith(f"live view: {attempts - 1} more like 'Dropping client <client>: handshake failed'")
    readme = (REPO / "README.md").read_text()
    live_paragraph = readme[readme.index("Live view:"):].split("\n\n", 1)[0]
    assert "`foxglove.sdk.v1`" in live_paragraph and "`foxglove.websocket.v1`" in live_paragraph


def test_unsent_bytes_counts_what_the_peer_has_not_acknowledged(tmp_path):
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    peer = socket.create_connection(("127.0.0.1", port))
    conn, _ = listener.accept()
    try:
        assert unsent_bytes(port) == 0
        conn.setblocking(False)
        sent = 0
        try:
            while True:  # until the peer's receive buffer and this send buffer are full
                sent += conn.send(b"x" * 65536)
        except BlockingIOError:
            pass
        assert _wait(lambda: (unsent_bytes(port) or 0) > 0, 10.0)
        assert unsent_bytes(port) <= sent
        assert not wait_drained(port, 0.2, busy=lambda: True)  # a subscribed client that reads nothing
        got = 0
        while got < sent:
            got += len(peer.recv(1 << 20))
        assert got == sent
        assert _wait(lambda: unsent_bytes(port) == 0, 10.0)
        assert wait_drained(port, 10.0, busy=lambda: True)
        assert unsent_bytes(port + 1 if port < 65535 else port - 1) == 0
        assert unsent_bytes(port, tables=(tmp_path / "no-such-table",)) is None
    finally:
        for s in (conn, peer, listener):
            s.close()


def test_a_negative_linger_is_one_line_and_non_zero(capsys, tmp_path):
    code = main(["capture", "--log-dir", str(tmp_path), "--live", "0", "--live-linger", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0
    assert err[-1].startswith("viper capture: error: --live-linger -1.0"), err
    assert not list(tmp_path.iterdir())


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_lines_differing_only_in_the_clients_address_are_counted_not_repeated(caplog):
    clock = _Clock()
    guard = ClientTextGuard(per_window=100, window_s=10.0, clock=clock, repeat_window_s=60.0)
    sdk = logging.getLogger("foxglove.test-repeats")
    sdk.propagate = False
    sdk.addHandler(guard)
    try:
        with caplog.at_level(logging.INFO, logger="appliance.logbook.live"):
            for i in range(5):
                clock.now = float(i)
                sdk.error("Dropping client 10.0.0.%d:%d: handshake failed", i, 40000 + i)
            sdk.error("Invalid message from [::1]:5000: `x`")
            clock.now = 61.0
            sdk.error("Dropping client 10.0.0.9:1: handshake failed")
            sdk.error("Invalid message from [::1]:5001: `x`")
            guard.flush()
            for i in range(live_mod.REPEAT_SHAPES + 10):  # lines a client makes all different
                sdk.error("Invalid message from 10.0.0.1:1: `%d`", i)
                sdk.error("Invalid message from 10.0.0.1:2: `%d`", i)
            assert len(guard._repeats) == live_mod.REPEAT_SHAPES
            guard.flush()
    finally:
        sdk.removeHandler(guard)
    lines = [r.getMessage() for r in caplog.records]
    hint = " (the server speaks the foxglove.sdk.v1 subprotocol only; a client offering only foxglove.websocket.v1 " \
           "is refused)"
    assert lines[:5] == [
        "live view: Dropping client 10.0.0.0:40000: handshake failed" + hint,
        "live view: Invalid message from [::1]:5000: `x`",
        "live view: 4 more like 'Dropping client <client>: handshake failed' in 61 s",
        "live view: Dropping client 10.0.0.9:1: handshake failed" + hint,
        "live view: 1 more like 'Invalid message from <client>: `x`' in 57 s",  # within its window: counted
    ]
    distinct = lines[5:]
    assert len([x for x in distinct if x.startswith("live view: Invalid message from 10.0.0.1:1: ")]) == \
        live_mod.REPEAT_SHAPES + 10
    assert len([x for x in distinct if "1 more like 'Invalid message from <client>: `" in x]) == \
        live_mod.REPEAT_SHAPES + 10


def test_a_topic_that_comes_in_another_encoding_is_advertised_anew(tmp_path):
    from appliance.logbook.live_channels import ChannelSpec, json_schema_data

    spec = ChannelSpec("/session/info", "viper.Session", "jsonschema", json_schema_data("viper.Session"), "json")
    with LiveServer("127.0.0.1", 0, linger_s=0.0, channels=[spec]) as server:
        watching = StrictClient(server.port)
        watching.start()
        assert _wait(lambda: list(server.subscriptions().values()) == [{"/session/info"}])
        # a ROS 2 log's String message: another schema and encoding on the same topic
        server.publish("/session/info", "std_msgs/msg/String", "ros2msg", b"string data", "cdr", b"\x00\x01", 5)
        late = StrictClient(server.port)
        late.start()
        assert _wait(lambda: late.counts()["/session/info"] == 1, 30.0)
        assert _wait(lambda: any(ch["encoding"] == "cdr" for ch in watching.channels.values()), 30.0)
    for client in (watching, late):
        client.finish()
        assert client.error is None, client.error
    assert [(ch["topic"], ch["schemaName"], ch["encoding"]) for ch in late.channels.values()] == [
        ("/session/info", "std_msgs/msg/String", "cdr")]
    assert late.payloads("/session/info") == [b"\x00\x01"] and late.refused() == []
