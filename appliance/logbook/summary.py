"""``viper log info``: topics, message counts, time span, and the estimate against the GPS truth."""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.bodies import geodesic_distance_m
from appliance.errors import ErrorPolicy, LogError
from appliance.logbook import topics
from appliance.logbook.reader import LogMessage, LogReader


@dataclass
class TopicStats:
    schema_name: str
    message_encoding: str = ""
    json_schema: str = ""  # the JSON schema a ROS 2 String channel carries
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None


@dataclass
class LogSummary:
    path: Path
    size_bytes: int
    complete: bool
    problem: str | None
    topics: dict[str, TopicStats] = field(default_factory=dict)
    estimate: dict[str, Any] | None = None
    truth: dict[str, Any] | None = None
    profile: str | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    @property
    def span_ns(self) -> tuple[int, int] | None:
        firsts = [t.first_ns for t in self.topics.values() if t.first_ns is not None]
        lasts = [t.last_ns for t in self.topics.values() if t.last_ns is not None]
        return (min(firsts), max(lasts)) if firsts and lasts else None

    @property
    def error_m(self) -> float | None:
        """Distance between the last estimate and the GPS truth (geodesic on WGS84, metres)."""
        if self.estimate is not None and self.estimate.get("error_m") is not None:
            return float(self.estimate["error_m"])
        if self.estimate is None or self.truth is None:
            return None
        return geodesic_distance_m(
            self.estimate["lat"], self.estimate["lon"], self.truth["lat"], self.truth["lon"]
        )

    @property
    def estimate_status(self) -> str:
        """'ambiguous' when the estimate's region was too large (or the truth lies outside it), 'ok'
        otherwise, 'unknown' for a log without the full estimate record."""
        if self.estimate is None or "ambiguous" not in self.estimate:
            return "unknown"
        if self.estimate["ambiguous"]:
            region = self.estimate.get("region", {})
            return f"ambiguous ({region.get('n_cells', '?')} cells as likely as the best)"
        return "ok"

    def lines(self) -> list[str]:
        state = "complete" if self.complete else f"INCOMPLETE: {self.problem} (try 'viper log recover')"
        out = [f"{self.path}: {self.size_bytes} bytes, {self.message_count} messages, {state}"]
        span = self.span_ns
        if span is not None:
            out.append(f"time span: {utc_text(span[0])} .. {utc_text(span[1])} ({(span[1] - span[0]) / 1e9:.3f} s)")
        software = self.metadata.get("viper.software")
        if software is not None:
            out.append(f"written by {software.get('name', '?')} {software.get('version', '?')}, profile "
                       f"{self.profile or '?'}, metadata: {', '.join(sorted(self.metadata))}")
        elif self.profile is not None:
            out.append(f"profile {self.profile}, metadata: {', '.join(sorted(self.metadata)) or 'none'}")
        the_map = self.metadata.get("viper.map")
        if the_map is not None:
            out.append(f"map: {the_map.get('path', '?')} sha256 {the_map.get('sha256', '?')}")
        width = max((len(t) for t in self.topics), default=5)
        for name, st in sorted(self.topics.items()):
            carried = f" ({st.json_schema})" if st.json_schema else ""
            out.append(f"  {name:<{width}}  {st.count:>6}  {st.schema_name}{carried}")
        if self.truth is not None:
            out.append(f"GPS truth: lat {self.truth['lat']:.6f} lon {self.truth['lon']:.6f}")
        if self.estimate is not None:
            e = self.estimate
            out.append(f"estimate:  lat {e['lat']:.6f} lon {e['lon']:.6f}  {self.estimate_status}")
        err = self.error_m
        if err is not None:
            out.append(f"estimate error vs GPS truth: {err:.1f} m")
        elif self.estimate is None:
            out.append("no estimate in this log")
        return out

    def to_json(self) -> dict[str, Any]:
        """The facts of :meth:`lines` as one JSON object (times in ns since the Unix epoch and as UTC text)."""
        span = self.span_ns
        return {
            "path": str(self.path),
            "size_bytes": self.size_bytes,
            "message_count": self.message_count,
            "complete": self.complete,
            "problem": self.problem,
            "profile": self.profile,
            "span": None if span is None else {"start_ns": span[0], "end_ns": span[1], "start": utc_text(span[0]),
                                               "end": utc_text(span[1]), "duration_s": (span[1] - span[0]) / 1e9},
            "topics": {name: {"schema": st.schema_name, "message_encoding": st.message_encoding,
                              "json_schema": st.json_schema or None, "count": st.count,
                              "first_ns": st.first_ns, "last_ns": st.last_ns}
                       for name, st in sorted(self.topics.items())},
            "metadata": self.metadata,
            "truth": self.truth,
            "estimate": None if self.estimate is None else {
                "lat": self.estimate["lat"], "lon": self.estimate["lon"], "status": self.estimate_status},
            "error_m": self.error_m,
        }


def utc_text(time_ns: int) -> str:
    """A log time (ns since the Unix epoch) as ISO 8601 UTC to the millisecond: 2026-06-01T12:00:05.250Z."""
    seconds, ns = divmod(int(time_ns), 1_000_000_000)
    stamp = dt.datetime.fromtimestamp(seconds, tz=dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{stamp}.{ns // 1_000_000:03d}Z"


def _number(v: Any) -> float | None:
    """``v`` as a finite number, or None when it is none (a bool, a string, a list...)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _fix(msg: LogMessage) -> dict[str, Any] | None:
    """{lat, lon} of a location fix message; None for a message that does not decode as one."""
    try:
        fix = msg.decode()
        lat, lon = _number(fix.latitude), _number(fix.longitude)
    except (LogError, AttributeError):  # another encoding or schema on this topic: not a fix
        return None
    return None if lat is None or lon is None else {"lat": lat, "lon": lon}


def _estimate_record(msg: LogMessage) -> dict[str, Any] | None:
    """The estimate record with the fields :meth:`LogSummary.lines` shows, each of its type (a field of
    another type is left out); None for a record without a numeric lat and lon."""
    try:
        rec = msg.decode()
    except LogError:
        return None
    if not isinstance(rec, dict) or _number(rec.get("lat")) is None or _number(rec.get("lon")) is None:
        return None
    out = {k: v for k, v in rec.items() if k not in ("lat", "lon", "error_m", "ambiguous", "region")}
    out.update(lat=_number(rec["lat"]), lon=_number(rec["lon"]))
    if _number(rec.get("error_m")) is not None:
        out["error_m"] = _number(rec["error_m"])
    if isinstance(rec.get("ambiguous"), bool):
        out["ambiguous"] = rec["ambiguous"]
    if isinstance(rec.get("region"), dict):
        out["region"] = rec["region"]
    return out


def summarize_log(path: str | Path) -> LogSummary:
    reader = LogReader(path, ErrorPolicy.SKIP)
    stats: dict[str, TopicStats] = {}
    estimate: dict[str, Any] | None = None
    truth: dict[str, Any] | None = None
    for msg in reader.messages():
        st = stats.setdefault(msg.topic, TopicStats(msg.schema_name, msg.message_encoding, msg.json_schema))
        st.count += 1
        st.first_ns = msg.log_time_ns if st.first_ns is None else min(st.first_ns, msg.log_time_ns)
        st.last_ns = msg.log_time_ns if st.last_ns is None else max(st.last_ns, msg.log_time_ns)
        if msg.topic == topics.ESTIMATE_RECORD:
            estimate = _estimate_record(msg) or estimate
        elif msg.topic == topics.ESTIMATE_FIX and estimate is None:
            estimate = _fix(msg)
        elif msg.topic == topics.GPS_TRUTH:
            truth = _fix(msg) or truth
    return LogSummary(
        path=Path(path),
        size_bytes=reader.size_bytes,
        complete=reader.complete,
        problem=reader.problem,
        topics=stats,
        estimate=estimate,
        truth=truth,
        profile=reader.header.profile if reader.header is not None else None,
        metadata=reader.metadata,
    )
