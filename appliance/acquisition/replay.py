"""Replay: rerun stitch -> skyline -> estimate from a session log's raw data, perhaps with another map
or other parameters, and report it.

A session log holds every frame (``/camera/image``, JPEG) with its tag (``/camera/capture``: stage
angle, true heading of the optical axis, roll and pitch; same log time as the frame), the camera's
calibration and the GPS ground truth.  :func:`read_session` gathers them (a truncated log gives
what it holds up to its last readable record, and says so); :func:`replay_session` reruns the
onboard chain on them and writes a results log (MCAP, the same estimate topics as a session);
:func:`replay_logs` replays several and reports them (:func:`appliance.outputs.report.write_replay_report`:
the pictures, a table of errors and the session's facts of each log, from
:mod:`appliance.acquisition.session_facts`); :func:`session_report` reports a session that has just run.

A replay is all or nothing in its output folder: its files are written in a hidden staging folder there
and moved into place only once all of them are written; on any failure (a full disk) the folder is left
as it was.  A killed replay's staging folder is removed by the next write into that folder.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from appliance.acquisition import onboard
from appliance.acquisition.log_metadata import write_log_metadata
from appliance.acquisition.platform import Frame
from appliance.acquisition.procedures import TaggedFrame
from appliance.acquisition.session_facts import FactsCollector, SessionFacts, read_session_facts
from appliance.atomic import atomic_output, check_output_folder, fsync_folder, output_error, temporary_path
from appliance.config import EstimatorConfig
from appliance.errors import ErrorPolicy, EstimationError, InputError, LogError, OutputError
from appliance.inputs import bounded_png, check_image_pixels
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.reader import LogMessage, LogReader
from appliance.logbook.writer import Logbook
from appliance.outputs.records import skyline_payload, write_estimate_records
from appliance.outputs.report import write_replay_report
from appliance.skyline import Skyline
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama
from appliance.vision.skyline_detect import detect_skyline

if TYPE_CHECKING:
    from appliance.acquisition.session import SessionResult
    from appliance.locating.position import Position
    from appliance.terrain.database import SkylineDatabase


@dataclass
class SessionData:
    """The raw data of one session log needed to rerun the estimate."""

    path: Path
    frames: list[TaggedFrame]
    intrinsics: CameraIntrinsics | None
    truth: tuple[float, float] | None  # GPS ground truth (lat, lon)
    onboard_error_m: float | None  # the onboard estimate's error, if the log has one
    complete: bool
    problem: str | None  # why reading stopped early (truncated, corrupt), or None
    facts: SessionFacts = field(default_factory=SessionFacts)
    traverse: bool = False  # the log is a traverse's (several stops; :mod:`appliance.acquisition.replay_traverse`)

    @property
    def frame_count(self) -> int:
        """The tagged frames read; a session reported as it ends loads none, and counts its capture tags."""
        return len(self.frames) if self.frames else self.facts.captures


@dataclass
class ReplayResult:
    name: str
    data: SessionData
    panorama: Panorama | None = None
    skyline: Skyline | None = None
    position: Position | None = None
    error_m: float | None = None
    notes: list[str] = field(default_factory=list)
    failure: str | None = None  # why no estimate
    results_log: Path | None = None
    pictures: list[Path] = field(default_factory=list)


def intrinsics_from_calibration(cal: Any) -> CameraIntrinsics:
    """The intrinsics of a foxglove.CameraCalibration (``K``, ``D``) or a ROS 2 sensor_msgs/msg/CameraInfo
    (``k``, ``d``)."""
    k = list(cal.K if hasattr(cal, "K") else cal.k)
    d = (list(cal.D if hasattr(cal, "D") else cal.d) + [0.0] * 5)[:5]
    return CameraIntrinsics(int(cal.width), int(cal.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                            (d[0], d[1], d[2], d[3], d[4]))


def read_session(path: str | Path) -> SessionData:
    """Frames with their tags, the intrinsics and the truth of a session log (up to its last readable
    record).  Raises :class:`LogError` for a file that is not a readable MCAP log at all."""
    reader = LogReader(path, ErrorPolicy.SKIP)
    collector = SessionCollector()
    for msg in reader.messages():
        collector.take(msg)
    return collector.finish(reader)


class SessionCollector:
    """Gathers a session's records (frames and tags, calibration, GPS truth, the onboard error and the
    facts) from a log's messages taken one by one; a traverse's replay keeps one per stop."""

    def __init__(self, intrinsics: CameraIntrinsics | None = None) -> None:
        self.images: dict[int, np.ndarray] = {}
        self.tags: dict[int, dict[str, Any]] = {}
        self.intrinsics = intrinsics
        self.truth: tuple[float, float] | None = None
        self.onboard_error: float | None = None
        self.undecodable = 0
        self.problem: str | None = None
        self.facts = FactsCollector()
        self.traverse = False  # the log holds a traverse's records

    def take(self, msg: LogMessage) -> None:
        try:
            self.facts.take(msg)
            if msg.topic in (t.ODOMETRY, t.TRAVERSE_STOP):
                self.traverse = True
            elif msg.topic == t.IMAGE:
                jpeg = bytes(msg.decode().data)
                check_image_pixels(jpeg, f"{msg.topic} at {msg.log_time_ns} ns")
                img = cv2.imdecode(np.frombuffer(bounded_png(jpeg), np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    self.undecodable += 1
                    return
                self.images[msg.log_time_ns] = img
            elif msg.topic == t.CAPTURE:
                self.tags[msg.log_time_ns] = _capture_tag(msg.decode())
            elif msg.topic == t.CALIBRATION:
                self.intrinsics = intrinsics_from_calibration(msg.decode())
            elif msg.topic == t.GPS_TRUTH:
                fix = msg.decode()
                self.truth = (float(fix.latitude), float(fix.longitude))
            elif msg.topic == t.ESTIMATE_RECORD:
                rec = msg.decode()
                if isinstance(rec, dict) and rec.get("error_m") is not None:
                    self.onboard_error = float(rec["error_m"])
        # a message of another encoding, schema or shape on its topic (no .data, no .latitude, a field
        # of another type) counts as undecodable, like a damaged one
        except (LogError, ValueError, TypeError, AttributeError, OverflowError) as exc:
            self.undecodable += 1
            if self.undecodable == 1:
                self.problem = f"undecodable message on {msg.topic}: {exc}"

    def finish(self, reader: LogReader) -> SessionData:
        """The session's data; ``reader`` (done reading) says whether the log was whole."""
        problem = self.problem or reader.problem  # an undecodable message came before any cut
        if reader.header is None and not self.images and not self.tags:
            raise LogError(f"{reader.path}: not a readable MCAP log ({problem or 'no records'})")
        frames = []
        for ns in sorted(set(self.images) & set(self.tags)):
            tag = self.tags[ns]
            frames.append(TaggedFrame(tag["index"], Frame(ns, self.images[ns]), tag["stage_deg"],
                                      tag["heading_deg"], tag["roll_deg"], tag["pitch_deg"]))
        return SessionData(reader.path, frames, self.intrinsics, self.truth, self.onboard_error, reader.complete,
                           problem, self.facts.facts, traverse=self.traverse)


def _capture_tag(payload: Any) -> dict[str, Any]:
    """A frame's tag (index, stage angle; heading, roll and pitch if known) from its ``/camera/capture``
    record; a record of another shape raises ``ValueError``."""
    if not isinstance(payload, dict):
        raise ValueError(f"a capture tag is a JSON object, got {type(payload).__name__}")
    index = payload.get("index")
    if isinstance(index, bool) or not isinstance(index, int):
        raise ValueError(f"capture tag index {index!r} is not an integer")
    tag: dict[str, Any] = {"index": index}
    for key in ("stage_deg", "heading_deg", "roll_deg", "pitch_deg"):
        v = payload.get(key)
        ok = v is None or (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v))
        if not ok or (v is None and key == "stage_deg"):
            raise ValueError(f"capture tag {key} {v!r} is not a finite number")
        tag[key] = None if v is None else float(v)
    return tag


def session_report(session: SessionResult, db: SkylineDatabase, out_dir: Path, title: str) -> Path:
    """The report, titled ``title``, of a session that has just run (its estimate, not a rerun), with the
    facts its log holds; the page's path."""
    truth = None
    if session.truth is not None and session.truth.lat_deg is not None and session.truth.lon_deg is not None:
        truth = (session.truth.lat_deg, session.truth.lon_deg)
    data = SessionData(path=session.log_path, frames=[], intrinsics=None, truth=truth,
                       onboard_error_m=session.error_m, complete=True, problem=None,
                       facts=read_session_facts(session.log_path))
    res = ReplayResult(session.log_path.stem, data, panorama=session.panorama, skyline=session.skyline,
                       position=session.estimate, error_m=session.error_m, results_log=session.log_path)
    return write_replay_report([res], db, out_dir, title)


def replay_session(data: SessionData, db: SkylineDatabase, cfg: EstimatorConfig, out_dir: Path,
                   into: Path | None = None) -> ReplayResult:
    """Stitch, detect, estimate; the results log goes to ``out_dir/<log name>.replay.mcap`` (written in
    ``into`` instead, a staging folder that becomes ``out_dir``, where given)."""
    name = data.path.stem
    res = ReplayResult(name, data)
    if not data.complete:
        res.notes.append(f"log incomplete ({data.problem}); replayed its {len(data.frames)} readable frames")
    try:
        if not data.frames:
            raise InputError("no tagged frames in the log")
        if data.intrinsics is None:
            raise InputError("no camera calibration in the log")
        pano = onboard.stitch_frames(data.frames, data.intrinsics)
        sky = detect_skyline(pano)
        res.panorama, res.skyline = pano, sky
        pos = onboard.locate_skyline(db, sky, cfg, source=str(data.path))
    except (InputError, EstimationError) as exc:
        res.failure = str(exc)
        return res
    res.position = pos
    log_path = out_dir / f"{name}.replay.mcap"
    now = data.frames[-1].frame.time_ns
    with results_logbook(log_path, into) as log:
        write_log_metadata(log, None, db, data.intrinsics)
        ok, jpeg = cv2.imencode(".jpg", pano.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        if ok:
            log.write_proto(t.PANORAMA, m.compressed_image(now, jpeg.tobytes(), frame_id="panorama"), now)
        if data.truth is not None:
            log.write_proto(t.GPS_TRUTH, m.location_fix(now, data.truth[0], data.truth[1], frame_id="truth"), now)
        log.write_json(t.SKYLINE_DETECTED, "viper.Skyline", skyline_payload(sky), now)
        rec = write_estimate_records(log, now, db, pos, sky, data.truth)
        for note in res.notes:
            log.write_proto(t.LOG, m.log_message(now, "warning", note, "replay"), now)
    res.error_m = rec.error_m
    res.results_log = log_path
    return res


@contextmanager
def results_logbook(log_path: Path, into: Path | None = None) -> Iterator[Logbook]:
    """A new results log to become ``log_path`` (written in the folder ``into`` instead, where given),
    in place only once it is closed whole; a failed write raises :class:`OutputError` naming it."""
    with atomic_output(check_output_folder(into or log_path.parent) / log_path.name) as tmp:
        tmp.unlink()  # the logbook creates its file itself and never opens an existing one
        try:
            with Logbook.create(tmp) as log:
                yield log
        except LogError as exc:  # the log's own words name its temporary: say it of the results log
            why = str(exc).rsplit(f"{tmp.name}: ", 1)[-1].split(";")[0]
            raise OutputError(f"{log_path}: cannot write: {why}") from None


def replay_logs(paths: list[Path], db: SkylineDatabase, cfg: EstimatorConfig, out_dir: Path,
                on_result: Any = None) -> tuple[list[ReplayResult], Path]:
    """Replay every log (an unreadable one is a row with its reason) and write the report; the files
    appear in ``out_dir`` all together once all are written, or none of them."""
    results = []
    with staged_output(out_dir) as staging:
        for p in paths:
            try:
                data = read_session(p)
            except LogError as exc:
                data = SessionData(path=Path(p), frames=[], intrinsics=None, truth=None, onboard_error_m=None,
                                   complete=False, problem=str(exc))
                r = ReplayResult(Path(p).stem, data, failure=str(exc))
            else:
                if data.traverse and len(paths) > 1:  # its stops' frames in one panorama would be a ghost
                    r = ReplayResult(Path(p).stem, data, failure="a traverse's log (several stops): replay it "
                                     "on its own, stop by stop")
                else:
                    r = replay_session(data, db, cfg, out_dir, into=staging)
            results.append(r)
            if on_result is not None:
                on_result(r)
        page = write_replay_report(results, db, out_dir, into=staging)
    return results, page


@contextmanager
def staged_output(out_dir: Path) -> Iterator[Path]:
    """A new hidden staging folder in ``out_dir`` (named as a temporary file, so that a dead writer's is
    removed by the next write there); on a clean exit its files replace those of the same names in
    ``out_dir`` (keeping their modes), and it is removed in any case."""
    staging = temporary_path(check_output_folder(out_dir) / "replay", "")
    try:
        staging.mkdir()
    except OSError as exc:
        raise output_error(staging, exc, "cannot create the folder") from None
    try:
        yield staging
        _publish(staging, out_dir)
    except OutputError as exc:  # said of the file it was to become
        named = OutputError(str(exc).replace(f"{staging}{os.sep}", f"{out_dir}{os.sep}"))
        named.errno = exc.errno
        raise named from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _publish(staging: Path, out_dir: Path) -> None:
    """Move every file of ``staging`` into ``out_dir`` (a file already there keeps its mode)."""
    for entry in sorted(staging.iterdir()):
        final = out_dir / entry.name
        try:
            try:
                os.chmod(entry, final.stat().st_mode & 0o7777)
            except FileNotFoundError:
                pass
            os.replace(entry, final)
        except OSError as exc:
            raise output_error(final, exc) from None
    fsync_folder(out_dir)
