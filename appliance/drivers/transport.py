"""Byte transports for serial devices: a pyserial URL or device path, or a recorded log to replay.

A transport is anything with ``read(n) -> bytes``, ``write(data) -> int | None`` and ``close()``
(:class:`ByteStream`).  :func:`open_serial` opens a device path or any pyserial URL (``loop://``,
``socket://host:port``, a pty's path) with ``serial_for_url``; :class:`LogReplay` replays a
recorded log file (``#`` comment lines dropped, gpsfake's ``# Delay-Cookie:`` character removed).
:class:`ReconnectingStream` reopens a serial device that went away (unplugged USB receiver, a
twin's pty closed) with exponential back-off, logging each loss and each recovery.
"""

from __future__ import annotations

import logging
import re
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import serial

from appliance.errors import DeviceError

log = logging.getLogger(__name__)


class ByteStream(Protocol):
    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def close(self) -> None: ...


def open_serial(source: str, baudrate: int = 9600, timeout_s: float = 0.5) -> serial.SerialBase:
    """Open a serial device path or pyserial URL; a missing device raises :class:`DeviceError`."""
    try:
        return serial.serial_for_url(source, baudrate=baudrate, timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"{source}: cannot open serial port at {baudrate} baud: {exc}") from None


_COOKIE = re.compile(rb"^#\s*Delay-Cookie:\s*(\S)", re.MULTILINE)


class LogReplay:
    """A recorded NMEA/ASCII log as a read-only stream (returns b'' at its end)."""

    def __init__(self, path: str | Path) -> None:
        p = Path(path)
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise DeviceError(f"{p}: cannot read log: {exc.strerror}") from None
        m = _COOKIE.search(data)
        #: The gpsfake delay cookie the log declares (removed by the framer), or b''.
        self.delay_cookie = m.group(1) if m else b""
        lines = data.splitlines(keepends=True)
        self._data = b"".join(ln for ln in lines if not ln.startswith(b"#"))
        self._pos = 0

    def read(self, size: int = 1) -> bytes:
        chunk = self._data[self._pos : self._pos + size]
        self._pos += len(chunk)
        return chunk

    def write(self, data: bytes) -> int | None:
        raise DeviceError("a replayed log cannot be written to")

    def close(self) -> None:
        self._pos = len(self._data)


def is_log_file(source: str) -> bool:
    """True when ``source`` names a regular file (a recorded log), not a device or URL."""
    p = Path(source)
    return "://" not in source and p.is_file()


@dataclass
class Backoff:
    """Exponential back-off between reopen attempts (s)."""

    initial_s: float = 0.1
    maximum_s: float = 5.0
    factor: float = 2.0

    def delays(self) -> list[float]:
        out, d = [], self.initial_s
        while d < self.maximum_s:
            out.append(d)
            d *= self.factor
        return out + [self.maximum_s]


class ReconnectingStream:
    """A serial stream that reopens itself when its device goes away.

    Give the first, already opened stream as ``initial`` so that a device absent at start is an
    error for the caller rather than a silent retry loop.  ``read`` never raises for a lost
    device: it closes it, waits per ``backoff`` (``sleep`` is injectable) and returns ``b''``
    until the device is back.  ``reconnects`` counts recoveries.
    """

    def __init__(
        self,
        opener: Callable[[], ByteStream],
        backoff: Backoff | None = None,
        sleep: Callable[[float], None] = time.sleep,
        name: str = "device",
        initial: ByteStream | None = None,
    ) -> None:
        self._opener = opener
        self._backoff = backoff or Backoff()
        self._sleep = sleep
        self._name = name
        self._stream: ByteStream | None = initial
        self._attempt = 0
        self.reconnects = 0
        self.losses = 0

    def _ensure_open(self) -> ByteStream | None:
        if self._stream is not None:
            return self._stream
        delays = self._backoff.delays()
        try:
            self._stream = self._opener()
        except DeviceError as exc:
            delay = delays[min(self._attempt, len(delays) - 1)]
            self._attempt += 1
            log.warning("%s: reopen attempt %d failed (%s); retrying in %.2f s", self._name, self._attempt,
                        exc, delay)
            self._sleep(delay)
            return None
        if self._attempt or self.losses:
            self.reconnects += 1
            log.warning("%s: reopened after %d failed attempt(s)", self._name, self._attempt)
        self._attempt = 0
        return self._stream

    def _lost(self, exc: Exception) -> None:
        self.losses += 1
        log.warning("%s: lost (%s); reopening", self._name, exc)
        if self._stream is not None:
            try:
                self._stream.close()
            except (OSError, serial.SerialException):
                pass
        self._stream = None

    def read(self, size: int = 1) -> bytes:
        s = self._ensure_open()
        if s is None:
            return b""
        try:
            return s.read(size)
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            return b""

    def reset_input_buffer(self) -> None:
        """Discard the bytes received and not read yet (nothing while disconnected)."""
        s = self._stream
        reset = getattr(s, "reset_input_buffer", None)
        if reset is None:
            return
        try:
            reset()
        except (serial.SerialException, OSError, termios.error) as exc:  # a pty whose other side went away
            self._lost(exc)

    def write(self, data: bytes) -> int | None:
        s = self._ensure_open()
        if s is None:
            raise DeviceError(f"{self._name}: not connected")
        try:
            return s.write(data)
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            raise DeviceError(f"{self._name}: write failed: {exc}") from None

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()
            self._stream = None
