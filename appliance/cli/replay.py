"""``viper replay LOG.mcap... [--db DB] [--sigma LO,HI] [--out DIR] [--json]``: rerun the estimate from logs.

A traverse's log (several stops) is replayed stop by stop, each fused with the one before through the
odometry: the log's own lines, or the rover's record (``--odometry-log rover.ulg``, a PX4 ULog's local
position at each stop's time; its clock placed by its GPS time or ``--odometry-time-offset``)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.acquisition.onboard import load_session_database
from appliance.acquisition.replay import ReplayResult, replay_logs
from appliance.acquisition.replay_traverse import is_traverse_log
from appliance.acquisition.result_json import dumps, replay_json
from appliance.acquisition.retention import mark_replayed_into
from appliance.atomic import check_output_folder
from appliance.cli._replay_traverse import replay_traverse_command
from appliance.config import Config, EstimatorConfig, load_config, override
from appliance.drivers.ulog_position import read_local_positions
from appliance.errors import InputError
from appliance.locating.position import estimate_status
from appliance.logsetup import ProgressCallback
from appliance.outputs.files import MAP_LAYER_SUFFIXES

if TYPE_CHECKING:
    from appliance.terrain.database import SkylineDatabase

#: what a replay writes per log, after the log's name: its results log, pictures and map layers
REPLAY_FILES = (".replay.mcap", ".map.png", ".panorama.png", *MAP_LAYER_SUFFIXES)

LOG = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("replay", help="rerun stitch, skyline and estimate from session logs; report")
    p.add_argument("logs", nargs="+", metavar="LOG.mcap")
    p.add_argument("--db", metavar="DB", help="skyline database (default: [session] database, else the demo "
                   "map's in ./viper-demo)")
    p.add_argument("--sigma", metavar="LO,HI", help="interval of the skyline noise sigma in degrees")
    p.add_argument("--heading-tolerance", type=float, metavar="DEG", help="compass error searched (deg)")
    p.add_argument("--config", metavar="FILE", help="TOML configuration (default: built-in defaults)")
    p.add_argument("--out", default="viper-replay", help="folder of the results logs and report")
    p.add_argument("--force", action="store_true", help="replace results and report files that exist")
    p.add_argument("--odometry-log", metavar="ULOG", help="a traverse: take the odometry between stops from the "
                   "rover's PX4 ULog (vehicle_local_position) instead of the log's odometry lines")
    p.add_argument("--odometry-time-offset", type=float, metavar="S", help="UTC of the ULog's boot, seconds since "
                   "the Unix epoch (default: from its GPS time)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object on stdout")
    p.set_defaults(func=run)


def truth_on_map(db: SkylineDatabase, truth: tuple[float, float]) -> bool:
    """Whether the GPS truth (lat, lon) falls on the database's grid (half a node of margin)."""
    g = db.grid
    x, y = g.lonlat_to_xy(truth[1], truth[0])
    rows, cols = g.xy_to_rc(x, y)
    row, col = float(rows), float(cols)
    return -0.5 <= row <= g.n_rows - 0.5 and -0.5 <= col <= g.n_cols - 0.5


def parse_sigma(text: str) -> tuple[float, float]:
    """``LO,HI`` as two numbers (their range is checked with the configuration's)."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--sigma: expected LO,HI in degrees, got {text!r}") from None
    return lo, hi


def _estimator_config(args: argparse.Namespace, config: Config) -> EstimatorConfig:
    est = config.estimator
    if args.sigma:
        est = override(est, "--sigma", sigma_deg=parse_sigma(args.sigma))
    if args.heading_tolerance is not None:
        est = override(est, "--heading-tolerance", heading_tolerance_deg=args.heading_tolerance)
    return est


def _database(args: argparse.Namespace, config: Config) -> SkylineDatabase:
    session = config.session
    if args.db:
        session = dataclasses.replace(session, database=Path(args.db))
    db = load_session_database(session)
    if db is None:
        # the demo map, only when no database is given
        from appliance.sim.demo import DEMO_DEM, demo_database
        from appliance.terrain.dem import load_dem

        LOG.warning("no --db: using the demo map's database (%s) in ./viper-demo", DEMO_DEM)
        demo_dir = Path("viper-demo")
        demo_dir.mkdir(parents=True, exist_ok=True)
        db = demo_database(load_dem(DEMO_DEM), demo_dir)
    return db


def run(args: argparse.Namespace) -> int:
    if args.odometry_time_offset is not None and args.odometry_log is None:
        raise InputError("--odometry-time-offset places the clock of --odometry-log; give --odometry-log too")
    traverse = is_traverse_log(args.logs[0]) if len(args.logs) == 1 else False
    if args.odometry_log is not None and not traverse:
        raise InputError(f"--odometry-log: {', '.join(args.logs)} is not one traverse's log (its odometry "
                         "between stops is what the ULog replaces)")
    stems = [Path(p).stem for p in args.logs]
    out = Path(args.out)
    files = ["report.html", "summary.csv", *(f"{s}{e}" for s in stems for e in REPLAY_FILES)]
    if traverse:  # the stops' pictures: as many as the log holds
        files += ["track.png", *(q.name for q in out.glob("stop-*.png"))]
    check_output_folder(args.out, args.logs, files, args.force)
    config = load_config(args.config)
    est = _estimator_config(args, config)
    positions = None if args.odometry_log is None else read_local_positions(args.odometry_log)
    db = _database(args, config)
    if traverse:
        return replay_traverse_command(args, db, est, positions)
    elsewhere: list[str] = []
    bar = ProgressCallback("log")
    shown = [0]

    def show(r: ReplayResult) -> None:
        shown[0] += 1
        bar(shown[0], len(args.logs), "replay")
        lines = result_lines(db, r)
        if r.data.truth is not None and not truth_on_map(db, r.data.truth):
            elsewhere.append(str(r.data.path))
        if not args.json:
            for line in lines:
                bar.write(line)

    results, page = replay_logs([Path(p) for p in args.logs], db, est, out, show)
    if args.json:
        print(dumps(replay_json(db, results, page, elsewhere)))
    else:
        print(f"report: {page}  table: {out / 'summary.csv'}")
    for r in results:  # retention's keep_unreplayed may now remove the logs that were read
        if r.data.problem is not None and not r.data.frames:
            continue
        mark_replayed_into(r.data.path, out)
    if elsewhere:
        raise InputError(f"{len(elsewhere)} of {len(results)} logs were taken outside the database {db.path} "
                         f"(a database of another map?): {', '.join(elsewhere)}")
    return 0 if any(r.position is not None for r in results) else 1


def result_lines(db: SkylineDatabase, r: ReplayResult) -> list[str]:
    """What ``viper replay`` prints of one log's replay."""
    if r.data.truth is not None and not truth_on_map(db, r.data.truth):
        return [f"{r.data.path}: GPS truth {r.data.truth[0]:.6f}, {r.data.truth[1]:.6f} lies outside the database"]
    lines = [f"{r.data.path}: note: {note}" for note in r.notes]
    if r.failure:
        return [*lines, f"{r.data.path}: no estimate: {r.failure}"]
    p = r.position
    assert p is not None
    err = "no GPS truth" if r.error_m is None else f"error {r.error_m:.1f} m"
    was = "" if r.data.onboard_error_m is None else f" (onboard {r.data.onboard_error_m:.1f} m)"
    status = estimate_status(db, p, r.data.truth)
    return [*lines, f"{r.data.path}: {p.lat:.6f}, {p.lon:.6f}  {status}  {err}{was}  [{len(r.data.frames)} frames]"]
