"""Pan stage: the FLIR (Directed Perception) PTU ASCII protocol over serial.

Commands are ASCII words ended by a space; after ``ED`` (echo disable) and ``FT`` (terse feedback)
the unit answers each with one line: ``*`` (done), ``* <value>`` (a query's answer) or
``!<message>`` (refused: illegal position, limit hit...).  Used here: ``ED``, ``FT``, ``CI``
(independent control), ``PR`` (pan resolution, arc-seconds per position), ``PN``/``PX`` (pan
limits, positions), ``PS<n>`` (pan speed, positions/s), ``PP<n>`` (absolute pan position), ``PP``
(query), ``A`` (await completion of the last move), ``R`` (reset: homes the axes).

Pure part: :func:`parse_reply` (one line to a :class:`PtuReply`).  :class:`PanTiltUnit` talks over
any byte stream with ``read``/``write`` (pyserial port, pty, ``loop://``); a unit that does not
answer within the timeout raises :class:`DeviceError`, a refused command too, and a move that does
not end where it was sent (a missed step) is reported, never hidden.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from appliance.drivers.transport import ByteStream
from appliance.errors import DeviceError, ProtocolError

log = logging.getLogger(__name__)
ARCSEC_PER_DEG = 3600.0


@dataclass(frozen=True)
class PtuReply:
    ok: bool
    value: str  # the text after "* " for a query, the message after "!" for an error


def parse_reply(line: bytes) -> PtuReply:
    """One reply line (without line end) in terse mode."""
    text = line.decode("ascii", errors="replace").strip()
    if text.startswith("*"):
        return PtuReply(True, text[1:].strip())
    if text.startswith("!"):
        return PtuReply(False, text[1:].strip())
    raise ProtocolError(f"PTU reply neither '*' nor '!': {text[:40]!r}")


@dataclass(frozen=True)
class StageLimits:
    min_position: int
    max_position: int
    arcsec_per_position: float

    def to_position(self, pan_deg: float) -> int:
        return round(pan_deg * ARCSEC_PER_DEG / self.arcsec_per_position)

    def to_deg(self, position: int) -> float:
        return position * self.arcsec_per_position / ARCSEC_PER_DEG


class PanTiltUnit:
    """A PTU's pan axis.  Angles in degrees, positive clockwise seen from above (the unit's sense)."""

    def __init__(
        self,
        stream: ByteStream,
        timeout_s: float = 2.0,
        move_timeout_s: float = 30.0,
        position_tolerance: int = 0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream = stream
        self.timeout_s = timeout_s
        self.move_timeout_s = move_timeout_s
        self.position_tolerance = position_tolerance
        self._clock = clock
        self._buf = bytearray()
        self.missed_moves = 0
        self.command("ED")
        self.command("FT")
        self.command("CI")
        res = self._number(self.command("PR").value, "PR")
        lo = int(self._number(self.command("PN").value, "PN"))
        hi = int(self._number(self.command("PX").value, "PX"))
        if res <= 0 or lo >= hi:
            raise DeviceError(f"PTU: implausible resolution {res} arcsec or limits {lo}..{hi}")
        self.limits = StageLimits(lo, hi, res)

    @staticmethod
    def _number(text: str, what: str) -> float:
        try:
            value = float(text.split()[-1])
        except (ValueError, IndexError):
            raise ProtocolError(f"PTU {what}: no number in answer {text!r}") from None
        if not math.isfinite(value) or abs(value) > 1e9:
            raise ProtocolError(f"PTU {what}: implausible number in answer {text!r}")
        return value

    def _readline(self, timeout_s: float) -> bytes:
        deadline = self._clock() + timeout_s
        while True:
            for sep in (b"\n", b"\r"):
                i = self._buf.find(sep)
                if i >= 0:
                    line = bytes(self._buf[:i])
                    del self._buf[: i + 1]
                    if line.strip():
                        return line
                    break
            else:
                if self._clock() > deadline:
                    raise DeviceError(f"PTU: no answer within {timeout_s:.1f} s")
                self._buf.extend(self.stream.read(1))
                continue

    def command(self, cmd: str, timeout_s: float | None = None) -> PtuReply:
        """Send one command; a refusal (``!``) raises :class:`DeviceError` naming the command."""
        self._buf.clear()
        try:
            self.stream.write(cmd.encode("ascii") + b" ")
        except OSError as exc:
            raise DeviceError(f"PTU: cannot send {cmd!r}: {exc}") from None
        line = self._readline(timeout_s or self.timeout_s).strip()
        if line.upper().startswith(cmd.upper().encode("ascii")):
            line = line[len(cmd) :]  # the unit's echo, before ED takes effect
        reply = parse_reply(line)
        if not reply.ok:
            raise DeviceError(f"PTU refused {cmd!r}: {reply.value}")
        return reply

    def position(self) -> int:
        return int(self._number(self.command("PP").value, "PP"))

    def position_deg(self) -> float:
        return self.limits.to_deg(self.position())

    def set_speed_deg_s(self, speed_deg_s: float) -> None:
        n = round(speed_deg_s * ARCSEC_PER_DEG / self.limits.arcsec_per_position)
        if n <= 0:
            raise DeviceError(f"PTU: speed {speed_deg_s} deg/s is not positive")
        self.command(f"PS{n}")

    def move_to_deg(self, pan_deg: float, strict: bool = True) -> float:
        """Move, wait for completion, check the position reached; return it (deg).

        A move that ends off its target (missed steps) is logged; it raises :class:`DeviceError`
        when ``strict``, else the position actually reached is returned for the caller to judge.
        """
        target = self.limits.to_position(pan_deg)
        if not self.limits.min_position <= target <= self.limits.max_position:
            raise DeviceError(
                f"PTU: pan {pan_deg:.3f} deg = position {target} outside limits "
                f"{self.limits.min_position}..{self.limits.max_position}"
            )
        self.command(f"PP{target}")
        self.command("A", timeout_s=self.move_timeout_s)
        reached = self.position()
        if abs(reached - target) > self.position_tolerance:
            self.missed_moves += 1
            log.warning("PTU: sent to position %d, stopped at %d (missed steps)", target, reached)
            if not strict:
                return self.limits.to_deg(reached)
            raise DeviceError(f"PTU: sent to position {target}, stopped at {reached} (missed steps)")
        return self.limits.to_deg(reached)

    def reset(self) -> None:
        """Home the axes (``R``); slow on a real unit."""
        self.command("R", timeout_s=self.move_timeout_s)

    def close(self) -> None:
        self.stream.close()
