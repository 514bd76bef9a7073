"""One field session: level, compass, ground truth, capture, onboard estimate, all into one MCAP log.

A failing device degrades the session (the procedure is marked degraded or failed, the reason is
logged on ``/log`` and ``/session/procedure``) instead of ending it; a full disk (or any failed
write) ends it cleanly with the log sealed, and a log that cannot be opened, or holds nothing when
the disk fails, is removed: :class:`LogError` then says so and no file is left; a stop request
(SIGTERM in the daemon) is honoured between captures and the log is closed properly.  The session
daemon hands faults it saw before a session (devices that did not answer) to the session's log with
:func:`earlier_faults`.  The simulated session of the demo is :mod:`appliance.sim.field_session`.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from appliance.acquisition import onboard, procedures
from appliance.acquisition.clock_check import check_clock
from appliance.acquisition.log_metadata import write_log_metadata
from appliance.acquisition.platform import Frame, Platform, platform_of
from appliance.acquisition.procedures import CaptureProblem, Status, TaggedFrame
from appliance.config import Config
from appliance.drivers.factory import Devices
from appliance.errors import DeviceError, EstimationError, InputError, LogError, ViperError
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook, LogbookFullError
from appliance.skyline import Skyline

if TYPE_CHECKING:
    from appliance.estimator.exact import PositionPrior
    from appliance.locating.position import Position
    from appliance.logbook.live import Publisher
    from appliance.terrain.database import SkylineDatabase


class StopRequestedError(Exception):
    """Raised inside a session when a stop was requested; the session closes its log and returns."""


#: warnings the next log written in this context starts with (:func:`earlier_faults`)
_EARLIER_FAULTS: ContextVar[tuple[str, ...]] = ContextVar("earlier_faults", default=())


@contextmanager
def earlier_faults(lines: Sequence[str]) -> Iterator[None]:
    """Sessions (and traverses) started inside write ``lines`` as warnings at the start of their
    log: what went wrong before them that no log holds (the daemon's devices that did not answer)."""
    token = _EARLIER_FAULTS.set(tuple(lines))
    try:
        yield
    finally:
        _EARLIER_FAULTS.reset(token)


@dataclass
class SessionResult:
    log_path: Path
    session_id: str
    status: Status = Status.OK
    outcomes: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    truth: procedures.TruthResult | None = None
    estimate: Position | None = None
    error_m: float | None = None
    frames: int = 0
    stopped: bool = False
    disk_full: bool = False
    # why the log ended early (a full disk, a failed write); the log keeps what was durable before
    log_error: str | None = None
    panorama: Any = None
    skyline: Skyline | None = None
    # with a prior (a traverse's stop after the first): the estimate from this skyline alone, and its error;
    # ``estimate`` is then the fused one
    estimate_alone: Position | None = None
    error_alone_m: float | None = None
    # the system clock against the GPS time (s, positive: ahead), and the fault line when beyond the limit
    clock_offset_s: float | None = None
    clock_fault: str | None = None
    # the skyline database ``estimate`` is on (its grid, for the map's layers written beside the log)
    database: SkylineDatabase | None = None
    # the map's layers written beside the log (:func:`appliance.acquisition.daemon.run_one_session`), and
    # why they could not be written
    map_layers: tuple[Path, ...] = ()
    layers_error: str | None = None


def magnetic_declination_deg(lat_deg: float, lon_deg: float, when: dt.datetime) -> float:
    """Declination (deg, east positive) of the World Magnetic Model at a place and time."""
    from pygeomag import GeoMag

    year = when.year + (when.timetuple().tm_yday - 0.5) / 365.25
    return float(GeoMag().calculate(glat=lat_deg, glon=lon_deg, alt=0.0, time=year).d)


def _utc(ns: int) -> dt.datetime:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.timezone.utc)


class Session:
    """Runs the procedures on a platform and writes everything into ``logbook``."""

    def __init__(
        self,
        platform: Platform,
        logbook: Logbook,
        config: Config,
        db: SkylineDatabase | None,
        result: SessionResult,
        should_stop: Callable[[], bool] = lambda: False,
        on_status: Callable[[str], None] = lambda s: None,
        approx_position: tuple[float, float] | None = None,
        log_prior: np.ndarray | None = None,
        position_prior: PositionPrior | None = None,
    ) -> None:
        self.p, self.log, self.cfg = platform, logbook, config
        self.db, self.result = db, result
        self.should_stop, self.on_status = should_stop, on_status
        self.approx = approx_position
        self.log_prior, self.position_prior = log_prior, position_prior

    # -------------------------------------------------------------------------------- helpers
    def now(self) -> int:
        return self.p.clock.now_ns()

    def say(self, level: str, text: str) -> None:
        self.log.write_proto(t.LOG, m.log_message(self.now(), level, text, "session"), self.now())
        if level in ("warning", "error"):
            self.result.problems.append(text)

    def outcome(self, name: str, status: Status, reason: str = "", **extra: Any) -> None:
        self.result.outcomes[name] = status.value
        if status is Status.AMBIGUOUS:
            if self.result.status is Status.OK:
                self.result.status = Status.AMBIGUOUS
        elif status is not Status.OK and self.result.status in (Status.OK, Status.AMBIGUOUS):
            self.result.status = Status.DEGRADED
        payload = {"procedure": name, "status": status.value, "reason": reason, **extra}
        self.log.write_json(t.PROCEDURE, "viper.Procedure", payload, self.now())
        if reason:
            self.say("warning" if status is not Status.OK else "info", f"{name}: {reason}")
        self.log.flush()

    def check_stop(self) -> None:
        if self.should_stop():
            raise StopRequestedError()

    # ----------------------------------------------------------------------------- the session
    def run(self) -> SessionResult:
        r = self.result
        try:
            self.write_header()
            self.run_procedures()
        except StopRequestedError:
            self.stopped()
        except LogError as exc:
            if self.log.is_open:
                raise
            self.log_failed(exc)
        finally:
            self.close_log()
        if r.log_error is not None and self.log.messages_durable == 0:
            raise LogError(f"{r.log_error}; it held no message: {remove_unwritten_log(r.log_path)}")
        return r

    def write_header(self) -> None:
        """The metadata records (software, configuration, calibrations, map), the session's description
        and the camera's calibration, once at the start of the log."""
        write_log_metadata(self.log, self.cfg, self.db, self.p.camera.intrinsics if self.p.camera is not None else None)
        self.log.write_json(t.SESSION, "viper.Session", {"session_id": self.result.session_id}, self.now())
        if self.p.camera is not None:
            intr = self.p.camera.intrinsics
            self.log.write_proto(t.CALIBRATION, m.camera_calibration(self.now(), intr), self.now())
            self.log.write_proto(t.TF, m.optical_transform(self.now()), self.now())
        for text in _EARLIER_FAULTS.get():
            self.say("warning", text)

    def run_procedures(self) -> None:
        """Level, compass, truth, capture, estimate into the log (left open: a traverse writes its
        stops one after the other into one log); raises StopRequestedError and LogbookFullError."""
        r = self.result
        self.say("info", f"session {r.session_id} started")
        self.log.flush()
        self.step("level", self.do_level)
        compass = self.step("compass", self.do_compass)
        truth = self.step("truth", self.do_truth)
        frames = self.step("capture", lambda: self.do_capture(compass, truth)) or []
        self.step("estimate", lambda: self.do_estimate(frames, truth))
        self.say("info", f"session {r.session_id} finished: {r.status.value}")

    def stopped(self) -> None:
        """A stop request ended the session: recorded in the result and the log."""
        self.result.stopped = True
        self.result.status = Status.DEGRADED
        self.say("warning", "session stopped on request; log closed with everything captured so far")

    def close_log(self) -> None:
        """Close the log; a summary that cannot be written leaves it sealed at the end of its data."""
        try:
            self.log.close()
        except LogError as exc:
            self.log_failed(exc)

    def log_failed(self, exc: LogError) -> None:
        """The log took no more writes (a full disk, an I/O error): the session failed there."""
        self.result.disk_full = isinstance(exc, LogbookFullError)
        self.result.status = Status.FAILED
        self.result.log_error = str(exc)

    def step(self, name: str, action: Callable[[], Any]) -> Any:
        self.check_stop()
        self.on_status(f"{name}...")
        try:
            return action()
        except (StopRequestedError, LogbookFullError):
            raise
        except (DeviceError, EstimationError, InputError) as exc:
            self.outcome(name, Status.FAILED, str(exc))
            return None
        except ViperError as exc:
            if isinstance(exc, LogError) and not self.log.is_open:
                raise  # the log itself failed: the session ends there (run)
            self.outcome(name, Status.FAILED, f"{type(exc).__name__}: {exc}")
            return None

    def do_level(self) -> procedures.LevelResult | None:
        if self.p.tilt is None:
            self.outcome("level", Status.DEGRADED, "no inclinometer: residual tilt unknown")
            return None

        def on_reading(reading: Any) -> None:
            payload = {"roll_deg": reading.roll_deg, "pitch_deg": reading.pitch_deg}
            self.log.write_json(t.TILT_RAW, "viper.TiltRaw", payload, reading.time_ns)

        res = procedures.level(self.p.tilt, self.p.leveller, self.p.clock, self.cfg.session, on_reading)
        for text in res.instructions:
            self.say("info", f"level: {text}")
        self.outcome("level", res.status, res.reason, roll_deg=res.roll_deg, pitch_deg=res.pitch_deg)
        return res

    def do_compass(self) -> procedures.CompassResult | None:
        if self.p.compass is None or self.p.stage is None:
            self.outcome("compass", Status.FAILED, "no compass or no stage: heading unknown")
            return None

        def on_reading(reading: Any, stage_deg: float) -> None:
            payload = {"mag_x": reading.x, "mag_y": reading.y, "mag_z": reading.z, "stage_deg": stage_deg}
            self.log.write_json(t.HEADING_RAW, "viper.HeadingRaw", payload, reading.time_ns)
            self.log.write_json(t.STAGE_RAW, "viper.StageRaw", {"angle_deg": stage_deg}, reading.time_ns)

        res = procedures.calibrate_compass(self.p.compass, self.p.stage, self.cfg.session, on_reading)
        extra: dict[str, Any] = {"heading_magnetic_deg": res.platform_heading_deg}
        if res.fit is not None:
            extra.update(hard_iron=res.fit.offset, soft_iron=res.fit.matrix, residual=res.fit.residual)
        self.outcome("compass", res.status, res.reason, **extra)
        return res if res.status is Status.OK else None

    def do_truth(self) -> procedures.TruthResult | None:
        if self.p.gps is None:
            self.outcome("truth", Status.DEGRADED, "no GPS receiver: no ground truth")
            return None

        fixes: list[Any] = []

        def on_fix(fix: Any) -> None:
            fixes.append(fix)
            self.log.write_proto(
                t.GPS_FIX,
                m.location_fix(fix.receive_time_ns, fix.lat_deg, fix.lon_deg, fix.alt_msl_m, fix.sigma_m),
                fix.receive_time_ns,
            )

        res = procedures.ground_truth(self.p.gps, self.p.clock, self.cfg.session, on_fix)
        clock = check_clock(fixes, self.cfg.logbook.max_clock_offset_s)
        self.log.write_json(t.CLOCK, "viper.Clock", clock.payload(), self.now())
        self.result.clock_offset_s, self.result.clock_fault = clock.offset_s, clock.fault()
        if self.result.clock_fault is not None:
            self.say("error", self.result.clock_fault)
        if res.lat_deg is not None and res.lon_deg is not None:
            fix = m.location_fix(self.now(), res.lat_deg, res.lon_deg, res.alt_m, res.sigma_m, frame_id="truth")
            self.log.write_proto(t.GPS_TRUTH, fix, self.now())
        self.outcome(
            "truth",
            res.status,
            res.reason,
            lat=res.lat_deg,
            lon=res.lon_deg,
            sigma_m=res.sigma_m,
            spread_m=res.spread_m,
            fix_type=res.fix_type,
            used=res.used,
            rejected=res.rejected,
        )
        self.result.truth = res if res.status is Status.OK else None
        return self.result.truth

    def do_capture(
        self, compass: procedures.CompassResult | None, truth: procedures.TruthResult | None
    ) -> list[TaggedFrame]:
        if self.p.camera is None or self.p.stage is None:
            self.outcome("capture", Status.FAILED, "no camera or no stage")
            return []
        heading = None
        if compass is not None and compass.platform_heading_deg is not None:
            where = (truth.lat_deg, truth.lon_deg) if truth is not None else self.approx
            decl = 0.0
            if where is not None and where[0] is not None and where[1] is not None:
                decl = magnetic_declination_deg(float(where[0]), float(where[1]), _utc(self.now()))
            else:
                self.say("warning", "capture: no position for the magnetic declination; headings are magnetic")
            heading = (compass.platform_heading_deg + decl) % 360.0
        captured: list[TaggedFrame] = []
        logged: dict[int, np.ndarray] = {}  # each frame as the log holds it, by its time

        def on_frame(f: TaggedFrame) -> None:
            ok, jpeg = cv2.imencode(".jpg", f.frame.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
            if not ok:
                raise InputError(f"capture {f.index}: JPEG encoding failed")
            ns = f.frame.time_ns
            image = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
            if image is not None:
                logged[ns] = image
            self.log.write_proto(t.IMAGE, m.compressed_image(ns, jpeg.tobytes()), ns)
            tag = {
                "index": f.index,
                "stage_deg": f.stage_deg,
                "heading_deg": f.heading_deg,
                "roll_deg": f.roll_deg,
                "pitch_deg": f.pitch_deg,
                "yaw_deg": f.heading_deg,
            }
            self.log.write_json(t.CAPTURE, "viper.Capture", tag, ns)
            self.log.write_json(t.STAGE_RAW, "viper.StageRaw", {"angle_deg": f.stage_deg}, ns)
            self.log.write_proto(t.TF, m.stage_transform(ns, f.stage_deg), ns)
            if heading is not None:
                self.log.write_proto(t.TF, m.attitude_transform(ns, heading, f.roll_deg or 0.0, f.pitch_deg or 0.0), ns)
            self.log.flush()
            captured.append(f)
            self.result.frames = len(captured)
            self.on_status(f"capture {len(captured)}")
            self.check_stop()

        def on_problem(pr: CaptureProblem) -> None:
            self.say("warning", f"capture {pr.index} at {pr.stage_deg:.1f} deg: {pr.reason}")

        try:
            frames, problems = procedures.capture_ring(
                self.p.stage,
                self.p.camera,
                self.p.tilt,
                self.p.clock,
                self.cfg.session,
                heading,
                on_frame,
                on_problem,
            )
        except DeviceError as exc:
            self.outcome(
                "capture",
                Status.DEGRADED if captured else Status.FAILED,
                f"{exc} after {len(captured)} frames",
                frames=len(captured),
            )
            return as_logged(captured, logged)
        status = Status.OK if not problems else Status.DEGRADED
        reason = f"{len(problems)} of {len(frames) + len(problems)} steps failed" if problems else ""
        self.outcome("capture", status, reason, frames=len(frames))
        return as_logged(frames, logged)

    def do_estimate(self, frames: list[TaggedFrame], truth: procedures.TruthResult | None) -> None:
        if not frames or self.p.camera is None:
            self.outcome("estimate", Status.FAILED, "no frames to estimate from")
            return
        if self.db is None:
            self.outcome("estimate", Status.DEGRADED, "no skyline database configured ([session] database)")
            return
        # the estimator's compiled kernels load only when a session estimates
        from appliance.locating.position import fix_status, truth_error_m
        from appliance.outputs.records import estimate_fix, skyline_payload, write_estimate_records
        from appliance.vision.skyline_detect import detect_skyline

        pano = onboard.stitch_frames(frames, self.p.camera.intrinsics)
        self.result.panorama = pano
        pano_ns = self.now()  # the panorama's time: its skyline and the skyline's annotations carry it too
        ok, jpeg = cv2.imencode(".jpg", pano.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        if ok:
            self.log.write_proto(t.PANORAMA, m.compressed_image(pano_ns, jpeg.tobytes(), frame_id="panorama"), pano_ns)
        sky = detect_skyline(pano)
        tagged = [f for f in frames if f.heading_deg is not None]
        if self.cfg.session.body_mask_deg and tagged:
            platform_heading = (float(tagged[0].heading_deg or 0.0) - tagged[0].stage_deg) % 360.0
            sky = onboard.mask_stage_angles(sky, platform_heading, self.cfg.session.body_mask_deg)
        self.result.skyline = sky
        self.log.write_json(t.SKYLINE_DETECTED, "viper.Skyline", skyline_payload(sky), pano_ns)
        overlay = m.skyline_annotations(pano_ns, pano.azimuth_to_column(sky.azimuth_deg),
                                        pano.elevation_to_row(sky.elevation_deg))
        self.log.write_proto(t.PANORAMA_SKYLINE, overlay, pano_ns)
        self.on_status("estimate: searching the skyline database")
        where = None
        if truth is not None and truth.lat_deg is not None and truth.lon_deg is not None:
            where = (truth.lat_deg, truth.lon_deg)
        pos = onboard.locate_skyline(self.db, sky, self.cfg.estimator, source=self.result.session_id)
        if self.log_prior is not None:
            self.result.estimate_alone = pos
            self.result.error_alone_m = None if where is None else truth_error_m(self.db, pos, where)
            self.log.write_proto(t.ESTIMATE_ALONE_FIX, estimate_fix(self.db, pos, self.now(), "estimate_alone"),
                                 self.now())
            self.on_status("estimate: fusing with the previous stop")
            pos = onboard.locate_skyline(self.db, sky, self.cfg.estimator, source=self.result.session_id,
                                         log_prior=self.log_prior, position_prior=self.position_prior)
        self.result.estimate, self.result.database = pos, self.db
        rec = write_estimate_records(self.log, self.now(), self.db, pos, sky, where)
        self.result.error_m = rec.error_m
        flag = fix_status(pos)
        fused = " fused with the previous stop" if self.log_prior is not None else ""
        if rec.error_m is not None:
            self.say("info", f"estimate{fused} {pos.lat:.6f} {pos.lon:.6f} ({flag}): {rec.error_m:.0f} m from the "
                             "GPS truth")
        else:
            self.say("info", f"estimate{fused} {pos.lat:.6f} {pos.lon:.6f} ({flag}; no GPS truth to compare)")
        if pos.result.ambiguous:
            self.outcome("estimate", Status.AMBIGUOUS, "; ".join(pos.result.notes) or "region too large",
                         region_cells=int(pos.result.region_nodes.size))
        else:
            self.outcome("estimate", Status.OK)


def as_logged(frames: list[TaggedFrame], logged: dict[int, np.ndarray]) -> list[TaggedFrame]:
    """``frames`` with each image as the log holds it (its JPEG decoded), so that the onboard estimate is
    made from what the log keeps and ``viper replay`` of the log reproduces it."""
    return [dataclasses.replace(f, frame=Frame(f.frame.time_ns, logged[f.frame.time_ns]))
            if f.frame.time_ns in logged else f for f in frames]


def session_log_path(log_dir: Path, start_ns: int, session_id: str) -> Path:
    stamp = _utc(start_ns).strftime("%Y%m%dT%H%M%SZ")
    return Path(log_dir) / f"viper-{stamp}-{session_id}.mcap"


def remove_unwritten_log(path: Path) -> str:
    """Remove the log a session could not write anything into; what became of it, for the message."""
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:
        return f"{path.name} could not be removed ({exc.strerror})"
    return f"{path.name} removed"


def open_session_log(config: Config, log_dir: Path, now_ns: int,
                     publisher: Publisher | None = None) -> tuple[str, Path, Logbook]:
    """A new log in ``log_dir`` for a session (or a traverse) starting at ``now_ns``, written as
    ``[logbook]`` says and also sent to ``publisher`` when given; returns its id, its path and the
    logbook.  A log that cannot be opened (a full disk, a read-only folder) raises :class:`LogError`
    and leaves no file behind."""
    session_id = uuid.uuid4().hex[:8]
    lc = config.logbook
    path = session_log_path(log_dir, now_ns, session_id)
    existed = path.exists()  # never remove a file this session did not create
    try:
        logbook = Logbook.create(path, fsync_interval_s=lc.fsync_interval_s, chunk_size_bytes=lc.chunk_size_bytes,
                                 compression=lc.compression, reserve_bytes=lc.reserve_bytes, publisher=publisher,
                                 encoding=lc.encoding)
    except LogError as exc:
        if existed or not path.exists():
            raise
        raise LogError(f"{exc}; no log written: {remove_unwritten_log(path)}") from None
    return session_id, path, logbook


def run_session(
    platform: Platform,
    config: Config,
    log_dir: Path,
    db: SkylineDatabase | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    approx_position: tuple[float, float] | None = None,
    publisher: Publisher | None = None,
) -> SessionResult:
    """Run one session on ``platform``; the log goes to a new file in ``log_dir`` (and every message
    also to ``publisher``, the live view, when given)."""
    session_id, path, logbook = open_session_log(config, log_dir, platform.clock.now_ns(), publisher)
    result = SessionResult(path, session_id)
    return Session(platform, logbook, config, db, result, should_stop, on_status, approx_position).run()


def run_platform_session(
    open_devices: Callable[[Config], Devices],
    config: Config,
    log_dir: Path,
    db: SkylineDatabase | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    publisher: Publisher | None = None,
) -> SessionResult:
    """One session on the devices ``open_devices(config)`` gives (the caller chooses the hardware or
    the simulated twins); they are closed when the session ends."""
    on_status("opening the devices")
    with open_devices(config) as devices:
        return run_session(platform_of(devices), config, Path(log_dir), db, should_stop, on_status,
                           publisher=publisher)
