"""Byte-stream framer for NMEA 0183: raw bytes in, candidate sentences out.

Pure: it is fed bytes together with their receive time (ns since the Unix epoch, UTC) and never
reads a clock or a port.  A sentence starts at ``$`` or ``!`` and ends at ``*HH`` (checksum), at the
next start character or at the end of the line.  Bytes outside a sentence (binary protocols
interleaved on the same port, NUL padding, boot banners) are skipped and counted as garbage.  Several
sentences on one line are split at their start characters.  The checksum itself is checked by
:func:`appliance.drivers.nmea.parse_sentence`, not here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

#: Longest line kept while waiting for its end; NMEA 0183 allows 82 characters, some receivers more.
MAX_LINE_BYTES = 1024
_START = re.compile(rb"[$!]")
_PRINTABLE = re.compile(rb"^[\x20-\x7e]*$")


@dataclass(frozen=True)
class RawSentence:
    """One candidate sentence: its text (from ``$`` to the checksum, no line end) and receive time."""

    text: str
    receive_time_ns: int


@dataclass
class FramerStats:
    lines: int = 0
    candidates: int = 0
    garbage_bytes: int = 0
    non_printable: int = 0
    overlong_lines: int = 0


class NmeaFramer:
    """Splits a byte stream into :class:`RawSentence` candidates.

    ``strip_chars`` are removed before framing (gpsfake's delay cookie ``|`` in a replayed log).
    """

    def __init__(self, strip_chars: bytes = b"") -> None:
        self._buf = bytearray()
        self._strip = strip_chars
        self.stats = FramerStats()

    def feed(self, data: bytes, receive_time_ns: int) -> list[RawSentence]:
        """Add ``data`` received at ``receive_time_ns``; return the sentences completed by it."""
        self._buf.extend(data)
        out: list[RawSentence] = []
        while True:
            idx = _line_end(self._buf)
            if idx < 0:
                break
            line = bytes(self._buf[:idx])
            del self._buf[: idx + 1]
            out.extend(self._frame_line(line, receive_time_ns))
        if len(self._buf) > MAX_LINE_BYTES:
            self.stats.overlong_lines += 1
            out.extend(self._frame_line(bytes(self._buf), receive_time_ns))
            self._buf.clear()
        return out

    def flush(self, receive_time_ns: int) -> list[RawSentence]:
        """Frame what is left in the buffer (end of a log file)."""
        line = bytes(self._buf)
        self._buf.clear()
        return self._frame_line(line, receive_time_ns) if line.strip() else []

    def _frame_line(self, line: bytes, receive_time_ns: int) -> list[RawSentence]:
        if not line.strip(b"\x00 \t"):
            return []
        self.stats.lines += 1
        for ch in self._strip:
            line = line.replace(bytes([ch]), b"")
        starts = [m.start() for m in _START.finditer(line)]
        if not starts:
            self.stats.garbage_bytes += len(line.strip())
            return []
        self.stats.garbage_bytes += len(line[: starts[0]].strip(b"\x00 \t\r"))
        out = []
        for begin, end in zip(starts, starts[1:] + [len(line)]):
            segment = line[begin:end].rstrip(b"\r\n\t \x00")
            star = segment.find(b"*")
            if star >= 0 and len(segment) > star + 3:
                self.stats.garbage_bytes += len(segment) - (star + 3)
                segment = segment[: star + 3]
            if not _PRINTABLE.match(segment):
                self.stats.non_printable += 1
                self.stats.garbage_bytes += len(segment)
                continue
            self.stats.candidates += 1
            out.append(RawSentence(segment.decode("ascii"), receive_time_ns))
        return out


def _line_end(buf: bytearray) -> int:
    n = buf.find(b"\n")
    r = buf.find(b"\r")
    if n < 0:
        return r
    if r < 0:
        return n
    return min(n, r)
