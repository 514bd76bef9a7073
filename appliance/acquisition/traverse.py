"""A rover's traverse: a series of stops in one log, each fused with the last (paper section 6.4).

At each stop the usual session runs (:class:`appliance.acquisition.session.Session`: level, compass,
GPS truth, capture, estimate).  Before every stop after the first, the traverse waits for the rover's
odometry line (:mod:`appliance.drivers.odometry`: the displacement from the previous stop and its
sigma), and the stop's estimate takes as its prior the last estimate's posterior moved by that
displacement and blurred by its sigma (:func:`appliance.locating.position.transported_prior`).  The stop
reports both: its estimate from its own skyline alone (``/estimate/alone/fix``) and the fused one,
which is the stop's position (``/estimate/fix`` and the other estimate topics).

Fusion spans a stop without an estimate (the moves add up, their sigmas in quadrature) but never a
lost odometry line: stop ids must follow each other, and after a gap the next stop starts afresh; nor
a reset of the odometry's frame (a MAVLink autopilot's reboot, :attr:`OdometryReport.reset`).  With a
MAVLink autopilot (``[devices.odometry] kind = "mavlink"``, :mod:`appliance.acquisition.rover_link`)
the link's faults become the traverse's warnings, each stop logs the autopilot's attitude and mode
as its capture begins (``/traverse/rover``), and each estimate goes back to the autopilot
(``/traverse/position_out``).
Each stop writes ``/traverse/stop`` (both estimates, their errors against the GPS truth, their
statuses) and ``/traverse/track`` (GeoJSON lines through the estimates and through the GPS truths so
far: the last message is the whole track).  A stop request ends the traverse between steps with the
log sealed; an odometry line that does not come within ``[traverse] odometry_timeout_s`` ends it too.

Frames: stop N's frames are named ``stop-N/world``, ``stop-N/platform``, ... (the logbook's frame
prefix), and ``/tf`` places each ``stop-N/world`` in ``map``, east-north-up at the first stop's position,
at the stop's position (its estimate, else its GPS truth), so the 3D panel shows the path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from appliance.acquisition.platform import Platform, platform_of
from appliance.acquisition.procedures import Status
from appliance.acquisition.rover_link import log_rover_state, say_faults, send_estimate
from appliance.acquisition.session import (
    Session,
    SessionResult,
    StopRequestedError,
    open_session_log,
)
from appliance.bodies import EARTH, Body, body_named
from appliance.config import Config
from appliance.drivers.factory import Devices
from appliance.drivers.odometry import OdometryReport
from appliance.locating.position import (
    Move,
    Position,
    estimate_status,
    skyline_grid,
    transported_fix,
    transported_prior,
)
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook, LogbookFullError

if TYPE_CHECKING:
    from appliance.estimator import SkylineGrid
    from appliance.estimator.exact import PositionPrior
    from appliance.logbook.live import Publisher
    from appliance.terrain.database import SkylineDatabase


@dataclass
class StopResult:
    """One stop: its session, the odometry line that announced it, and how its prior was made."""

    stop: int
    session: SessionResult
    odometry: OdometryReport | None
    log_prior: np.ndarray | None  # the transported posterior of the last estimate (log, per node), or None
    position_prior: PositionPrior | None  # the last fix moved, for the fit between nodes (None: not unique)
    prior_peak: tuple[float, float] | None  # (lat, lon) of the prior's most probable node
    fusion_note: str  # why the stop was not fused ("" when it was)

    @property
    def fused(self) -> bool:
        return self.log_prior is not None

    @property
    def position(self) -> Position | None:
        """The stop's position: the fused estimate (the alone one at the first stop or after a gap)."""
        return self.session.estimate

    @property
    def alone(self) -> Position | None:
        return self.session.estimate_alone if self.fused else self.session.estimate

    @property
    def error_m(self) -> float | None:
        return self.session.error_m

    @property
    def error_alone_m(self) -> float | None:
        return self.session.error_alone_m if self.fused else self.session.error_m

    @property
    def truth(self) -> tuple[float, float] | None:
        tr = self.session.truth
        if tr is None or tr.lat_deg is None or tr.lon_deg is None:
            return None
        return (tr.lat_deg, tr.lon_deg)


@dataclass
class TraverseResult(SessionResult):
    """A whole traverse; the fields of :class:`SessionResult` summarise it (the last stop's estimate and
    error, every stop's frames and problems), so the daemon reports it as a session."""

    stops: list[StopResult] = field(default_factory=list)


def estimate_flag(db: SkylineDatabase, pos: Position, truth: tuple[float, float] | None) -> str:
    """'ambiguous' when the region is too large (or the GPS truth lies outside it), else 'ok'."""
    return estimate_status(db, pos, truth)


def _summary(db: SkylineDatabase, pos: Position | None, truth: tuple[float, float] | None,
             error_m: float | None) -> dict[str, Any] | None:
    if pos is None:
        return None
    return {"lat": pos.lat, "lon": pos.lon, "status": estimate_flag(db, pos, truth),
            "region_cells": int(pos.result.region_nodes.size), "region_area_m2": float(pos.result.region_area_m2),
            "error_m": error_m}


def stop_record(db: SkylineDatabase, s: StopResult) -> dict[str, Any]:
    """The ``/traverse/stop`` record of a stop (``viper.TraverseStop``)."""
    odo = s.odometry
    truth = s.truth
    return {
        "stop": s.stop,
        "session_id": s.session.session_id,
        "status": s.session.status.value,
        "odometry": None if odo is None else odometry_record(odo),
        "fused": s.fused,
        "fusion_note": s.fusion_note,
        "prior_peak": None if s.prior_peak is None else {"lat": s.prior_peak[0], "lon": s.prior_peak[1]},
        "alone": _summary(db, s.alone, truth, s.error_alone_m),
        "position": _summary(db, s.position, truth, s.error_m),
        "truth": None if truth is None else {"lat": truth[0], "lon": truth[1]},
    }


def odometry_record(o: OdometryReport) -> dict[str, Any]:
    return {"stop_id": o.stop_id, "east_m": o.east_m, "north_m": o.north_m, "sigma_m": o.sigma_m,
            "receive_time_ns": o.receive_time_ns, "reset": o.reset}


def added_odometry(total: OdometryReport | None, rep: OdometryReport) -> OdometryReport:
    """``rep`` added to the lines before it (the rover drove on): displacements add, sigmas in quadrature."""
    if total is None or rep.reset:
        return rep
    return OdometryReport(rep.stop_id, total.east_m + rep.east_m, total.north_m + rep.north_m,
                          float(np.hypot(total.sigma_m, rep.sigma_m)), rep.receive_time_ns, total.reset)


def track_features(stops: list[StopResult]) -> list[dict[str, Any]]:
    """GeoJSON LineStrings (lon, lat) through the stops' positions and through their GPS truths; a line
    of fewer than two points is left out."""
    lines = {
        "estimates": [[s.position.lon, s.position.lat] for s in stops if s.position is not None],
        "truth": [[s.truth[1], s.truth[0]] for s in stops if s.truth is not None],
    }
    return [{"type": "Feature", "properties": {"name": name, "kind": "track", "stops": len(coords)},
             "geometry": {"type": "LineString", "coordinates": coords}}
            for name, coords in lines.items() if len(coords) >= 2]


def stop_prefix(i: int) -> str:
    """The prefix of stop ``i``'s frames (``stop-2/world``...)."""
    return f"stop-{i}/"


def enu_offset_m(body: Body, origin: tuple[float, float], where: tuple[float, float]) -> tuple[float, float]:
    """(east, north) in metres of ``where`` from ``origin`` (both lat, lon in degrees): the geodesic's
    length along its azimuth at ``origin``."""
    az_deg, _, dist_m = body.geod.inv(origin[1], origin[0], where[1], where[0])
    return (float(dist_m * np.sin(np.radians(az_deg))), float(dist_m * np.cos(np.radians(az_deg))))


def _status_of(stops: list[StopResult]) -> Status:
    statuses = {s.session.status for s in stops}
    if statuses <= {Status.OK}:
        return Status.OK
    if statuses <= {Status.OK, Status.AMBIGUOUS}:
        return Status.AMBIGUOUS
    return Status.DEGRADED


class FusionChain:
    """The belief a traverse carries from stop to stop: the last estimate and the rover's displacement
    since it, from the odometry lines in stop order.  The onboard traverse and its replay
    (:mod:`appliance.acquisition.replay_traverse`) fuse through it alike."""

    def __init__(self, db: SkylineDatabase | None) -> None:
        self.db = db
        self.grid: SkylineGrid | None = None
        self.belief: Position | None = None  # the last estimate, whose posterior the next prior moves
        self.moved: Move | None = None  # the rover's displacement since that estimate
        self.last_stop_id = 0
        self.note = ""

    def take_move(self, rep: OdometryReport) -> str | None:
        """Add ``rep`` to the displacement since the last estimate; on a lost line (stop ids not in
        sequence) break the chain and return why."""
        expected = self.last_stop_id + 1
        self.last_stop_id = rep.stop_id
        move = Move(rep.east_m, rep.north_m, rep.sigma_m)
        if rep.reset:
            self.lose(f"the autopilot's position frame was reset before stop {rep.stop_id} (a reboot): "
                      "not fused across it")
            return self.note
        if rep.stop_id != expected:
            self.lose(f"odometry of stop {expected} missing (got stop {rep.stop_id}): not fused across the gap")
            return self.note
        self.moved = move if self.moved is None else self.moved.then(move)
        return None

    def lose(self, note: str) -> None:
        """Break the chain: the next stop is not fused, for the reason ``note``."""
        self.note, self.belief, self.moved = note, None, None

    def prepare_stop(self, i: int, result: SessionResult, odometry: OdometryReport | None) -> StopResult:
        """Stop ``i`` (from 0) with its prior: the belief moved by the displacement, when there is both."""
        prior, fix, peak, note = None, None, None, self.note
        if i == 0:
            note = "first stop"
        elif self.db is not None and self.belief is not None and self.moved is not None:
            if self.grid is None:
                self.grid = skyline_grid(self.db)
            prior = transported_prior(self.db, self.grid, self.belief, self.moved)
            fix = transported_fix(self.db, self.grid, self.belief, self.moved)
            g = self.db.grid
            lon, lat = g.xy_to_lonlat(*g.rc_to_xy(*divmod(int(np.argmax(prior)), g.n_cols)))
            peak, note = (float(lat), float(lon)), ""
        elif not note:
            note = "no earlier estimate to fuse with"
        self.note = ""
        return StopResult(i, result, odometry, prior, fix, peak, note)

    def settle(self, stop: StopResult) -> None:
        """The stop is over: its position (if any) becomes the belief the next stop's prior moves."""
        if stop.position is not None:
            self.belief, self.moved = stop.position, Move(0.0, 0.0, 0.0)


class Traverse:
    """Runs the stops of one traverse into one log."""

    def __init__(self, platform: Platform, logbook: Logbook, config: Config, db: SkylineDatabase | None,
                 result: TraverseResult, n_stops: int, should_stop: Callable[[], bool],
                 on_status: Callable[[str], None], on_stop_done: Callable[[int], None]) -> None:
        self.p, self.log, self.cfg, self.db = platform, logbook, config, db
        self.result, self.n_stops = result, n_stops
        self.should_stop, self.on_status, self.on_stop_done = should_stop, on_status, on_stop_done
        self.chain = FusionChain(db)
        self._queued: list[OdometryReport] = []
        self.map_origin: tuple[float, float] | None = None  # (lat, lon) of ``map``'s origin: the first stop placed
        self.stop_start_ns = 0
        self.head_problems: list[str] = []

    @property
    def moved(self) -> Move | None:
        return self.chain.moved

    @property
    def note(self) -> str:
        return self.chain.note

    def session(self, result: SessionResult, log_prior: np.ndarray | None = None,
                position_prior: PositionPrior | None = None) -> Session:
        return Session(self.p, self.log, self.cfg, self.db, result, self.should_stop, self.on_status,
                       log_prior=log_prior, position_prior=position_prior)

    def run(self) -> TraverseResult:
        r = self.result
        head = self.session(SessionResult(r.log_path, r.session_id))
        self.head_problems = head.result.problems  # the traverse's own warnings (odometry, autopilot)
        current: Session | None = None
        try:
            self.log.frame_prefix = stop_prefix(0)
            head.write_header()
            head.say("info", f"traverse {r.session_id} started: {self.n_stops} stops")
            for i in range(self.n_stops):
                odometry = None
                if i > 0:
                    self.on_stop_done(i - 1)
                    odometry = self.next_odometry(head)
                    if odometry is None:
                        break
                stop = self.prepare_stop(i, odometry)
                current = self.session(stop.session, stop.log_prior, stop.position_prior)
                r.stops.append(stop)
                self.start_frames(i)
                log_rover_state(self.p.autopilot, self.log, i, self.p.clock.now_ns())
                current.run_procedures()
                current = None
                self.finish_stop(head, stop)
            head.say("info", f"traverse {r.session_id} finished after {len(r.stops)} stops")
        except StopRequestedError:
            (current or head).stopped()
            r.stopped = True
        except LogbookFullError as exc:
            r.disk_full = True
            r.log_error = str(exc)
        finally:
            self.log.close()
        self.summarise()
        return r

    # ------------------------------------------------------------------------------- odometry
    def next_odometry(self, head: Session) -> OdometryReport | None:
        """The odometry of the rover's next stop: the lines received until one comes (several at once,
        the rover having driven on, are added up); None after ``[traverse] odometry_timeout_s``."""
        timeout_s = self.cfg.traverse.odometry_timeout_s
        if self.p.odometry is None:
            head.say("error", "traverse: no odometry source ([devices.odometry] source); the traverse ends")
            return None
        self.on_status("waiting for the rover's odometry")
        clock = self.p.clock
        start = clock.monotonic_s()
        reports = self._queued
        while not reports:
            if self.should_stop():
                raise StopRequestedError()
            if clock.monotonic_s() - start > timeout_s:
                say_faults(self.p.autopilot, head)
                head.say("error", f"traverse: no odometry line within {timeout_s:g} s; the traverse ends")
                return None
            reports = self.p.odometry.poll()
            say_faults(self.p.autopilot, head)
        self._queued = []
        total: OdometryReport | None = None
        for rep in reports:
            now = self.p.clock.now_ns()
            self.log.write_json(t.ODOMETRY, "viper.Odometry", odometry_record(rep), now)
            self.take_move(head, rep)
            total = added_odometry(total, rep)
        return total

    def take_move(self, head: Session, rep: OdometryReport) -> None:
        """Add ``rep`` to the displacement since the last estimate, or break the chain on a lost line."""
        gap = self.chain.take_move(rep)
        if gap is not None:
            head.say("warning", f"traverse: {gap}")

    # ---------------------------------------------------------------------------------- stops
    def prepare_stop(self, i: int, odometry: OdometryReport | None) -> StopResult:
        result = SessionResult(self.result.log_path, f"{self.result.session_id}-{i}")
        return self.chain.prepare_stop(i, result, odometry)

    def start_frames(self, i: int) -> None:
        """Stop ``i``'s frames from now on: named ``stop-i/...``, its camera -> camera_optical given."""
        self.stop_start_ns = self.p.clock.now_ns()
        self.log.frame_prefix = stop_prefix(i)
        self.log.write_proto(t.TF, m.optical_transform(self.stop_start_ns), self.stop_start_ns)

    def place_stop(self, stop: StopResult) -> None:
        """map -> stop-N/world: the stop's position (its estimate, else its GPS truth) east and north of
        ``map``'s origin (the first stop placed), stamped with the stop's start."""
        where = (stop.position.lat, stop.position.lon) if stop.position is not None else stop.truth
        if where is None:
            return
        if self.map_origin is None:
            self.map_origin = where
        body = body_named(self.db.header["body"]) if self.db is not None else EARTH
        east_m, north_m = enu_offset_m(body, self.map_origin, where)
        ns = self.stop_start_ns
        self.log.write_proto(t.TF, m.map_transform(ns, east_m, north_m), self.p.clock.now_ns())

    def finish_stop(self, head: Session, stop: StopResult) -> None:
        """The stop's records; its position becomes the belief the next stop's prior moves."""
        self.place_stop(stop)
        self.chain.settle(stop)
        if self.db is None:
            return
        now = self.p.clock.now_ns()
        rec = stop_record(self.db, stop)
        self.log.write_json(t.TRAVERSE_STOP, "viper.TraverseStop", rec, now)
        features = track_features(self.result.stops)
        if features:
            self.log.write_proto(t.TRAVERSE_TRACK, m.geojson(features), now)
        send_estimate(self.p.autopilot, self.log, head, stop.stop, stop.position, now)
        say_faults(self.p.autopilot, head)
        self.log.flush()
        pos, alone = rec["position"], rec["alone"]
        if pos is not None and alone is not None:
            def err(e: Any) -> str:
                return "no GPS truth" if e["error_m"] is None else f"{e['error_m']:.0f} m"

            head.say("info", f"traverse stop {stop.stop}: alone {err(alone)} ({alone['status']}), "
                             f"{'fused' if stop.fused else 'not fused'} {err(pos)} ({pos['status']})")

    def summarise(self) -> None:
        r = self.result
        r.problems += self.head_problems
        for s in r.stops:
            r.problems += s.session.problems
            r.frames += s.session.frames
        if r.stops:
            last = r.stops[-1].session
            r.outcomes, r.truth, r.estimate, r.error_m = last.outcomes, last.truth, last.estimate, last.error_m
            r.database = last.database
            r.panorama, r.skyline = last.panorama, last.skyline
            r.estimate_alone, r.error_alone_m = last.estimate_alone, last.error_alone_m
            off = next((s.session for s in r.stops if s.session.clock_fault is not None), last)  # the first flagged
            r.clock_offset_s, r.clock_fault = off.clock_offset_s, off.clock_fault
        if r.disk_full:
            r.status = Status.FAILED
        elif r.stopped or len(r.stops) < self.n_stops:
            r.status = Status.DEGRADED
        else:
            r.status = _status_of(r.stops)


def run_traverse(
    platform: Platform,
    config: Config,
    log_dir: Path,
    db: SkylineDatabase | None,
    n_stops: int,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    publisher: Publisher | None = None,
    on_stop_done: Callable[[int], None] = lambda i: None,
) -> TraverseResult:
    """A traverse of ``n_stops`` stops on ``platform`` into a new log in ``log_dir`` (every message also
    to ``publisher``, the live view, when given).  ``on_stop_done(i)`` is called when stop ``i`` is over
    and the rover may drive on (the simulated rover drives then)."""
    traverse_id, path, logbook = open_session_log(config, log_dir, platform.clock.now_ns(), publisher)
    result = TraverseResult(path, traverse_id)
    return Traverse(platform, logbook, config, db, result, n_stops, should_stop, on_status, on_stop_done).run()


def run_platform_traverse(
    open_devices: Callable[[Config], Devices],
    config: Config,
    log_dir: Path,
    db: SkylineDatabase | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    publisher: Publisher | None = None,
) -> TraverseResult:
    """A traverse of ``[traverse] stops`` on the devices ``open_devices(config)`` gives; they are closed
    when it ends."""
    on_status("opening the devices")
    with open_devices(config) as devices:
        return run_traverse(platform_of(devices), config, Path(log_dir), db, config.traverse.stops, should_stop,
                            on_status, publisher)
