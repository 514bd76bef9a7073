"""Odometry transports: the line protocol of :mod:`appliance.drivers.odometry` from a serial port
(pyserial: a device path, a pty, any pyserial URL) or from UDP datagrams (``udp://HOST:PORT``, the
address listened on; one line per datagram).

The only place that reads a clock: each chunk or datagram is stamped with ``clock_ns()`` as its
receive time.  :meth:`OdometryReader.poll` waits at most the read timeout and returns the reports
completed since the last call.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

from appliance.config import UDP_SCHEME, udp_address
from appliance.drivers.odometry import OdometryDecoder, OdometryReport
from appliance.drivers.policy import ErrorPolicy
from appliance.drivers.transport import Backoff, ByteStream, ReconnectingStream, open_serial
from appliance.errors import DeviceError

READ_CHUNK_BYTES = 256


class OdometryReader:
    """Reports from a byte stream (serial) or a UDP socket; ``close()`` releases it."""

    def __init__(self, stream: ByteStream | None = None, udp: socket.socket | None = None,
                 policy: ErrorPolicy = ErrorPolicy.LOG, clock_ns: Callable[[], int] = time.time_ns) -> None:
        if (stream is None) == (udp is None):
            raise ValueError("an odometry reader needs exactly one of a stream and a UDP socket")
        self.stream, self.udp = stream, udp
        self.decoder = OdometryDecoder(policy)
        self._clock_ns = clock_ns

    @property
    def udp_port(self) -> int | None:
        """The UDP port listened on (useful when 0 was asked for), or None for a serial source."""
        return None if self.udp is None else int(self.udp.getsockname()[1])

    def poll(self) -> list[OdometryReport]:
        """Read once (waits at most the read timeout); the reports completed by what was read."""
        if self.udp is not None:
            try:
                data = self.udp.recv(65535)
            except (TimeoutError, BlockingIOError):
                return []
            except OSError as exc:
                raise DeviceError(f"odometry UDP socket: {exc.strerror or exc}") from None
            now = self._clock_ns()
            lines = [ln for ln in data.split(b"\n") if ln.strip(b"\r")]
            return [r for r in (self.decoder.decode(ln, now) for ln in lines) if r is not None]
        assert self.stream is not None
        data = self.stream.read(READ_CHUNK_BYTES)
        if not data:
            return []
        return self.decoder.feed(data, self._clock_ns())

    def counts(self) -> dict[str, int]:
        """Rejected lines and discarded bytes by reason."""
        return dict(self.decoder.errors.counts)

    def close(self) -> None:
        if self.udp is not None:
            self.udp.close()
        if self.stream is not None:
            self.stream.close()


def open_udp(host: str, port: int, read_timeout_s: float) -> socket.socket:
    """A UDP socket bound to (host, port), reads waiting at most ``read_timeout_s``."""
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0][0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
    except OSError as exc:
        raise DeviceError(f"udp://{host}:{port}: cannot open a UDP socket: {exc.strerror or exc}") from None
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise DeviceError(f"udp://{host}:{port}: cannot listen: {exc.strerror or exc}") from None
    sock.settimeout(read_timeout_s)
    return sock


def open_odometry(source: str, baudrate: int = 9600, read_timeout_s: float = 0.5,
                  policy: ErrorPolicy = ErrorPolicy.LOG, backoff: Backoff | None = None,
                  clock_ns: Callable[[], int] = time.time_ns) -> OdometryReader:
    """A reader on ``udp://HOST:PORT`` (listening) or on a serial device path / pyserial URL (reopened
    when it goes away, as the GPS is)."""
    if source.startswith(UDP_SCHEME):
        host, port = udp_address(source, "odometry source")
        return OdometryReader(udp=open_udp(host, port, read_timeout_s), policy=policy, clock_ns=clock_ns)

    def opener() -> ByteStream:
        return open_serial(source, baudrate, read_timeout_s)

    stream = ReconnectingStream(opener, backoff, name=source, initial=opener())
    return OdometryReader(stream, policy=policy, clock_ns=clock_ns)
