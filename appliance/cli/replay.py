"""``viper replay LOG.mcap... [--db DB] [--sigma LO,HI] [--out DIR]``: rerun the estimate from logs."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.acquisition.onboard import load_session_database
from appliance.acquisition.replay import ReplayResult, replay_logs
from appliance.atomic import check_output_folder
from appliance.config import load_config, override
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


def run(args: argparse.Namespace) -> int:
    stems = [Path(p).stem for p in args.logs]
    files = ["report.html", "summary.csv", *(f"{s}{e}" for s in stems for e in REPLAY_FILES)]
    check_output_folder(args.out, args.logs, files, args.force)
    config = load_config(args.config)
    est = config.estimator
    if args.sigma:
        est = override(est, "--sigma", sigma_deg=parse_sigma(args.sigma))
    if args.heading_tolerance is not None:
        est = override(est, "--heading-tolerance", heading_tolerance_deg=args.heading_tolerance)
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
    out = Path(args.out)

    elsewhere: list[str] = []
    bar = ProgressCallback("log")
    shown = [0]

    def show(r: ReplayResult) -> None:
        shown[0] += 1
        bar(shown[0], len(args.logs), "replay")
        if r.data.truth is not None and not truth_on_map(db, r.data.truth):
            elsewhere.append(str(r.data.path))
            print(f"{r.data.path}: GPS truth {r.data.truth[0]:.6f}, {r.data.truth[1]:.6f} lies outside the database")
            return
        for note in r.notes:
            print(f"{r.data.path}: note: {note}")
        if r.failure:
            print(f"{r.data.path}: no estimate: {r.failure}")
            return
        p = r.position
        assert p is not None
        err = "no GPS truth" if r.error_m is None else f"error {r.error_m:.1f} m"
        was = "" if r.data.onboard_error_m is None else f" (onboard {r.data.onboard_error_m:.1f} m)"
        status = estimate_status(db, p, r.data.truth)
        print(f"{r.data.path}: {p.lat:.6f}, {p.lon:.6f}  {status}  {err}{was}  [{len(r.data.frames)} frames]")

    results, page = replay_logs([Path(p) for p in args.logs], db, est, out, show)
    print(f"report: {page}  table: {out / 'summary.csv'}")
    if elsewhere:
        raise InputError(f"{len(elsewhere)} of {len(results)} logs were taken outside the database {db.path} "
                         f"(a database of another map?): {', '.join(elsewhere)}")
    return 0 if any(r.position is not None for r in results) else 1
