"""What a session log says of its session: when it ran, how each procedure ended, the GPS truth's
fixes and standard error, the frames and the valid azimuths of the detected skyline.

:class:`FactsCollector` takes the log's messages one by one (so :func:`appliance.acquisition.replay.read_session`
gathers the facts in the same pass as the frames); :func:`read_session_facts` reads a log for them
alone, decoding no image.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.errors import ErrorPolicy, LogError
from appliance.logbook import topics as t
from appliance.logbook.reader import LogMessage, LogReader

#: the procedures whose outcome the report shows, in session order
PROCEDURES = ("level", "compass", "truth", "capture", "estimate")
_DECODED = (t.PROCEDURE, t.SKYLINE_DETECTED, t.SESSION)


@dataclass(frozen=True)
class ProcedureOutcome:
    status: str
    reason: str


@dataclass
class SessionFacts:
    """Facts of one session log; None where the log does not say."""

    session_id: str | None = None
    first_ns: int | None = None  # log time of the first message (ns since the Unix epoch, UTC)
    last_ns: int | None = None
    procedures: dict[str, ProcedureOutcome] = field(default_factory=dict)
    gps_fixes: int = 0  # /gps/fix messages: every fix received
    truth_fixes_used: int | None = None  # fixes averaged into the truth (those past the quality gate)
    truth_sigma_m: float | None = None  # standard error of the averaged truth (horizontal, radial)
    captures: int = 0  # /camera/capture tags
    valid_azimuths: int | None = None  # of the skyline detected on board
    azimuths: int | None = None

    @property
    def duration_s(self) -> float | None:
        if self.first_ns is None or self.last_ns is None:
            return None
        return (self.last_ns - self.first_ns) / 1e9

    def rows(self, one_session: bool = True) -> list[tuple[str, str]]:
        """(name, value) pairs for the report, in a fixed order; facts the log lacks are left out (all of
        them for a log without a readable message).  A log of several sessions (a traverse's stops)
        gives ``one_session=False``: only what its whole holds (time, fixes and frames received),
        since the procedures, the truth and the skyline are each stop's own."""
        out: list[tuple[str, str]] = []
        if self.first_ns is None:
            return out
        start = dt.datetime.fromtimestamp(self.first_ns / 1e9, tz=dt.timezone.utc)
        out.append(("session time", f"{start:%Y-%m-%d %H:%M:%S} UTC, {self.duration_s:.0f} s"))
        if self.session_id is not None:
            out.append(("session id", self.session_id))
        for name in PROCEDURES if one_session else ():
            if name in self.procedures:
                o = self.procedures[name]
                out.append((name, o.status + (f": {o.reason}" if o.reason else "")))
        gps = f"{self.gps_fixes} received"
        if self.truth_fixes_used is not None and one_session:
            gps += f", {self.truth_fixes_used} averaged"
        if self.truth_sigma_m is not None and one_session:
            gps += f", σ {self.truth_sigma_m:.1f} m"
        out.append(("GPS fixes", gps))
        out.append(("frames", str(self.captures)))
        if self.valid_azimuths is not None and one_session:
            out.append(("valid azimuths (on board)", f"{self.valid_azimuths} of {self.azimuths}"))
        return out


class FactsCollector:
    """Builds :class:`SessionFacts` from a log's messages in file order."""

    def __init__(self) -> None:
        self.facts = SessionFacts()

    def take(self, msg: LogMessage) -> None:
        """Counts ``msg``; decodes only the few topics it needs (raises what ``decode`` raises)."""
        f = self.facts
        ns = msg.log_time_ns
        f.first_ns = ns if f.first_ns is None else min(f.first_ns, ns)
        f.last_ns = ns if f.last_ns is None else max(f.last_ns, ns)
        if msg.topic == t.GPS_FIX:
            f.gps_fixes += 1
        elif msg.topic == t.CAPTURE:
            f.captures += 1
        elif msg.topic in _DECODED:
            self._decoded(msg.topic, msg.decode())

    def _decoded(self, topic: str, payload: Any) -> None:
        """Takes the facts of one decoded record; a record of another shape (a field of another type)
        says nothing and is left out."""
        if not isinstance(payload, dict):
            return
        try:
            self._facts_of(topic, payload)
        except (TypeError, ValueError, OverflowError):
            return

    def _facts_of(self, topic: str, payload: dict[str, Any]) -> None:
        f = self.facts
        if topic == t.SESSION:
            f.session_id = str(payload.get("session_id")) if payload.get("session_id") is not None else None
        elif topic == t.PROCEDURE and payload.get("procedure") is not None:
            name = str(payload["procedure"])
            f.procedures[name] = ProcedureOutcome(str(payload.get("status", "")), str(payload.get("reason") or ""))
            if name == "truth":
                used, sigma = payload.get("used"), payload.get("sigma_m")
                f.truth_fixes_used = None if used is None else int(used)
                f.truth_sigma_m = None if sigma is None else float(sigma)
        elif topic == t.SKYLINE_DETECTED:
            el = payload.get("elevation_deg") or []
            if not isinstance(el, list):
                return
            valid = sum(1 for v in el if v is not None and math.isfinite(float(v)))
            f.azimuths, f.valid_azimuths = len(el), valid


def read_session_facts(path: str | Path) -> SessionFacts:
    """The facts of the log at ``path`` up to its last readable record."""
    reader = LogReader(path, ErrorPolicy.SKIP)
    collector = FactsCollector()
    for msg in reader.messages():
        try:
            collector.take(msg)
        except (LogError, ValueError):
            continue
    return collector.facts
