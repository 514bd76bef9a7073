"""The results of ``viper capture`` and ``viper replay`` as one JSON object each (``--json``): what the
text output says, with the estimate's full record (the ``/estimate/record`` of the logs).

A session that has just run is described from its result and its own log (the estimate records and
``/traverse/stop`` records it wrote); a replay from its results.  Numbers that are not finite become
null, so that the object is strict JSON.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from appliance.acquisition.traverse import stop_record
from appliance.errors import ErrorPolicy, LogError
from appliance.locating.position import estimate_status
from appliance.logbook import topics as t
from appliance.logbook.reader import LogReader
from appliance.outputs.records import estimate_record

if TYPE_CHECKING:
    from appliance.acquisition.replay import ReplayResult
    from appliance.acquisition.replay_traverse import TraverseReplay
    from appliance.acquisition.session import SessionResult
    from appliance.terrain.database import SkylineDatabase


def strict(value: Any) -> Any:
    """``value`` with every non-finite float as None and numpy scalars and tuples as plain JSON values."""
    if isinstance(value, dict):
        return {str(k): strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, (str, int)):
        return value
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return strict(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return str(value)


def dumps(obj: dict[str, Any]) -> str:
    """``obj`` as one line of strict JSON."""
    return json.dumps(strict(obj), allow_nan=False)


def _logged_records(path: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The ``/estimate/record`` and ``/traverse/stop`` records of a log, in order (what is readable)."""
    estimates: list[dict[str, Any]] = []
    stops: list[dict[str, Any]] = []
    try:
        for msg in LogReader(path, ErrorPolicy.SKIP).messages():
            if msg.topic in (t.ESTIMATE_RECORD, t.TRAVERSE_STOP):
                try:
                    rec = msg.decode()
                except LogError:
                    continue
                if isinstance(rec, dict):
                    (estimates if msg.topic == t.ESTIMATE_RECORD else stops).append(rec)
    except LogError:
        pass  # a log that cannot be read (removed, never written) holds no record
    return estimates, stops


def capture_json(result: SessionResult) -> dict[str, Any]:
    """``viper capture``'s result: the log, the session's status, outcomes and problems, and the last
    estimate's record as the log holds it (with a traverse's ``stops``, each stop's record)."""
    estimates, stops = _logged_records(result.log_path)
    obj: dict[str, Any] = {
        "log": str(result.log_path),
        "session_id": result.session_id,
        "status": result.status.value,
        "frames": result.frames,
        "outcomes": dict(result.outcomes),
        "problems": list(result.problems),
        "estimate": estimates[-1] if result.estimate is not None and estimates else None,
        "error_m": result.error_m,
        "log_error": result.log_error,
    }
    if stops or getattr(result, "stops", None):
        obj["traverse"] = True
        obj["stops"] = stops
    return obj


def replay_json(db: SkylineDatabase, results: Sequence[ReplayResult], page: Path,
                outside: Sequence[str] = ()) -> dict[str, Any]:
    """``viper replay``'s result for session logs: per log its estimate record, errors and files."""
    logs = []
    for r in results:
        p, sky = r.position, r.skyline
        logs.append({
            "log": str(r.data.path),
            "traverse": False,
            "frames": len(r.data.frames),
            "complete": r.data.complete,
            "status": None if p is None else estimate_status(db, p, r.data.truth),
            "error_m": r.error_m,
            "onboard_error_m": r.data.onboard_error_m,
            "estimate": None if p is None or sky is None else estimate_record(db, p, sky, r.data.truth).record,
            "results_log": None if r.results_log is None else str(r.results_log),
            "notes": list(r.notes),
            "failure": r.failure,
            "truth_outside_database": str(r.data.path) in outside,
        })
    return {"report": str(page), "table": str(page.parent / "summary.csv"), "logs": logs}


def traverse_replay_json(db: SkylineDatabase, replay: TraverseReplay) -> dict[str, Any]:
    """``viper replay``'s result for a traverse's log: per stop the ``/traverse/stop`` record of the
    replay, the estimate's record, and the onboard errors beside."""
    stops = []
    for s, logged in zip(replay.result.stops, replay.log.stops, strict=True):
        rec = stop_record(db, s)
        ses = s.session
        rec["estimate"] = (None if ses.estimate is None or ses.skyline is None
                           else estimate_record(db, ses.estimate, ses.skyline, logged.data.truth).record)
        rec["frames"] = len(logged.data.frames)
        rec["onboard_error_m"] = logged.onboard_error_m
        rec["onboard_alone_error_m"] = logged.onboard_alone_error_m
        rec["failure"] = "; ".join(ses.problems) or None
        stops.append(rec)
    return {
        "log": str(replay.log.path),
        "traverse": True,
        "traverse_id": replay.result.session_id,
        "complete": replay.log.complete,
        "odometry": replay.odometry_source,
        "results_log": str(replay.results_log),
        "report": str(replay.page),
        "table": str(replay.table),
        "stops": stops,
    }
