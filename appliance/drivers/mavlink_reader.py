"""The MAVLink link to a rover's autopilot: transports (UDP, serial) and the thread that reads them.

:func:`open_mavlink` opens ``url``: ``udpin:HOST:PORT`` listens (the autopilot, or a router such as
mavlink-routerd, sends there; replies go to whoever sent last), ``udpout:HOST:PORT`` sends to the
autopilot (our heartbeat makes it answer), anything else is a serial device path or pyserial URL at
``baudrate`` (reopened when it goes away).  A :class:`MavlinkLink` reads in a thread of its own, so
that the stream is consumed while a stop's session runs: every frame is decoded by pymavlink, checked
by :class:`appliance.drivers.mavlink.LinkMonitor` and turned into readings
(:func:`appliance.drivers.mavlink.reading_of`), the local positions into stops
(:class:`appliance.drivers.mavlink_odometry.StopTracker`).  It sends a HEARTBEAT of its own once a
second (an onboard computer) and, on request, the appliance's estimate (:meth:`MavlinkLink.send_position`).

The only place that reads a clock: each datagram or chunk is stamped with ``clock_ns()`` on arrival.
"""

from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from appliance.config import OdometryDeviceConfig, PositionOutput, mavlink_udp_address
from appliance.drivers.autopilot import PositionFix, RoverState, SentPosition
from appliance.drivers.mavlink import (
    Attitude,
    Fault,
    FaultKind,
    GlobalPosition,
    Heartbeat,
    LinkMonitor,
    LocalPosition,
    mavlink2,
    reading_of,
    time_boot_ms_of,
)
from appliance.drivers.mavlink_odometry import StopRules, StopTracker
from appliance.drivers.mavlink_output import (
    gps_input_fields,
    horizontal_accuracy_m,
    origin_of,
    vision_position_fields,
)
from appliance.drivers.odometry import OdometryReport
from appliance.drivers.transport import Backoff, ByteStream, ReconnectingStream, open_serial
from appliance.errors import DeviceError, ProtocolError

log = logging.getLogger(__name__)

READ_BYTES = 4096
HEARTBEAT_INTERVAL_NS = 1_000_000_000
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4


class Transport(Protocol):
    def recv(self) -> bytes: ...

    def send(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class UdpTransport:
    """A UDP socket: listening (replies to the last sender) or sending to a fixed peer."""

    def __init__(self, sock: socket.socket, peer: tuple[str, int] | None, listening: bool) -> None:
        self.sock, self.peer, self.listening = sock, peer, listening

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def recv(self) -> bytes:
        try:
            data, addr = self.sock.recvfrom(65535)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise DeviceError(f"MAVLink UDP socket: {exc.strerror or exc}") from None
        if self.listening:
            self.peer = (str(addr[0]), int(addr[1]))
        return data

    def send(self, data: bytes) -> None:
        if self.peer is None:
            return  # nobody has spoken yet: nowhere to answer
        try:
            self.sock.sendto(data, self.peer)
        except OSError as exc:
            log.warning("MAVLink UDP send to %s:%d: %s", *self.peer, exc.strerror or exc)

    def close(self) -> None:
        self.sock.close()


class StreamTransport:
    """A serial device (or pty, or pyserial URL)."""

    def __init__(self, stream: ByteStream) -> None:
        self.stream = stream

    def recv(self) -> bytes:
        return self.stream.read(READ_BYTES)

    def send(self, data: bytes) -> None:
        self.stream.write(data)

    def close(self) -> None:
        self.stream.close()


def open_udp_transport(url: str, read_timeout_s: float) -> UdpTransport:
    """The socket of a ``udpin:``/``udpout:``/``udp:`` URL; a port taken is a one-line :class:`DeviceError`."""
    parsed = mavlink_udp_address(url, "devices.odometry.url")
    assert parsed is not None
    mode, host, port = parsed
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0][0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
    except OSError as exc:
        raise DeviceError(f"{url}: cannot open a UDP socket: {exc.strerror or exc}") from None
    sock.settimeout(read_timeout_s)
    if mode == "udpout":
        return UdpTransport(sock, (host, port), listening=False)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise DeviceError(f"{url}: UDP port {port} is taken (another program listens on it; "
                              "choose another port in [devices.odometry] url)") from None
        raise DeviceError(f"{url}: cannot listen on UDP port {port}: {exc.strerror or exc}") from None
    return UdpTransport(sock, None, listening=True)


class _Collect:
    """The file pymavlink's encoder writes a frame to."""

    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data += bytes(data)


class MavlinkLink:
    """The autopilot's stream read in a thread; ``poll()`` gives the stops (as odometry reports),
    ``faults()`` the faults since the last call, ``state()`` the latest attitude and position."""

    def __init__(self, transport: Transport, cfg: OdometryDeviceConfig,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.transport, self.cfg, self._clock_ns = transport, cfg, clock_ns
        self._out = _Collect()
        self._mav = mavlink2.MAVLink(self._out, srcSystem=cfg.own_system_id, srcComponent=cfg.own_component_id)
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True
        self.monitor = LinkMonitor(cfg.system_id, cfg.component_id, int(cfg.reorder_window_s * 1000),
                                   int(cfg.link_timeout_s * 1e9), start_ns=clock_ns())
        self.tracker = StopTracker(StopRules(cfg.moving_speed_m_s, int(cfg.settle_s * 1000), cfg.sigma_per_m))
        self._lock = threading.Lock()
        self._reports: list[OdometryReport] = []
        self._faults: list[Fault] = []
        self._heartbeat: Heartbeat | None = None
        self._attitude: Attitude | None = None
        self._global: GlobalPosition | None = None
        self._local: LocalPosition | None = None
        self._odometry_seen = False
        self._hb_sent_ns: int | None = None
        self._out_ns: int | None = None
        self._origin: tuple[float, float] | None = None
        self._vision_resets = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-link", daemon=True)
        self._thread.start()

    @property
    def udp_port(self) -> int | None:
        return self.transport.port if isinstance(self.transport, UdpTransport) else None

    # ------------------------------------------------------------------------------ reading
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.pump()
            except DeviceError as exc:
                with self._lock:
                    self.monitor.count(FaultKind.LINK_ERROR)
                self._fault(Fault(FaultKind.LINK_ERROR, str(exc)))
                self._stop.wait(0.5)

    def pump(self) -> None:
        """Read once (waits at most the read timeout), decode, and check the link's silence."""
        self._send_heartbeat()
        data = self.transport.recv()
        now = self._clock_ns()
        with self._lock:
            if data:
                for msg in self._parser.parse_buffer(data) or []:
                    self._take(msg, now)
            silent = self.monitor.silence(now)
        if silent is not None:
            self._fault(silent)

    def _fault(self, fault: Fault) -> None:
        log.warning("MAVLink: %s", fault.text())
        self._faults.append(fault)

    def _take(self, msg: Any, now: int) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.monitor.count(FaultKind.BAD_FRAME)
            return
        taken, fault = self.monitor.check(msg.get_srcSystem(), msg.get_srcComponent(), kind, time_boot_ms_of(msg),
                                          now)
        if fault is not None:
            self._fault(fault)
            if fault.kind is FaultKind.REBOOT:
                self.tracker.reset()
                self._origin = None
        if not taken:
            return
        try:
            reading = reading_of(msg, now)
        except ProtocolError as exc:
            fk = FaultKind.NAN_FIELD if "not finite" in str(exc) else FaultKind.UNSUPPORTED
            self.monitor.count(fk)
            self._fault(Fault(fk, f"{exc}; rejected"))
            return
        if isinstance(reading, Heartbeat):
            self._heartbeat = reading
        elif isinstance(reading, Attitude):
            self._attitude = reading
        elif isinstance(reading, GlobalPosition):
            self._global = reading
        elif isinstance(reading, LocalPosition):
            self._position(reading, kind)

    def _position(self, p: LocalPosition, kind: str) -> None:
        if kind == "ODOMETRY":
            self._odometry_seen = True
        elif self._odometry_seen:
            return  # ODOMETRY, with its covariance, is the one position read once it comes
        self._local = p
        report, frame_reset = self.tracker.update(p)
        if frame_reset:
            self.monitor.count(FaultKind.FRAME_RESET)
            self._origin = None
            self._fault(Fault(FaultKind.FRAME_RESET, f"{kind} reset_counter changed to {p.reset_counter}"))
        if report is not None:
            self._reports.append(report)

    def poll(self) -> list[OdometryReport]:
        """The stops completed since the last call (waits at most the read timeout for one)."""
        deadline = time.monotonic() + self.cfg.read_timeout_s
        while True:
            with self._lock:
                out, self._reports = self._reports, []
            if out or time.monotonic() >= deadline or not self._thread.is_alive():
                return out
            self._stop.wait(0.02)

    def faults(self) -> list[str]:
        """The faults since the last call, one line each."""
        with self._lock:
            out, self._faults = self._faults, []
        return [f.text() for f in out]

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.monitor.counts)

    def state(self) -> RoverState:
        with self._lock:
            a, h, g = self._attitude, self._heartbeat, self._global
            return RoverState(None if a is None else a.heading_deg, None if a is None else a.roll_deg,
                              None if a is None else a.pitch_deg, None if h is None else h.armed,
                              None if h is None else h.mode, None if g is None else g.lat_deg,
                              None if g is None else g.lon_deg,
                              None if a is None else a.time_boot_ms, self.monitor.boots)

    # ------------------------------------------------------------------------------ sending
    def _send(self, msg: Any) -> None:
        self._out.data = b""
        self._mav.send(msg)
        self.transport.send(self._out.data)

    def _send_heartbeat(self) -> None:
        now = self._clock_ns()
        if self._hb_sent_ns is not None and now - self._hb_sent_ns < HEARTBEAT_INTERVAL_NS:
            return
        self._hb_sent_ns = now
        with self._lock:
            self._send(self._mav.heartbeat_encode(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                                                  MAV_STATE_ACTIVE))

    def send_position(self, fix: PositionFix) -> SentPosition:
        """Send ``fix`` as ``[devices.odometry] output`` says, at most once per ``output_min_interval_s``
        and only when it says ok (unless ``output_ambiguous``)."""
        cfg = self.cfg
        if cfg.output is PositionOutput.NONE:
            return SentPosition("", False, "output = \"none\"")
        name = "GPS_INPUT" if cfg.output is PositionOutput.GPS_INPUT else "VISION_POSITION_ESTIMATE"
        accuracy = horizontal_accuracy_m(fix.covariance_m2)
        ok = fix.ok and accuracy is not None
        if not ok and (not cfg.output_ambiguous or cfg.output is PositionOutput.VISION_POSITION_ESTIMATE):
            return SentPosition(name, False, "the estimate is not ok (ambiguous or without a covariance)")
        now = self._clock_ns()
        if self._out_ns is not None and now - self._out_ns < cfg.output_min_interval_s * 1e9:
            return SentPosition(name, False, f"rate limit: less than {cfg.output_min_interval_s:g} s since the last")
        with self._lock:
            if cfg.output is PositionOutput.GPS_INPUT:
                fields = gps_input_fields(fix)
                self._send(self._mav.gps_input_encode(**fields))
                self._out_ns = now
                return SentPosition(name, True, "", int(fields["fix_type"]), accuracy)
            local = self._local
            if self._origin is None:
                if local is None:
                    return SentPosition(name, False, "no local position from the autopilot yet to anchor the frame")
                self._origin = origin_of(fix.lat_deg, fix.lon_deg, local.north_m, local.east_m)
                self._vision_resets += 1
            self._send(self._mav.vision_position_estimate_encode(
                **vision_position_fields(fix, self._origin, self._vision_resets)))
            self._out_ns = now
            return SentPosition(name, True, "", None, accuracy)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=max(2.0, 2 * self.cfg.read_timeout_s))
        self.transport.close()


def open_mavlink(url: str, cfg: OdometryDeviceConfig, backoff: Backoff | None = None,
                 clock_ns: Callable[[], int] = time.time_ns) -> MavlinkLink:
    """The link on ``url`` (UDP or serial, see the module)."""
    if mavlink_udp_address(url, "devices.odometry.url") is not None:
        return MavlinkLink(open_udp_transport(url, cfg.read_timeout_s), cfg, clock_ns)

    def opener() -> ByteStream:
        return open_serial(url, cfg.baudrate, cfg.read_timeout_s)

    return MavlinkLink(StreamTransport(ReconnectingStream(opener, backoff, name=url, initial=opener())), cfg,
                       clock_ns)
