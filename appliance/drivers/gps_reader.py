"""GPS driver: a byte stream (serial port, pyserial URL or replayed log) to :class:`GpsFix` records.

The only place that reads a clock: each chunk read is stamped with ``time.time_ns()`` (UTC) as its
receive time, then framed and decoded by the pure layers (:mod:`nmea_framer`, :mod:`gps`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from appliance.drivers.gps import DEFAULT_ERROR_BY_QUALITY_M, FixQuality, GpsDecoder, GpsFix
from appliance.drivers.nmea_framer import NmeaFramer
from appliance.drivers.policy import ErrorPolicy
from appliance.drivers.transport import (
    Backoff,
    ByteStream,
    LogReplay,
    ReconnectingStream,
    is_log_file,
    open_serial,
)

READ_CHUNK_BYTES = 256


@dataclass(frozen=True)
class GpsSourceOptions:
    baudrate: int = 9600
    read_timeout_s: float = 0.5
    reconnect: bool = True


class GpsReader:
    """Reads fixes from one stream.  ``fixes()`` ends at the end of a log; on a port it runs on."""

    def __init__(
        self,
        stream: ByteStream,
        policy: ErrorPolicy = ErrorPolicy.LOG,
        delay_cookie: bytes = b"",
        clock_ns: Callable[[], int] = time.time_ns,
        error_by_quality_m: dict[FixQuality, float] | None = None,
    ) -> None:
        self.stream = stream
        self.framer = NmeaFramer(strip_chars=delay_cookie)
        self._delay_cookie = delay_cookie
        self.decoder = GpsDecoder(policy, error_by_quality_m or dict(DEFAULT_ERROR_BY_QUALITY_M))
        self._clock_ns = clock_ns
        self._ended = False

    @property
    def ended(self) -> bool:
        """True once a replayed log is exhausted."""
        return self._ended

    def poll(self) -> list[GpsFix]:
        """Read one chunk (waits at most the port's timeout); return the fixes it completed."""
        if self._ended:
            return []
        data = self.stream.read(READ_CHUNK_BYTES)
        now = self._clock_ns()
        if not data:
            if isinstance(self.stream, LogReplay):
                self._ended = True
                return self.decoder.feed(self.framer.flush(now)) + self.decoder.flush()
            return []
        return self.decoder.feed(self.framer.feed(data, now))

    def discard_pending(self) -> None:
        """Drop what the port buffered while nobody read it, and any partial line, so that a measurement
        starting now takes only the fixes that follow (after a long capture the buffer holds fixes of
        minutes ago: of the previous stop, on a rover).  A replayed log keeps everything."""
        reset = getattr(self.stream, "reset_input_buffer", None)
        if reset is None:
            return
        reset()
        self.framer = NmeaFramer(strip_chars=self._delay_cookie)
        self.decoder.flush()  # the epoch in progress is of the discarded past too

    def fixes(self) -> Iterator[GpsFix]:
        while not self._ended:
            yield from self.poll()

    def counts(self) -> dict[str, int]:
        """Rejected and skipped records by reason, plus the framer's garbage byte count."""
        out = dict(self.decoder.errors.counts)
        out["garbage bytes"] = self.framer.stats.garbage_bytes
        out["binary segments"] = self.framer.stats.non_printable
        return out

    def close(self) -> None:
        self.stream.close()


def open_gps(
    source: str,
    options: GpsSourceOptions = GpsSourceOptions(),
    policy: ErrorPolicy = ErrorPolicy.LOG,
    backoff: Backoff | None = None,
    clock_ns: Callable[[], int] = time.time_ns,
) -> GpsReader:
    """A reader on a log file path, a device path or a pyserial URL (reopened when unplugged)."""
    if is_log_file(source):
        replay = LogReplay(source)
        return GpsReader(replay, policy, delay_cookie=replay.delay_cookie, clock_ns=clock_ns)
    def opener() -> ByteStream:
        return open_serial(source, options.baudrate, options.read_timeout_s)

    first = opener()  # a device absent at start is the caller's error, not a retry loop
    stream: ByteStream = (
        ReconnectingStream(opener, backoff, name=source, initial=first) if options.reconnect else first
    )
    return GpsReader(stream, policy, clock_ns=clock_ns)
