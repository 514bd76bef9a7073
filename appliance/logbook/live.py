"""The live view: a Foxglove WebSocket server carrying the session's log as it is written.

The logbook hands every message it writes (topic, schema, encoded bytes, log time) to a
:class:`Publisher`; :class:`LiveServer` forwards them on channels of the same topics and schemas,
so Foxglove shows live exactly what it later shows from the MCAP file.  Most topics are written
once or rarely (the calibration, the panorama, the estimate), so the server latches: a client that
subscribes to a topic is sent its latest message at once (for ``foxglove.FrameTransform``, the
latest of each child frame); clients already subscribed see that message once more.  The server is
off unless ``--live [HOST:]PORT`` is given, and binds to 127.0.0.1 unless a host is named.

Whoever reaches the port sees every topic (camera frames, panorama, position, log lines) without
authentication, and may send anything.  The SDK logs what a client does wrong, quoting what it sent;
those records pass through :class:`ClientTextGuard`, so a client cannot write a journal line of its
own: each becomes one line of printable ASCII (:func:`printable`), at most a warning, and at most
:data:`CLIENT_LINES_PER_WINDOW` of them per :data:`CLIENT_WINDOW_S` seconds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from appliance.errors import InputError, LogError
from appliance.extras import require

LOG = logging.getLogger(__name__)
DEFAULT_HOST = "127.0.0.1"
#: the Python loggers the foxglove SDK (and its WebSocket library) log through
SDK_LOGGERS = ("foxglove", "tungstenite")
#: the longest SDK line passed on (characters, after escaping); it quotes what a client sent
SDK_LINE_CHARS = 200
CLIENT_LINES_PER_WINDOW = 20
CLIENT_WINDOW_S = 10.0


def printable(text: str, limit: int = 80) -> str:
    r"""``text`` as one line of printable ASCII for a log line: line ends, escape sequences and every
    other character outside printable ASCII escaped as ``ascii()`` does (``\n``, ``\x1b``,
    ``\xe9``); longer than ``limit`` characters, it is cut there and says how long it was.

    >>> printable("op\n\x1b[31mred")
    'op\\n\\x1b[31mred'
    >>> printable("A" * 1000, limit=4)
    'AAAA... (1000 characters)'
    """
    escaped = "".join(c if " " <= c <= "~" else ascii(c)[1:-1] for c in text)
    if len(escaped) <= limit:
        return escaped
    return f"{escaped[:limit]}... ({len(text)} characters)"


class ClientTextGuard(logging.Handler):
    """Passes the SDK's log records on to this module's logger as one printable line each (at most
    :data:`SDK_LINE_CHARS` long), at most at WARNING (a misbehaving client is not the appliance's
    error), and at most ``per_window`` lines per ``window_s`` seconds; the next line after a window
    in which lines were left out says how many."""

    def __init__(self, per_window: int = CLIENT_LINES_PER_WINDOW, window_s: float = CLIENT_WINDOW_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.per_window, self.window_s, self._clock = per_window, window_s, clock
        self._window_start = clock()
        self._sent = 0
        self._dropped = 0

    def emit(self, record: logging.LogRecord) -> None:
        """Called under the handler's lock (:meth:`logging.Handler.handle`)."""
        try:
            text = printable(record.getMessage(), SDK_LINE_CHARS)
        except Exception:  # a record whose arguments do not format: say so rather than fail
            text = f"unformattable record from {record.name}"
        now = self._clock()
        if now - self._window_start >= self.window_s:
            if self._dropped:
                LOG.warning("live view: %d more lines of the WebSocket server left out", self._dropped)
            self._window_start, self._sent, self._dropped = now, 0, 0
        if self._sent >= self.per_window:
            self._dropped += 1
            return
        self._sent += 1
        LOG.log(min(record.levelno, logging.WARNING), "live view: %s", text)


def guard_sdk_logs() -> None:
    """Route the SDK's loggers through one :class:`ClientTextGuard` (once per process)."""
    for name in SDK_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(h, ClientTextGuard) for h in logger.handlers):
            logger.addHandler(_GUARD)
        logger.propagate = False


class Publisher(Protocol):
    """Receives each message the logbook writes, already encoded."""

    def publish(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                message_encoding: str, data: bytes, log_time_ns: int) -> None: ...


def parse_address(text: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (``[::1]:PORT`` for IPv6) as (host, port); the host defaults to 127.0.0.1."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host = DEFAULT_HOST
    host = host.strip("[]") or DEFAULT_HOST
    try:
        port = int(port_text)
    except ValueError:
        raise InputError(f"--live {text!r}: expected [HOST:]PORT with a numeric port") from None
    if not 0 <= port <= 65535:
        raise InputError(f"--live {text!r}: port {port} is outside 0..65535")
    return host, port


class LiveServer:
    """A Foxglove WebSocket server (foxglove-sdk) with one channel per topic the logbook writes.

    Channels are created on first use and kept across sessions (the daemon runs many sessions on
    one server); port 0 picks a free port, read back from :attr:`port`.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = 8765, name: str = "viper") -> None:
        # deferred: foxglove-sdk is the [live] extra, needed only when --live is given
        foxglove = require("foxglove", "the live view (--live)")
        guard_sdk_logs()
        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._lock = threading.Lock()
        self._channels: dict[str, Any] = {}
        self._latest: dict[str, dict[str, tuple[bytes, int]]] = {}
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                 server_listener=_latch_listener(self))
        except Exception as exc:  # the SDK raises its own error types for a busy or invalid address
            raise LogError(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.host = host
        self.port = int(self._server.port)
        LOG.info("live view: ws://%s:%d (Foxglove: Open connection, Foxglove WebSocket)", host, self.port)

    def publish(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                message_encoding: str, data: bytes, log_time_ns: int) -> None:
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                schema = self._foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
                channel = self._foxglove.Channel(topic, schema=schema, message_encoding=message_encoding,
                                                 context=self._context)
                self._channels[topic] = channel
            self._latest.setdefault(topic, {})[_latch_key(schema_name, data)] = (bytes(data), int(log_time_ns))
        channel.log(data, log_time=int(log_time_ns))

    def resend_latest(self, topic: str) -> None:
        """Send the latest message(s) of ``topic`` again (to its subscribers)."""
        with self._lock:
            channel = self._channels.get(topic)
            latest = list(self._latest.get(topic, {}).values())
        if channel is not None:
            for data, log_time_ns in sorted(latest, key=lambda item: item[1]):
                channel.log(data, log_time=log_time_ns)

    def close(self) -> None:
        self._server.stop()
        for channel in self._channels.values():
            channel.close()
        self._channels.clear()

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _latch_key(schema_name: str, data: bytes) -> str:
    """What a latched message replaces: the previous one of its topic, or of its child frame for a transform."""
    if schema_name == "foxglove.FrameTransform":
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

        return FrameTransform.FromString(data).child_frame_id
    return ""


def _latch_listener(server: LiveServer) -> Any:
    """The server listener: a new subscription gets the topic's latest message."""
    from foxglove.websocket import ServerListener

    class Latch(ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            server.resend_latest(channel.topic)

    return Latch()


_GUARD = ClientTextGuard()
