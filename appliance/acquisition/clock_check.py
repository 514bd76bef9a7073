"""The system clock against the GPS time in a session.

Every fix the session's GPS truth collects carries two times: the receiver's UTC (RMC or ZDA date
with the epoch's time of day) and the platform clock's time when its first byte arrived.  Their
difference, receive time minus GPS time, is the clock's offset plus the receiver's latency (the
sentence's transmission, the read), so the least difference over the session's fixes is the best
estimate of the offset: positive, the system clock is ahead of GPS.  A session whose offset exceeds
``[logbook] max_clock_offset_s`` is flagged: its log's timestamps (and the log's name) are off by
that much.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from appliance.drivers.gps import GpsFix


@dataclass(frozen=True)
class ClockCheck:
    """The clock's offset from GPS time in one session (s; None without a fix that has a date)."""

    offset_s: float | None
    fixes: int  # fixes with a UTC date and time
    max_offset_s: float

    @property
    def flagged(self) -> bool:
        return self.offset_s is not None and abs(self.offset_s) > self.max_offset_s

    def payload(self) -> dict[str, Any]:
        """The ``/session/clock`` record."""
        return {"offset_s": self.offset_s, "max_offset_s": self.max_offset_s, "fixes": self.fixes,
                "flagged": self.flagged}

    def fault(self) -> str | None:
        """The fault line of a flagged session, else None."""
        if not self.flagged or self.offset_s is None:
            return None
        side = "ahead of" if self.offset_s > 0 else "behind"
        return (f"clock: the system clock is {abs(self.offset_s):.1f} s {side} the GPS time (max_clock_offset_s "
                f"{self.max_offset_s:g}); this log's times are off by as much")


def check_clock(fixes: Iterable[GpsFix], max_offset_s: float) -> ClockCheck:
    """The least (receive time - GPS UTC) over ``fixes`` that have a UTC date and time."""
    diffs = [f.receive_time_ns / 1e9 - f.utc.timestamp() for f in fixes if f.utc is not None]
    return ClockCheck(min(diffs) if diffs else None, len(diffs), max_offset_s)
