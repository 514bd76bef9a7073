"""The live view: a Foxglove WebSocket server carrying the session's log as it is written.

The logbook hands every message it writes (topic, schema, encoded bytes, log time) to a
:class:`Publisher`; :class:`LiveServer` forwards them on channels of the same topics and schemas,
so Foxglove shows live exactly what it later shows from the MCAP file.  Every channel a session may
write is advertised from the start (:mod:`appliance.logbook.live_channels`), so a client connected
before the first message is sent every message.  Most topics are written once or rarely (the
calibration, the panorama, the estimate), so the server latches: a client that subscribes to a topic
is sent its latest message at once (for ``foxglove.FrameTransform``, the latest of each child frame),
and only that client.  On close the server lingers, a bounded while, until its clients have received
what was queued for them (:mod:`appliance.logbook.live_drain`).  The server is off unless ``--live
[HOST:]PORT`` is given, and binds to 127.0.0.1 unless a host is named.

The server speaks the ``foxglove.sdk.v1`` WebSocket subprotocol only (foxglove-sdk's handshake offers
no other): a client that offers only ``foxglove.websocket.v1`` is refused with HTTP 400.

Whoever reaches the port sees every topic (camera frames, panorama, position, log lines) without
authentication, and may send anything.  The SDK logs what a client does wrong, quoting what it sent;
those records pass through :class:`ClientTextGuard`, so a client cannot write a journal line of its
own: each becomes one line of printable ASCII (:func:`printable`), at most a warning, at most
:data:`CLIENT_LINES_PER_WINDOW` of them per :data:`CLIENT_WINDOW_S` seconds, and a line repeated
with only the client's address changed (a client retrying a refused handshake) once per
:data:`REPEAT_WINDOW_S` seconds, followed by how many times it came.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from appliance.errors import InputError, LogError
from appliance.extras import require
from appliance.logbook.live_channels import ChannelSpec, session_channels
from appliance.logbook.live_drain import wait_drained

LOG = logging.getLogger(__name__)
DEFAULT_HOST = "127.0.0.1"
#: the Python loggers the foxglove SDK (and its WebSocket library) log through
SDK_LOGGERS = ("foxglove", "tungstenite")
#: the longest SDK line passed on (characters, after escaping); it quotes what a client sent
SDK_LINE_CHARS = 200
CLIENT_LINES_PER_WINDOW = 20
CLIENT_WINDOW_S = 10.0
#: a line repeated with only a client's address changed is passed on once per this many seconds
REPEAT_WINDOW_S = 60.0
#: the most distinct lines whose repeats are counted at once (a client controls what the lines quote)
REPEAT_SHAPES = 64
#: how long a closing server waits at most for its clients to receive what is queued (s)
DEFAULT_LINGER_S = 2.0
#: the subprotocol foxglove-sdk's server accepts (its handshake refuses any other with HTTP 400)
SUBPROTOCOL = "foxglove.sdk.v1"
_ADDRESS = re.compile(r"\[[0-9A-Fa-f:.]+\]:\d+|\d{1,3}(?:\.\d{1,3}){3}:\d+")
_HANDSHAKE_HINT = (f" (the server speaks the {SUBPROTOCOL} subprotocol only; a client offering only "
                   "foxglove.websocket.v1 is refused)")


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
    in which lines were left out says how many.  A line that differs from an earlier one only in the
    client's address is passed on once per ``repeat_window_s`` seconds; the next one after that
    window (or :meth:`flush`) says how many came in between."""

    def __init__(self, per_window: int = CLIENT_LINES_PER_WINDOW, window_s: float = CLIENT_WINDOW_S,
                 clock: Callable[[], float] = time.monotonic, repeat_window_s: float = REPEAT_WINDOW_S) -> None:
        super().__init__()
        self.per_window, self.window_s, self._clock = per_window, window_s, clock
        self.repeat_window_s = repeat_window_s
        self._window_start = clock()
        self._sent = 0
        self._dropped = 0
        self._repeats: dict[str, tuple[float, int]] = {}  # line's shape -> (when passed on, repeats since)
        self.received = 0

    def emit(self, record: logging.LogRecord) -> None:
        """Called under the handler's lock (:meth:`logging.Handler.handle`)."""
        self.received += 1
        try:
            text = printable(record.getMessage(), SDK_LINE_CHARS)
        except Exception:  # a record whose arguments do not format: say so rather than fail
            text = f"unformattable record from {record.name}"
        now = self._clock()
        shape = _ADDRESS.sub("<client>", text)
        known = self._repeats.get(shape)
        if known is not None and now - known[0] < self.repeat_window_s:
            self._repeats[shape] = (known[0], known[1] + 1)
            return
        self._say_repeats(shape)
        self._repeats.pop(shape, None)
        if len(self._repeats) >= REPEAT_SHAPES:  # the oldest goes (dicts keep insertion order)
            oldest = next(iter(self._repeats))
            self._say_repeats(oldest)
            del self._repeats[oldest]
        self._repeats[shape] = (now, 0)
        if text.endswith("handshake failed"):
            text += _HANDSHAKE_HINT
        self._pass(now, min(record.levelno, logging.WARNING), text)

    def flush(self) -> None:
        """Say how many repeated lines were left out since each was last passed on."""
        self.acquire()
        try:
            for shape in list(self._repeats):
                self._say_repeats(shape)
            self._repeats.clear()
        finally:
            self.release()

    def _say_repeats(self, shape: str) -> None:
        first, repeats = self._repeats.get(shape, (0.0, 0))
        if repeats:
            LOG.warning("live view: %d more like '%s' in %.0f s", repeats, shape, self._clock() - first)

    def _pass(self, now: float, level: int, text: str) -> None:
        if now - self._window_start >= self.window_s:
            if self._dropped:
                LOG.warning("live view: %d more lines of the WebSocket server left out", self._dropped)
            self._window_start, self._sent, self._dropped = now, 0, 0
        if self._sent >= self.per_window:
            self._dropped += 1
            return
        self._sent += 1
        LOG.log(level, "live view: %s", text)


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

    Every channel of ``channels`` (default: :func:`live_channels.session_channels`, every topic a
    session or a traverse writes) is created before the server listens and kept until :meth:`close`
    (the daemon runs many sessions on one server), so no client's subscription can be refused; a
    topic outside them, or one that comes with another schema or encoding, gets its channel as it
    appears (and a client subscribing at that moment may be refused).  Port 0 picks a free port, read back from
    :attr:`port`.  :meth:`close` first waits up to ``linger_s`` seconds for the subscribed clients
    to receive what is queued for them (:func:`live_drain.wait_drained`).
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = 8765, name: str = "viper",
                 linger_s: float = DEFAULT_LINGER_S, channels: Iterable[ChannelSpec] | None = None) -> None:
        # deferred: foxglove-sdk is the [live] extra, needed only when --live is given
        foxglove = require("foxglove", "the live view (--live)")
        guard_sdk_logs()
        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._lock = threading.RLock()  # closing a channel calls on_unsubscribe on this thread
        self._channels: dict[str, Any] = {}
        self._topic_of: dict[int, str] = {}
        self._latest: dict[str, dict[str, tuple[bytes, int]]] = {}
        self._subscribed: dict[int, set[int]] = {}  # client id -> ids of the channels it subscribed to
        self._closed = False
        self.linger_s = linger_s
        for spec in session_channels() if channels is None else channels:
            self._create_channel(spec.topic, spec.schema_name, spec.schema_encoding, spec.schema_data,
                                 spec.message_encoding)
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                 server_listener=_latch_listener(self))
        except Exception as exc:  # the SDK raises its own error types for a busy or invalid address
            for channel in self._channels.values():
                channel.close()
            raise LogError(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.host = host
        self.port = int(self._server.port)
        LOG.info("live view: ws://%s:%d (Foxglove: Open connection, Foxglove WebSocket)", host, self.port)

    def _create_channel(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                        message_encoding: str) -> Any:
        schema = self._foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        channel = self._foxglove.Channel(topic, schema=schema, message_encoding=message_encoding,
                                         context=self._context)
        self._channels[topic] = channel
        self._topic_of[int(channel.id())] = topic
        return channel

    def publish(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                message_encoding: str, data: bytes, log_time_ns: int) -> None:
        """Send a message to every client subscribed to ``topic``; it is also latched.  Sent under the
        lock, so that a new subscriber's latched copy and the next message keep their order."""
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                LOG.warning("live view: %s is not among the advertised topics; a client that subscribes to it "
                            "as it appears may be refused", printable(topic))
                channel = self._create_channel(topic, schema_name, schema_encoding, schema_data, message_encoding)
            elif (channel.schema_name(), channel.message_encoding) != (schema_name, message_encoding):
                # another encoding of the log (ROS 2 messages): the topic is advertised anew, as it appears
                LOG.info("live view: %s carries %s (%s), advertised anew", topic, schema_name, message_encoding)
                self._topic_of.pop(int(channel.id()), None)
                self._latest.pop(topic, None)
                channel.close()
                channel = self._create_channel(topic, schema_name, schema_encoding, schema_data, message_encoding)
            self._latest.setdefault(topic, {})[_latch_key(schema_name, data)] = (bytes(data), int(log_time_ns))
            channel.log(data, log_time=int(log_time_ns))

    def on_subscribe(self, client_id: int, sink_id: int, channel_id: int) -> None:
        """A client subscribed to a channel: it alone is sent the topic's latest message(s)."""
        with self._lock:
            self._subscribed.setdefault(client_id, set()).add(channel_id)
            topic = self._topic_of.get(channel_id)
            if topic is None:
                return
            channel = self._channels[topic]
            for data, log_time_ns in sorted(self._latest.get(topic, {}).values(), key=lambda item: item[1]):
                channel.log(data, log_time=log_time_ns, sink_id=sink_id)

    def on_unsubscribe(self, client_id: int, channel_id: int) -> None:
        with self._lock:
            channels = self._subscribed.get(client_id, set())
            channels.discard(channel_id)
            if not channels:
                self._subscribed.pop(client_id, None)

    def subscriptions(self) -> dict[int, frozenset[str]]:
        """The topics each connected client (by id) is subscribed to."""
        with self._lock:
            return {client: frozenset(self._topic_of.get(c, "") for c in channels)
                    for client, channels in self._subscribed.items()}

    def drain(self, timeout_s: float) -> bool:
        """Wait, at most ``timeout_s`` seconds, until the subscribed clients were sent everything queued
        for them; True if they were (or none is subscribed)."""
        return wait_drained(self.port, timeout_s, busy=lambda: bool(self.subscriptions()))

    def close(self, linger_s: float | None = None) -> None:
        """Linger (``linger_s``, default :attr:`linger_s`; 0: not at all) while clients drain, then stop."""
        if self._closed:
            return
        self._closed = True
        linger = self.linger_s if linger_s is None else linger_s
        if linger > 0 and not self.drain(linger):
            LOG.warning("live view: clients still receiving after %.1f s; closing", linger)
        self._server.stop()
        for channel in self._channels.values():
            channel.close()
        self._channels.clear()
        _GUARD.flush()

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(None if exc_type is None else 0.0)


def _latch_key(schema_name: str, data: bytes) -> str:
    """What a latched message replaces: the previous one of its topic, or of its child frame for a transform."""
    if schema_name == "foxglove.FrameTransform":
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform  # only for /tf

        return FrameTransform.FromString(data).child_frame_id
    return ""


def _sink_of(client: Any) -> int:
    """The sink id of a WebSocket client, to send to it alone.  foxglove-sdk's Python ``Client`` has
    only ``id``; the SDK numbers clients and sinks from 1, one of each per accepted connection
    (``ConnectedClient::new``), so in a process whose only sinks are WebSocket clients they are equal."""
    return int(getattr(client, "sink_id", None) or client.id)


def _latch_listener(server: LiveServer) -> Any:
    """The server listener: a new subscription gets the topic's latest message (that client only)."""
    from foxglove.websocket import ServerListener  # the [live] extra, loaded with the server

    class Latch(ServerListener):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            server.on_subscribe(int(client.id), _sink_of(client), int(channel.id))

        def on_unsubscribe(self, client: Any, channel: Any) -> None:
            server.on_unsubscribe(int(client.id), int(channel.id))

    return Latch()


_GUARD = ClientTextGuard()
