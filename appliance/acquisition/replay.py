"""Replay: rerun stitch -> skyline -> estimate from a session log's raw data, perhaps with another map
or other parameters, and report it.

A session log holds every frame (``/camera/image``, JPEG) with its tag (``/camera/capture``: stage
angle, true heading of the optical axis, roll and pitch; same log time as the frame), the camera's
calibration and the GPS ground truth.  :func:`read_session` gathers them (a truncated log gives
what it holds up to its last readable record, and says so); :func:`replay_session` reruns the
onboard chain on them and writes a results log (MCAP, the same estimate topics as a session);
:func:`write_report` draws the pictures and one HTML page (:mod:`appliance.outputs.html`), with a
table of errors when several logs are replayed and the session's facts of each log
(:mod:`appliance.acquisition.session_facts`).
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from appliance.acquisition import onboard
from appliance.acquisition.platform import Frame
from appliance.acquisition.procedures import TaggedFrame
from appliance.acquisition.session_facts import FactsCollector, SessionFacts, read_session_facts
from appliance.atomic import atomic_output, check_output_folder, write_text_atomic
from appliance.config import EstimatorConfig
from appliance.errors import ErrorPolicy, EstimationError, InputError, LogError
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.reader import LogReader
from appliance.logbook.writer import Logbook
from appliance.skyline import Skyline
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama

if TYPE_CHECKING:
    from appliance.acquisition.session import SessionResult
    from appliance.locate.position import Position
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
    k = list(cal.K)
    d = (list(cal.D) + [0.0] * 5)[:5]
    return CameraIntrinsics(int(cal.width), int(cal.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                            (d[0], d[1], d[2], d[3], d[4]))


def read_session(path: str | Path) -> SessionData:
    """Frames with their tags, the intrinsics and the truth of a session log (up to its last readable
    record).  Raises :class:`LogError` for a file that is not a readable MCAP log at all."""
    reader = LogReader(path, ErrorPolicy.SKIP)
    images: dict[int, np.ndarray] = {}
    tags: dict[int, dict[str, Any]] = {}
    intr = None
    truth = None
    onboard_error = None
    undecodable = 0
    facts = FactsCollector()
    for msg in reader.messages():
        try:
            facts.take(msg)
            if msg.topic == t.IMAGE:
                img = cv2.imdecode(np.frombuffer(msg.decode().data, np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    undecodable += 1
                    continue
                images[msg.log_time_ns] = img
            elif msg.topic == t.CAPTURE:
                tags[msg.log_time_ns] = msg.decode()
            elif msg.topic == t.CALIBRATION:
                intr = intrinsics_from_calibration(msg.decode())
            elif msg.topic == t.GPS_TRUTH:
                fix = msg.decode()
                truth = (float(fix.latitude), float(fix.longitude))
            elif msg.topic == t.ESTIMATE_RECORD:
                rec = msg.decode()
                if isinstance(rec, dict) and rec.get("error_m") is not None:
                    onboard_error = float(rec["error_m"])
        except (LogError, ValueError) as exc:
            undecodable += 1
            if undecodable == 1:
                reader.problem = reader.problem or f"undecodable message on {msg.topic}: {exc}"
    if reader.header is None and not images and not tags:
        raise LogError(f"{path}: not a readable MCAP log ({reader.problem or 'no records'})")
    frames = []
    for ns in sorted(set(images) & set(tags)):
        tag = tags[ns]
        frames.append(TaggedFrame(int(tag["index"]), Frame(ns, images[ns]), float(tag["stage_deg"]),
                                  tag.get("heading_deg"), tag.get("roll_deg"), tag.get("pitch_deg")))
    return SessionData(Path(path), frames, intr, truth, onboard_error, reader.complete, reader.problem, facts.facts)


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
    return write_report([res], db, out_dir, title)


def replay_session(data: SessionData, db: SkylineDatabase, cfg: EstimatorConfig, out_dir: Path) -> ReplayResult:
    """Stitch, detect, estimate; the results log goes to ``out_dir/<log name>.replay.mcap``."""
    from appliance.outputs.records import skyline_payload, write_estimate_records
    from appliance.vision.skyline_detect import detect_skyline

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
    check_output_folder(out_dir)
    log_path = out_dir / f"{name}.replay.mcap"
    now = data.frames[-1].frame.time_ns
    with atomic_output(log_path) as tmp:
        tmp.unlink()  # the logbook creates its file itself and never opens an existing one
        with Logbook.create(tmp) as log:
            ok, jpeg = cv2.imencode(".jpg", pano.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
            if ok:
                log.write_proto(t.PANORAMA, m.compressed_image(now, jpeg.tobytes(), frame_id="panorama"), now)
            if data.truth is not None:
                log.write_proto(t.GPS_TRUTH, m.location_fix(now, data.truth[0], data.truth[1], frame_id="truth"),
                                now)
            log.write_json(t.SKYLINE_DETECTED, "viper.Skyline", skyline_payload(sky), now)
            rec = write_estimate_records(log, now, db, pos, sky, data.truth)
            for note in res.notes:
                log.write_proto(t.LOG, m.log_message(now, "warning", note, "replay"), now)
    res.error_m = rec.error_m
    res.results_log = log_path
    return res


# ------------------------------------------------------------------------------------------- report
def panorama_picture(res: ReplayResult, db: SkylineDatabase, path: Path) -> None:
    """The panorama with the detected skyline and the one rendered at the estimate (heading corrected)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    assert res.panorama is not None and res.skyline is not None and res.position is not None
    from appliance.outputs.records import rendered_skyline

    pano, sky, pos = res.panorama, res.skyline, res.position
    rendered = rendered_skyline(db, pos)
    h, w = pano.image.shape[:2]
    fig, ax = plt.subplots(figsize=(16, 16 * h / w + 1.0))
    ax.imshow(cv2.cvtColor(pano.image, cv2.COLOR_BGR2RGB), aspect="auto")
    ok = np.isfinite(sky.elevation_deg)
    ax.plot(pano.azimuth_to_column(sky.azimuth_deg[ok]), pano.elevation_to_row(sky.elevation_deg[ok]), ".",
            color="cyan", ms=2, label="detected skyline")
    # the measured azimuth a sees the map's a + correction
    az = (rendered.azimuth_deg - pos.result.heading_correction_deg) % 360.0
    order = np.argsort(az)
    ax.plot(pano.azimuth_to_column(az[order]), pano.elevation_to_row(rendered.elevation_deg[order]), "-",
            color="orange", lw=1.0, label="rendered at the estimate")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xlabel("column (azimuth clockwise from true north)")
    ax.set_title(f"{res.name}: heading correction {pos.result.heading_correction_deg:+.1f} deg")
    ax.legend(loc="lower right")
    fig.tight_layout()
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=80, format="png")
    finally:
        plt.close(fig)


def _fmt(v: float | None, spec: str = ".1f") -> str:
    return "" if v is None or not math.isfinite(v) else format(v, spec)


def summary_rows(results: list[ReplayResult], db: SkylineDatabase, out_dir: Path) -> list[dict[str, str]]:
    """One row per log; logs are named relative to ``out_dir``, where the table is written."""
    from appliance.locate.position import estimate_status

    rows = []
    for r in results:
        p = r.position
        rows.append({
            "log": Path(os.path.relpath(os.path.abspath(r.data.path), os.path.abspath(out_dir))).as_posix(),
            "status": "" if p is None else estimate_status(db, p, r.data.truth),
            "frames": str(r.data.frame_count),
            "complete": "yes" if r.data.complete else "no",
            "lat": "" if p is None else f"{p.lat:.6f}",
            "lon": "" if p is None else f"{p.lon:.6f}",
            "truth_lat": "" if r.data.truth is None else f"{r.data.truth[0]:.6f}",
            "truth_lon": "" if r.data.truth is None else f"{r.data.truth[1]:.6f}",
            "error_m": _fmt(r.error_m),
            "onboard_error_m": _fmt(r.data.onboard_error_m),
            "region_km2": "" if p is None else f"{p.result.region_area_m2 / 1e6:.4f}",
            "valid_azimuths": "" if r.skyline is None else str(int(r.skyline.valid.sum())),
            "heading_correction_deg": "" if p is None else f"{p.result.heading_correction_deg:+.2f}",
            "failure": r.failure or "",
        })
    return rows


def write_report(results: list[ReplayResult], db: SkylineDatabase, out_dir: Path, title: str | None = None) -> Path:
    """PNG pictures per log, ``summary.csv`` and ``report.html`` (titled ``title``, by default "Viper replay
    of N logs"); returns the HTML page's path."""
    from appliance.locate.position import estimate_status
    from appliance.outputs import html as rp
    from appliance.outputs.records import write_png

    check_output_folder(out_dir)
    for r in results:
        if r.position is None or r.skyline is None:
            continue
        map_png = out_dir / f"{r.name}.map.png"
        write_png(db, r.position, r.skyline, map_png, truth=r.data.truth)
        pano_png = out_dir / f"{r.name}.panorama.png"
        panorama_picture(r, db, pano_png)
        r.pictures = [map_png, pano_png]
    rows = summary_rows(results, db, out_dir)
    csv_path = out_dir / "summary.csv"
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, fieldnames=list(rows[0]) if rows else ["log"])
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(csv_path, table.getvalue())
    if title is None:
        title = f"Viper replay of {len(results)} log{'s' if len(results) != 1 else ''}"
    parts = [rp.paragraph(rp.shown_path(db.path, out_dir), "Skyline database:")]
    errors = [r.error_m for r in results if r.error_m is not None]
    if errors:
        parts.append(f"<p>Error against the GPS truth: median {np.median(errors):.1f} m, max {max(errors):.1f} m "
                     f"over {len(errors)} estimate{'s' if len(errors) != 1 else ''} "
                     f"({rp.link(csv_path, out_dir, 'CSV')})</p>")
    def shown(r: ReplayResult, text: str) -> str:
        return rp.without_folders(text, [r.data.path, db.path, *([r.results_log] if r.results_log else [])], out_dir)

    shown_rows = [{k: rp.shown_path(r.data.path, out_dir) if k == "log" else shown(r, v) for k, v in row.items()}
                  for row, r in zip(rows, results, strict=True)]
    parts.append(rp.table(shown_rows, {i: f"#log-{i + 1}" for i in range(len(results))}))
    for i, r in enumerate(results):
        parts.append(rp.heading(r.name, anchor=f"log-{i + 1}"))
        for note in r.notes:
            parts.append(rp.paragraph(shown(r, note), "note:"))
        if r.failure:
            parts.append(rp.paragraph(shown(r, r.failure), "no estimate:"))
        if r.position is not None:
            err = "no GPS truth" if r.error_m is None else f"{r.error_m:.1f} m from the GPS truth"
            status = estimate_status(db, r.position, r.data.truth)
            parts.append(rp.paragraph(f"{r.position.lat:.6f}, {r.position.lon:.6f} {status}: {err}", "estimate"))
        if r.results_log is not None:
            parts.append(f"<p><b>results log</b> {rp.link(r.results_log, out_dir)}</p>")
        parts.append(rp.facts_table(r.data.facts.rows()))
        for pic in r.pictures:
            parts.append(rp.image(pic, out_dir, pic.stem))
    page = out_dir / "report.html"
    write_text_atomic(page, rp.page(title, parts))
    return page


def replay_logs(paths: list[Path], db: SkylineDatabase, cfg: EstimatorConfig, out_dir: Path,
                on_result: Any = None) -> tuple[list[ReplayResult], Path]:
    """Replay every log (an unreadable one is a row with its reason) and write the report."""
    results = []
    for p in paths:
        try:
            data = read_session(p)
        except LogError as exc:
            data = SessionData(path=Path(p), frames=[], intrinsics=None, truth=None, onboard_error_m=None,
                               complete=False, problem=str(exc))
            r = ReplayResult(Path(p).stem, data, failure=str(exc))
        else:
            r = replay_session(data, db, cfg, out_dir)
        results.append(r)
        if on_result is not None:
            on_result(r)
    return results, write_report(results, db, out_dir)
