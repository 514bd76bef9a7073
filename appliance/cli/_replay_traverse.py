"""``viper replay`` of one traverse's log: stop by stop, each fused with the one before
(:mod:`appliance.acquisition.replay_traverse`), the odometry from the log or from the rover's ULog."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.acquisition.replay_traverse import (
    LoggedStop,
    read_traverse,
    replay_traverse_log,
    stop_times_ns,
)
from appliance.acquisition.result_json import dumps, traverse_replay_json
from appliance.acquisition.retention import mark_replayed_into
from appliance.config import EstimatorConfig
from appliance.drivers.ulog_position import LocalPositions, displacements
from appliance.errors import InputError
from appliance.locating.position import estimate_status
from appliance.logsetup import ProgressCallback

if TYPE_CHECKING:
    from appliance.acquisition.traverse import StopResult
    from appliance.terrain.database import SkylineDatabase



def boot_utc_ns(positions: LocalPositions, offset_s: float | None) -> int:
    """The UTC of the ULog's boot (ns): ``offset_s`` when given, else its GPS time."""
    if offset_s is not None:
        return round(offset_s * 1e9)
    if positions.boot_utc_us is None:
        raise InputError(f"{positions.path}: no GPS time (vehicle_gps_position.time_utc_usec) places its clock; "
                         "give --odometry-time-offset S, the UTC of its boot in seconds since the Unix epoch")
    return positions.boot_utc_us * 1000


def stop_line(db: SkylineDatabase, stop: StopResult, logged: LoggedStop, path: str) -> str:
    """What ``viper replay`` prints of one replayed stop."""
    s = stop.session
    head = f"{path}: stop {stop.stop}"
    if s.estimate is None:
        return f"{head}: no estimate: {'; '.join(s.problems) or 'no frames'}"
    p = s.estimate
    err = "no GPS truth" if s.error_m is None else f"error {s.error_m:.1f} m"
    was = "" if logged.onboard_error_m is None else f" (onboard {logged.onboard_error_m:.1f} m)"
    how = "fused" if stop.fused else f"alone ({stop.fusion_note})"
    alone = "" if not stop.fused or s.error_alone_m is None else f", alone {s.error_alone_m:.1f} m"
    status = estimate_status(db, p, logged.data.truth)
    return f"{head}: {p.lat:.6f}, {p.lon:.6f}  {status}  {err}{was}  {how}{alone}  [{len(logged.data.frames)} frames]"


def replay_traverse_command(args: argparse.Namespace, db: SkylineDatabase, est: EstimatorConfig,
                            positions: LocalPositions | None) -> int:
    path = args.logs[0]
    log = read_traverse(path)
    odometry, source = None, ""
    if positions is not None:
        odometry = displacements(positions, stop_times_ns(log), boot_utc_ns(positions, args.odometry_time_offset))
        source = f"{args.odometry_log} (PX4 vehicle_local_position)"
    bar = ProgressCallback("stop")
    if not args.json:
        told = source or "the log's odometry lines"
        bar.write(f"{path}: a traverse of {len(log.stops)} stops, replayed stop by stop (odometry: {told})")

    def show(stop: StopResult, logged: LoggedStop) -> None:
        bar(stop.stop + 1, len(log.stops), "replay")
        if not args.json:
            bar.write(stop_line(db, stop, logged, path))

    replay = replay_traverse_log(log, db, est, Path(args.out), odometry, source, show)
    if args.json:
        print(dumps(traverse_replay_json(db, replay)))
    else:
        print(f"report: {replay.page}  table: {replay.table}  results log: {replay.results_log}")
    mark_replayed_into(Path(path), Path(args.out))
    return 0 if any(s.position is not None for s in replay.result.stops) else 1
