"""The rover's odometry line protocol: one ASCII line per stop, pure parse and format.

Grammar (one line, at most :data:`MAX_LINE_CHARS` characters before the line end)::

    ODO,<stop_id>,<east_m>,<north_m>,<sigma_m>*<HH>\\r\\n

- ``stop_id``: the stop the rover has just reached, a decimal integer 1..2^31-1.  Stop 0 is where the
  traverse starts and has no line; each later stop's line follows the previous one's by exactly 1 (a
  gap tells the appliance a line was lost, and it does not fuse across it).
- ``east_m``, ``north_m``: the dead-reckoned displacement from the previous stop to this one, in
  metres towards true east and true north; plain decimals (``-12.5``, ``.5``, ``7``), no exponent.
- ``sigma_m``: the displacement's 1-sigma uncertainty along each axis, metres, >= 0.
- ``HH``: two hexadecimal digits (either case), the XOR of every byte between the line's start and
  the ``*`` (``ODO,...,<sigma_m>``), as NMEA 0183's checksum.  Required.
- The line ends with ``\\n``; a ``\\r`` before it is allowed.  No spaces anywhere.

Example: ``ODO,3,212.40,-87.05,15.00*4F`` (stop 3 is 212.4 m east and 87.05 m south of stop 2,
+-15 m).  Over a serial port the lines follow each other; over UDP each datagram holds one line.

:func:`parse_line` takes one line's text and its receive time and returns an :class:`OdometryReport`,
or raises :class:`ProtocolError` with a one-line reason; :func:`format_line` is its inverse;
:class:`OdometryDecoder` splits a byte stream into lines and applies an :class:`ErrorPolicy`.  No
clock and no port are read here.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass

from appliance.drivers.policy import ErrorCounter, ErrorPolicy
from appliance.errors import ProtocolError

log = logging.getLogger(__name__)

TALKER = "ODO"
MAX_LINE_CHARS = 80
MAX_STOP_ID = 2**31 - 1
#: a displacement larger than this (m) between two stops is not odometry
MAX_DISPLACEMENT_M = 100_000.0

_LINE = re.compile(r"(?P<body>ODO,(?P<fields>[^*]*))\*(?P<cs>[0-9A-Fa-f]{2})")
_DECIMAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)")
_STOP = re.compile(r"\d{1,10}")
#: field names in the order of the line
FIELDS = ("stop_id", "east_m", "north_m", "sigma_m")


@dataclass(frozen=True)
class OdometryReport:
    """The displacement from stop ``stop_id - 1`` to stop ``stop_id`` (m, true east and north, 1-sigma
    per axis) and when its line was received (UTC ns).  ``reset``: the source's frame was reset since
    the previous stop (an autopilot's reboot), so the displacement does not join the two stops."""

    stop_id: int
    east_m: float
    north_m: float
    sigma_m: float
    receive_time_ns: int = 0
    reset: bool = False


def checksum(body: str) -> str:
    """Two upper-case hexadecimal digits: the XOR of the bytes of ``body``."""
    cs = 0
    for ch in body.encode("ascii"):
        cs ^= ch
    return f"{cs:02X}"


def _decimal(text: str, what: str) -> float:
    if len(text) > 20 or not _DECIMAL.fullmatch(text):
        raise ProtocolError(f"odometry {what}: not a plain decimal number: {text[:24]!r}")
    return float(text)


def parse_line(line: str | bytes, receive_time_ns: int = 0) -> OdometryReport:
    """One line (its line end optional) as an :class:`OdometryReport`; anything else raises
    :class:`ProtocolError` naming what is wrong."""
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(f"odometry line: not ASCII: {line[:24]!r}") from None
    text = line[:-1] if line.endswith("\n") else line
    text = text[:-1] if text.endswith("\r") else text
    if len(text) > MAX_LINE_CHARS:
        raise ProtocolError(f"odometry line: longer than {MAX_LINE_CHARS} characters: {text[:24]!r}...")
    m = _LINE.fullmatch(text)
    if m is None:
        if not text.startswith(f"{TALKER},"):
            raise ProtocolError(f"odometry line: does not start with '{TALKER},': {text[:24]!r}")
        raise ProtocolError(f"odometry line: no '*HH' checksum at its end: {text[:40]!r}")
    expected = checksum(m.group("body"))
    if m.group("cs").upper() != expected:
        raise ProtocolError(f"odometry line: checksum {m.group('cs')} != {expected}: {text[:40]!r}")
    fields = m.group("fields").split(",")
    if len(fields) != len(FIELDS):
        raise ProtocolError(f"odometry line: {len(fields)} fields, expected {len(FIELDS)} "
                            f"({', '.join(FIELDS)}): {text[:40]!r}")
    stop_text, east_text, north_text, sigma_text = fields
    if not _STOP.fullmatch(stop_text) or not 1 <= int(stop_text) <= MAX_STOP_ID:
        raise ProtocolError(f"odometry stop_id: expected an integer 1..{MAX_STOP_ID}: {stop_text[:24]!r}")
    east, north = _decimal(east_text, "east_m"), _decimal(north_text, "north_m")
    sigma = _decimal(sigma_text, "sigma_m")
    if math.hypot(east, north) > MAX_DISPLACEMENT_M:
        raise ProtocolError(f"odometry displacement {math.hypot(east, north):.0f} m: more than "
                            f"{MAX_DISPLACEMENT_M:.0f} m between two stops")
    if not 0.0 <= sigma <= MAX_DISPLACEMENT_M:
        raise ProtocolError(f"odometry sigma_m {sigma_text!r}: expected 0..{MAX_DISPLACEMENT_M:.0f} m")
    return OdometryReport(int(stop_text), east, north, sigma, receive_time_ns)


def format_line(report: OdometryReport) -> bytes:
    """The line of ``report`` (centimetres), checksum and CR LF included."""
    if not 1 <= report.stop_id <= MAX_STOP_ID:
        raise ValueError(f"stop_id {report.stop_id}: expected 1..{MAX_STOP_ID}")
    values = (report.east_m, report.north_m, report.sigma_m)
    if not all(math.isfinite(v) for v in values) or report.sigma_m < 0:
        raise ValueError(f"odometry values must be finite and sigma_m >= 0: {values}")
    body = f"{TALKER},{report.stop_id},{report.east_m:.2f},{report.north_m:.2f},{report.sigma_m:.2f}"
    return f"{body}*{checksum(body)}\r\n".encode("ascii")


class OdometryDecoder:
    """Bytes in (as they arrive, with their receive time), reports out; a bad line is dropped and
    counted under the error policy (never a value).  Bytes beyond :data:`MAX_LINE_CHARS` without a
    line end are discarded as garbage."""

    def __init__(self, policy: ErrorPolicy = ErrorPolicy.LOG) -> None:
        self.errors = ErrorCounter(policy, log)
        self._pending = b""

    def feed(self, data: bytes, receive_time_ns: int) -> list[OdometryReport]:
        self._pending += data
        *lines, self._pending = self._pending.split(b"\n")
        if len(self._pending) > MAX_LINE_CHARS + 2:
            self.errors.count("garbage bytes", len(self._pending))
            self._pending = b""
        out = []
        for raw in lines:
            if not raw.strip(b"\r"):
                continue
            report = self.decode(raw, receive_time_ns)
            if report is not None:
                out.append(report)
        return out

    def decode(self, line: bytes, receive_time_ns: int) -> OdometryReport | None:
        """One line (a datagram, or a line of the stream) as a report, or None if it was rejected."""
        try:
            return parse_line(line, receive_time_ns)
        except ProtocolError as exc:
            self.errors.reject("bad odometry line", exc)
            return None
