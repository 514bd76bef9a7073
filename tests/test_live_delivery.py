"""Every message of a session reaches every live-view client: a real WebSocket client connected
before the first message, subscribing once to each channel as it is advertised, against the session's
MCAP log read back by the ``mcap`` reader; a second client joining mid-session; a client offering
only the old subprotocol; the kernel's count of unacknowledged bytes the server's linger waits on."""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader

from appliance.cli.main import main
from appliance.logbook import live as live_mod
from appliance.logbook import topics as t
from appliance.logbook.live import SDK_LOGGERS, ClientTextGuard, LiveServer
from appliance.logbook.live_channels import session_channels
from appliance.logbook.live_drain import unsent_bytes, wait_drained
from appliance.sim.field_session import run_field_session
from tests.conftest import small_config
from tests.live_client import StrictClient

REPO = Path(__file__).resolve().parents[1]
ALL_TOPICS = {spec.topic for spec in session_channels()}
#: the second client joins once the first has received this many camera frames
JOIN_AFTER_FRAMES = 3


def _wait(condition, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    return condition()


@pytest.fixture(scope="module")
def delivered(tmp_path_factory, dem, window_db):
    out = tmp_path_factory.mktemp("delivery")
    server = LiveServer("127.0.0.1", 0, linger_s=30.0)
    first = StrictClient(server.port)
    first.start()
    # the first client is subscribed to every channel before the session writes anything
    assert _wait(lambda: any(topics == ALL_TOPICS for topics in server.subscriptions().values()))
    second = StrictClient(server.port)

    def join_later() -> None:
        if _wait(lambda: first.counts()[t.IMAGE] >= JOIN_AFTER_FRAMES, 300.0):
            second.start()

    joiner = threading.Thread(target=join_later, daemon=True)
    joiner.start()
    try:
        result, _ = run_field_session(small_config(), out, seed=7, dem=dem, db=window_db, publisher=server)
    finally:
        server.close()  # lingers until both clients have everything
    for client in (first, second):
        assert client.closed.wait(30.0)  # the server closed the connection
        client.finish()
        assert client.error is None, client.error
    joiner.join(1.0)
    with open(result.log_path, "rb") as f:
        log = [(channel, message) for _s, channel, message in make_reader(f).iter_messages(log_time_order=False)]
    return log, first, second, result.log_path


def _by_topic(pairs):
    payloads: dict[str, list[bytes]] = {}
    for topic, data in pairs:
        payloads.setdefault(topic, []).append(data)
    return payloads


def test_a_client_connected_from_the_start_receives_every_message_once(delivered):
    log, first, _, _ = delivered
    logged = _by_topic((channel.topic, bytes(message.data)) for channel, message in log)
    received = _by_topic((topic, data) for topic, _, data in first.messages)
    assert first.refused() == [] and first.statuses == []
    assert {topic: len(v) for topic, v in received.items()} == {topic: len(v) for topic, v in logged.items()}
    assert received == logged  # the same bytes, in the order written
    # the topics written last (the estimate, its region and posterior, the rendered skyline, the
    # session's end) are among them: nothing was cut off when the server closed
    for topic in (t.ESTIMATE_FIX, t.ESTIMATE_RECORD, t.POSTERIOR, t.REGION, t.SKYLINE_DETECTED,
                  t.SKYLINE_RENDERED, t.SESSION, t.PROCEDURE, t.LOG):
        assert logged.get(topic), topic
    procedures = [p for p in logged[t.PROCEDURE] if b'"procedure":"estimate"' in p]
    assert procedures and received[t.PROCEDURE][-1] == logged[t.PROCEDURE][-1]


def test_every_channel_was_advertised_once_with_the_logs_schema(delivered):
    _, first, _, log_path = delivered
    advertised = Counter(ch["topic"] for ch in first.channels.values())
    assert advertised == Counter(ALL_TOPICS)
    specs = {spec.topic: spec for spec in session_channels()}
    seen = {}
    with open(log_path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        seen[channel.topic] = (schema.name, schema.encoding, bytes(schema.data), channel.message_encoding)
    for topic, found in seen.items():
        spec = specs[topic]
        assert found == (spec.schema_name, spec.schema_encoding, spec.schema_data, spec.message_encoding), topic


def test_a_client_joining_mid_session_gets_the_latest_once_and_then_everything(delivered):
    log, first, second, _ = delivered
    logged = _by_topic((channel.topic, bytes(message.data)) for channel, message in log)
    received = _by_topic((topic, data) for topic, _, data in second.messages)
    assert second.refused() == [] and second.statuses == []
    # it joined after the third frame: it has the latest frame then and every later one, no earlier one
    assert 0 < len(received[t.IMAGE]) <= len(logged[t.IMAGE]) - JOIN_AFTER_FRAMES + 1
    for topic, payloads in received.items():
        if topic == t.TF:  # latched per child frame: the latest of each, then every later one
            continue
        assert payloads == logged[topic][-len(payloads):], topic
    # a topic written once, before it joined, came to it once (the latched copy)
    assert received[t.CALIBRATION] == logged[t.CALIBRATION]
    assert received[t.SESSION] == logged[t.SESSION][-1:]
    assert set(logged[t.TF]) >= set(received[t.TF])


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
