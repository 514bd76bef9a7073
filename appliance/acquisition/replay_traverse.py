"""Replay of a traverse log stop by stop: each stop's own frames, compass and level tags and GPS truth,
fused with the odometry between stops as the onboard traverse fuses them.

A traverse (:mod:`appliance.acquisition.traverse`) writes its stops one after the other into one log:
the header (``/session/info``, the camera's calibration), then per stop its procedures
(``/session/procedure``: level first), frames, truth and estimate, and ``/traverse/stop``; before
every stop after the first, the odometry line(s) received (``/traverse/odometry``).  In file order, a
stop therefore begins at the first odometry message after a stop's procedures (:func:`read_traverse`).

:func:`replay_traverse` reruns stitch -> skyline -> estimate per stop, each stop after the first under
the prior the previous stop's posterior gives when moved by the odometry
(:class:`appliance.acquisition.traverse.FusionChain`, the onboard traverse's own), and writes one
results log (the onboard topics of a traverse: per stop the panorama, truth, skyline, the estimate
alone and fused, ``/traverse/stop`` and ``/traverse/track``).  The odometry is the log's own lines, or
another record of the rover's (``odometry``: a PX4 ULog's local positions at the stops' times,
:mod:`appliance.drivers.ulog_position`).  :func:`replay_traverse_log` adds the report
(:func:`appliance.outputs.report.write_traverse_report`) and the stop table, all in ``out_dir`` at once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from appliance.acquisition import onboard
from appliance.acquisition.log_metadata import write_log_metadata
from appliance.acquisition.procedures import Status, TruthResult
from appliance.acquisition.replay import SessionCollector, SessionData, results_logbook, staged_output
from appliance.acquisition.session import SessionResult
from appliance.acquisition.session_facts import FactsCollector, SessionFacts
from appliance.acquisition.traverse import (
    FusionChain,
    StopResult,
    TraverseResult,
    added_odometry,
    odometry_record,
    stop_record,
    track_features,
)
from appliance.config import EstimatorConfig
from appliance.drivers.odometry import OdometryReport
from appliance.errors import ErrorPolicy, EstimationError, InputError, LogError
from appliance.locating.position import truth_error_m
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.reader import LogMessage, LogReader
from appliance.outputs.records import estimate_fix, skyline_payload, write_estimate_records
from appliance.outputs.report import write_stop_table, write_traverse_report
from appliance.vision.skyline_detect import detect_skyline

if TYPE_CHECKING:
    from appliance.logbook.writer import Logbook
    from appliance.terrain.database import SkylineDatabase

_TRAVERSE_TOPICS = (t.ODOMETRY, t.TRAVERSE_STOP)


@dataclass
class LoggedStop:
    """One stop as its traverse log holds it: its own session data, the odometry lines received before
    it, and its ``/traverse/stop`` record (the onboard estimates and errors), if written."""

    index: int
    data: SessionData
    odometry: list[OdometryReport] = field(default_factory=list)
    record: dict[str, Any] | None = None

    @property
    def session_id(self) -> str | None:
        sid = None if self.record is None else self.record.get("session_id")
        return sid if isinstance(sid, str) else None

    def _onboard(self, key: str) -> float | None:
        est = None if self.record is None else self.record.get(key)
        err = est.get("error_m") if isinstance(est, dict) else None
        return float(err) if isinstance(err, (int, float)) and not isinstance(err, bool) else None

    @property
    def onboard_error_m(self) -> float | None:
        """The onboard (fused) estimate's error against the stop's GPS truth (m)."""
        err = self._onboard("position")
        return self.data.onboard_error_m if err is None else err

    @property
    def onboard_alone_error_m(self) -> float | None:
        return self._onboard("alone")

    @property
    def time_ns(self) -> int | None:
        """When the stop measured (its middle frame's log time; else its first message's)."""
        frames = self.data.frames
        return frames[len(frames) // 2].frame.time_ns if frames else self.data.facts.first_ns


@dataclass
class TraverseLog:
    """A log read stop by stop; ``is_traverse`` when it holds a traverse's topics."""

    path: Path
    traverse_id: str | None
    stops: list[LoggedStop]
    facts: SessionFacts  # of the whole log
    complete: bool
    problem: str | None
    is_traverse: bool


class _StopCollector:
    def __init__(self, index: int, previous: _StopCollector | None = None) -> None:
        self.index = index
        self.session: SessionCollector = SessionCollector(None if previous is None else previous.session.intrinsics)
        self.odometry: list[OdometryReport] = []
        self.record: dict[str, Any] | None = None
        self.started = False  # the stop's procedures have begun


def read_traverse(path: str | Path) -> TraverseLog:
    """A log's stops (a session log is one stop), up to its last readable record; a file that is not a
    readable MCAP log raises :class:`LogError`."""
    reader = LogReader(path, ErrorPolicy.SKIP)
    whole = FactsCollector()
    stops = [_StopCollector(0)]
    is_traverse = False
    for msg in reader.messages():
        try:
            whole.take(msg)
        except (LogError, ValueError):
            pass  # the stop's collector counts it as undecodable
        cur = stops[-1]
        if msg.topic in _TRAVERSE_TOPICS:
            is_traverse = True
            if msg.topic == t.ODOMETRY and cur.started:
                cur = _StopCollector(len(stops), cur)
                stops.append(cur)
            _take_traverse_message(cur, msg)
            continue
        if msg.topic == t.PROCEDURE:
            cur.started = True
        cur.session.take(msg)
    logged = []
    for i, c in enumerate(stops):
        data = c.session.finish(reader)
        if i < len(stops) - 1:  # a later stop began: this one is whole
            data.complete, data.problem = True, c.session.problem
        logged.append(LoggedStop(c.index, data, c.odometry, c.record))
    return TraverseLog(Path(path), whole.facts.session_id, logged, whole.facts, reader.complete, reader.problem,
                       is_traverse)


def _take_traverse_message(cur: _StopCollector, msg: LogMessage) -> None:
    try:
        payload = msg.decode()
        if not isinstance(payload, dict):
            raise ValueError(f"a JSON object, got {type(payload).__name__}")
        if msg.topic == t.TRAVERSE_STOP:
            cur.record = payload
            return
        cur.odometry.append(OdometryReport(int(payload["stop_id"]), float(payload["east_m"]),
                                           float(payload["north_m"]), float(payload["sigma_m"]),
                                           int(payload.get("receive_time_ns") or msg.log_time_ns),
                                           bool(payload.get("reset", False))))
    except (LogError, ValueError, TypeError, KeyError) as exc:
        cur.session.undecodable += 1
        cur.session.problem = cur.session.problem or f"undecodable message on {msg.topic}: {exc}"


def _truth_result(data: SessionData) -> TruthResult | None:
    """The stop's GPS truth as its truth procedure ended (what the onboard session keeps: only an ok one)."""
    f = data.facts
    o = f.procedures.get("truth")
    if data.truth is None or o is None or o.status != Status.OK.value:
        return None
    return TruthResult(Status.OK, data.truth[0], data.truth[1], None, f.truth_sigma_m, None, None,
                       f.truth_fixes_used or 0, 0)


def _estimate_stop(stop: StopResult, logged: LoggedStop, db: SkylineDatabase, cfg: EstimatorConfig) -> None:
    """Stitch, detect and estimate the stop alone and, under its prior, fused; into ``stop.session``."""
    s, data = stop.session, logged.data
    s.outcomes = {name: o.status for name, o in data.facts.procedures.items() if name != "estimate"}
    s.truth, s.frames = _truth_result(data), len(data.frames)
    try:
        if not data.frames:
            raise InputError("no tagged frames in the stop")
        if data.intrinsics is None:
            raise InputError("no camera calibration in the log")
        s.panorama = onboard.stitch_frames(data.frames, data.intrinsics)
        s.skyline = detect_skyline(s.panorama)
        pos = onboard.locate_skyline(db, s.skyline, cfg, source=s.session_id)
        if stop.log_prior is not None:
            s.estimate_alone = pos
            s.error_alone_m = None if data.truth is None else truth_error_m(db, pos, data.truth)
            pos = onboard.locate_skyline(db, s.skyline, cfg, source=s.session_id, log_prior=stop.log_prior,
                                         position_prior=stop.position_prior)
    except (InputError, EstimationError) as exc:
        s.outcomes["estimate"], s.status = Status.FAILED.value, Status.FAILED
        s.problems.append(f"estimate: {exc}")
        return
    s.estimate = pos
    s.error_m = None if data.truth is None else truth_error_m(db, pos, data.truth)
    s.status = Status.AMBIGUOUS if pos.result.ambiguous else Status.OK
    s.outcomes["estimate"] = s.status.value


def replay_traverse(log: TraverseLog, db: SkylineDatabase, cfg: EstimatorConfig,
                    odometry: Sequence[OdometryReport] | None = None,
                    on_stop: Callable[[StopResult, LoggedStop], None] | None = None) -> TraverseResult:
    """Every stop of ``log`` replayed in order, each after the first fused with the one before through
    the odometry: the log's lines, or ``odometry`` (the legs 1, 2, ... of another record) when given."""
    if odometry is not None and len(odometry) != len(log.stops) - 1:
        raise InputError(f"{log.path}: {len(log.stops)} stops need {len(log.stops) - 1} odometry legs, "
                         f"got {len(odometry)}")
    chain = FusionChain(db)
    traverse_id = log.traverse_id or log.path.stem
    result = TraverseResult(log.path, traverse_id)
    for i, logged in enumerate(log.stops):
        lines = logged.odometry if odometry is None else list(odometry[i - 1:i]) if i > 0 else []
        total = None
        for rep in lines:
            chain.take_move(rep)
            total = added_odometry(total, rep)
        if i > 0 and not lines:
            chain.lose(f"no odometry logged before stop {i}: not fused")
        session = SessionResult(log.path, logged.session_id or f"{traverse_id}-{i}")
        stop = chain.prepare_stop(i, session, total)
        _estimate_stop(stop, logged, db, cfg)
        chain.settle(stop)
        result.stops.append(stop)
        if on_stop is not None:
            on_stop(stop, logged)
    return result


def write_traverse_log(logbook: Logbook, db: SkylineDatabase, result: TraverseResult, log: TraverseLog) -> None:
    """The replayed stops into ``logbook`` on the onboard traverse's topics, each at its last frame's time."""
    for n, (stop, logged) in enumerate(zip(result.stops, log.stops, strict=True)):
        s, data = stop.session, logged.data
        now = data.frames[-1].frame.time_ns if data.frames else (logged.time_ns or 0)
        if stop.odometry is not None:  # the displacement the stop took (the lines added up)
            logbook.write_json(t.ODOMETRY, "viper.Odometry", odometry_record(stop.odometry), now)
        if s.estimate is None or s.skyline is None:
            continue
        if s.panorama is not None:
            ok, jpeg = cv2.imencode(".jpg", s.panorama.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
            if ok:
                logbook.write_proto(t.PANORAMA, m.compressed_image(now, jpeg.tobytes(), frame_id="panorama"), now)
        if data.truth is not None:
            logbook.write_proto(t.GPS_TRUTH, m.location_fix(now, data.truth[0], data.truth[1], frame_id="truth"),
                                now)
        logbook.write_json(t.SKYLINE_DETECTED, "viper.Skyline", skyline_payload(s.skyline), now)
        if stop.fused and s.estimate_alone is not None:
            logbook.write_proto(t.ESTIMATE_ALONE_FIX, estimate_fix(db, s.estimate_alone, now, "estimate_alone"), now)
        write_estimate_records(logbook, now, db, s.estimate, s.skyline, data.truth)
        logbook.write_json(t.TRAVERSE_STOP, "viper.TraverseStop", stop_record(db, stop), now)
        features = track_features(result.stops[:n + 1])
        if features:
            logbook.write_proto(t.TRAVERSE_TRACK, m.geojson(features), now)


@dataclass
class TraverseReplay:
    """A traverse replayed: the log read, the stops replayed, where the odometry came from, the files."""

    log: TraverseLog
    result: TraverseResult
    odometry_source: str
    results_log: Path
    page: Path
    table: Path


def replay_traverse_log(log: TraverseLog, db: SkylineDatabase, cfg: EstimatorConfig, out_dir: Path,
                        odometry: Sequence[OdometryReport] | None = None, odometry_source: str = "",
                        on_stop: Callable[[StopResult, LoggedStop], None] | None = None) -> TraverseReplay:
    """Replay ``log`` stop by stop and write its results log, ``report.html`` (the track, a row per stop
    with its coordinates, errors and the onboard ones), a picture per stop and ``summary.csv`` (the stop
    table) into ``out_dir``, all together once all are written, or none of them."""
    source = odometry_source or "the log's odometry lines"
    result = replay_traverse(log, db, cfg, odometry, on_stop)
    results_log = out_dir / f"{log.path.stem}.replay.mcap"
    onboard_errors = [s.onboard_error_m for s in log.stops]
    with staged_output(out_dir) as staging:
        with results_logbook(results_log, staging) as logbook:
            first = log.stops[0].data if log.stops else None
            write_log_metadata(logbook, None, db, first.intrinsics if first is not None else None)
            write_traverse_log(logbook, db, result, log)
        title = (f"Viper replay of a traverse: {log.traverse_id or log.path.stem}, {len(result.stops)} stops "
                 f"(odometry: {source})")
        notes = [] if log.complete else [f"log incomplete ({log.problem}); replayed its {len(log.stops)} stops"]
        page = write_traverse_report(result, db, out_dir, title, log.facts, into=staging,
                                     onboard_error_m=onboard_errors, results_log=results_log, notes=notes)
        table = write_stop_table(db, result.stops, out_dir / "summary.csv", into=staging,
                                 onboard_error_m=onboard_errors)
    return TraverseReplay(log, result, source, results_log, page, table)


def is_traverse_log(path: str | Path) -> bool:
    """Whether the log at ``path`` holds a traverse's records (odometry lines, stop records); a log that
    cannot be read is not one (its replay says why)."""
    try:
        return any(msg.topic in _TRAVERSE_TOPICS for msg in LogReader(path, ErrorPolicy.SKIP).messages())
    except LogError:
        return False


def stop_times_ns(log: TraverseLog) -> list[int]:
    """When each stop measured (UTC ns): its middle frame's time; a stop with no message raises
    :class:`InputError`."""
    times = []
    for s in log.stops:
        if s.time_ns is None:
            raise InputError(f"{log.path}: stop {s.index} holds no message to place it in time")
        times.append(s.time_ns)
    return times
