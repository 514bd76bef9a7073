"""``viper estimate DB SKYLINE...``: position from measured skylines."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from appliance.atomic import check_output_folder
from appliance.config import load_config, override
from appliance.errors import InputError
from appliance.extras import require
from appliance.locating.position import Move, Position, answer_text, locate, locate_sequence
from appliance.locating.tiled_index import TiledIndex
from appliance.skyline import Skyline, read_skyline_csv
from appliance.terrain.database import SkylineDatabase, load_database

LOG = logging.getLogger(__name__)


def _numbers(text: str, what: str, n: int) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"{what} {text!r}: expected {n} comma-separated numbers") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{what} {text!r}: expected {n} comma-separated finite numbers")
    return vals


def _pair(text: str, what: str) -> tuple[float, float]:
    a, b = _numbers(text, what, 2)
    return a, b


def _lat_lon(text: str, what: str) -> tuple[float, float]:
    lat, lon = _numbers(text, what, 2)
    if not (-90.0 <= lat <= 90.0 and -360.0 <= lon <= 360.0):
        raise InputError(f"{what} {text!r}: expected LAT,LON in degrees (-90..90, -360..360)")
    return lat, lon


def _move(text: str) -> Move:
    east, north, sigma = _numbers(text, "--move", 3)
    if not sigma >= 0.0:
        raise InputError(f"--move {text!r}: its sigma must be >= 0 m")
    return Move(east, north, sigma)


def _checked_height(height: float | None) -> float | None:
    if height is not None and not (math.isfinite(height) and -100.0 < height < 1000.0):
        raise InputError(f"--height {height}: expected a height in metres above the map's surface, -100..1000")
    return height


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimate", help="estimate the position from skyline CSVs and a skyline database")
    p.add_argument("db", help="skyline database from viper precompute, or a tiled database's folder")
    p.add_argument("skylines", nargs="+", help="skyline CSVs (azimuth_deg,elevation_deg)")
    head = p.add_mutually_exclusive_group()
    head.add_argument("--heading-tolerance", type=float, help="compass error bound beta (deg; default from config)")
    head.add_argument("--unknown-heading", action="store_true", help="no compass: search every heading")
    p.add_argument("--sigma", help="sigma interval LO,HI in degrees (default: [estimator] sigma_deg)")
    p.add_argument("--config", help="configuration TOML")
    p.add_argument("--occlusion-weight", type=float, metavar="W",
                   help="prior share of azimuths hidden by what the map lacks, trees or buildings (0 = none; "
                        "default: [estimator] occlusion_weight)")
    p.add_argument("--map-sigma", type=float, metavar="M",
                   help="the map's vertical error, 1 sigma in metres (default: [estimator] map_vertical_sigma_m)")
    p.add_argument("--height", type=float, metavar="M",
                   help="camera height above the map's surface (default: the database's); a camera on a roof "
                        "that the map holds stands a few metres above it")
    p.add_argument("--json", action="store_true", help="one JSON object per skyline, one per line")
    p.add_argument("--fuse", action="store_true",
                   help="fuse the skylines as a sequence of stations (needs one --move per gap)")
    p.add_argument("--move", action="append", default=[], metavar="E,N,SIGMA",
                   help="displacement to the next station: metres east, north and its 1-sigma (repeat)")
    p.add_argument("--truth", action="append", default=[], metavar="LAT,LON",
                   help="true position of each skyline's station, for the error and the picture")
    p.add_argument("--report", metavar="DIR",
                   help="write per skyline a PNG, the posteriors as GeoTIFF and the region as GeoJSON, "
                        "and report.html showing them all")
    p.add_argument("--force", action="store_true", help="replace report files that exist")
    tiled = p.add_argument_group("tiled database (DB is a folder with index.json)")
    where = tiled.add_mutually_exclusive_group()
    where.add_argument("--search-bounds", metavar="W,S,E,N",
                       help="search only the tiles meeting this lon/lat box (degrees)")
    where.add_argument("--near", metavar="LAT,LON,RADIUS_M",
                       help="search only the tiles within RADIUS_M metres of LAT,LON")
    run_on = tiled.add_mutually_exclusive_group()
    run_on.add_argument("--scheduler", metavar="ADDRESS",
                        help="search the tiles as tasks on this Dask scheduler (tcp://host:8786)")
    run_on.add_argument("--workers", type=int, metavar="N",
                        help="search the tiles as tasks on a local Dask cluster of N worker processes")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cfg = _estimator_config(args)
    tolerance = None if args.unknown_heading else cfg.heading_tolerance_deg
    truths = [_lat_lon(t, "--truth") for t in args.truth]
    if truths and len(truths) != len(args.skylines):
        raise InputError(f"{len(args.skylines)} skylines but {len(truths)} --truth values")
    moves = [_move(m) for m in args.move]
    if args.fuse and len(moves) != len(args.skylines) - 1:
        raise InputError(f"--fuse with {len(args.skylines)} skylines needs {len(args.skylines) - 1} --move values")
    if moves and not args.fuse:
        raise InputError("--move is only used with --fuse")
    skylines = [(s, read_skyline_csv(s)) for s in args.skylines]
    for name, sky in skylines:
        if sky.valid_fraction < cfg.min_valid_fraction:
            raise InputError(f"{name}: {int(sky.valid.sum())} valid azimuths ({sky.valid_fraction:.0%}), below "
                             f"[estimator] min_valid_fraction {cfg.min_valid_fraction:.0%}")
    tiled_only = [o for o, v in (("--search-bounds", args.search_bounds), ("--near", args.near),
                                 ("--scheduler", args.scheduler), ("--workers", args.workers)) if v is not None]
    where: SkylineDatabase | TiledIndex
    if Path(args.db).is_dir():  # a tiled database (tiled_index.is_tiled): its search is loaded only then
        where, positions = _locate_tiled(args, cfg, skylines, tolerance)
    else:
        if tiled_only:
            raise InputError(f"{tiled_only[0]} needs a tiled database (a folder with index.json), not {args.db}")
        where = load_database(args.db)
        positions = _locate_in_file(args, cfg, where, skylines, moves, tolerance)
    report = Path(args.report) if args.report else None
    if report is not None:
        from appliance.outputs import report as pages  # the report writers (rasterio, figures) load only for --report

        check_output_folder(report, [args.db, *args.skylines], pages.estimate_report_names(args.skylines), args.force)
    entries = []
    for i, (pos, (name, sky)) in enumerate(zip(positions, skylines)):
        truth = truths[i] if truths else None
        record = pos.to_json(where, truth)
        if report is not None and isinstance(where, SkylineDatabase):  # a tiled database refuses --report
            entries.append(pages.write_estimate_files(where, report, i, name, pos, sky, truth))
        if args.json:
            print(json.dumps(record), flush=True)
        else:
            print(f"{name}: {answer_text(pos, record)}")
            for note in pos.notes:
                LOG.info("  %s", note)
    if report is not None and isinstance(where, SkylineDatabase):
        pages.write_estimate_report(where, entries, report)
    return 0


def _estimator_config(args: argparse.Namespace) -> Any:
    """The configuration's [estimator] table with the command line's options over it."""
    cfg = load_config(args.config).estimator
    if args.sigma is not None:
        cfg = override(cfg, "--sigma", sigma_deg=_pair(args.sigma, "--sigma"))
    if args.heading_tolerance is not None:
        cfg = override(cfg, "--heading-tolerance", heading_tolerance_deg=args.heading_tolerance)
    if args.occlusion_weight is not None:
        cfg = override(cfg, "--occlusion-weight", occlusion_weight=args.occlusion_weight)
    if args.map_sigma is not None:
        cfg = override(cfg, "--map-sigma", map_vertical_sigma_m=args.map_sigma)
    return cfg


def _locate_in_file(args: argparse.Namespace, cfg: Any, db: SkylineDatabase, skylines: list[tuple[str, Skyline]],
                    moves: list[Move], tolerance: float | None) -> list[Position]:
    """Every skyline's answer on one database file, alone or fused as a sequence of stations."""
    height = _checked_height(args.height)
    occ, map_sigma = cfg.occlusion_weight, cfg.map_vertical_sigma_m
    if args.fuse:
        return locate_sequence(db, skylines, moves, cfg.sigma_deg, tolerance, height_m=height, occlusion_weight=occ,
                               map_sigma_m=map_sigma)
    return [locate(db, sky, cfg.sigma_deg, tolerance, source=name, height_m=height, occlusion_weight=occ,
                   map_sigma_m=map_sigma, sigma_floor_deg=cfg.sigma_floor_deg) for name, sky in skylines]



def _locate_tiled(args: argparse.Namespace, cfg: Any, skylines: list[tuple[str, Skyline]],
                  tolerance: float | None) -> tuple[TiledIndex, list[Position]]:
    """Every skyline's answer on a tiled database, searched over the tiles its search area meets
    (in process, or as Dask tasks with --scheduler or --workers), the tiles combined."""
    # the tiled search (threads, Dask, the fits on a map's surface) loads only for a tiled database
    from appliance.locating.tile_cache import SearchParams
    from appliance.locating.tiled_index import box_around, open_surface, open_tiled
    from appliance.locating.tiled_search import locate_tiled

    if args.fuse or args.report:
        raise InputError(f"{'--fuse' if args.fuse else '--report'} is not available with a tiled database; "
                         "give one tile's file instead")
    index = open_tiled(args.db)
    box: tuple[float, float, float, float] | None = None
    if args.search_bounds is not None:
        west, south, east, north = _numbers(args.search_bounds, "--search-bounds", 4)
        box = (west, south, east, north)
    elif args.near is not None:
        lat, lon, radius_m = _numbers(args.near, "--near", 3)
        box = box_around(lat, lon, radius_m, index.body)
    params = SearchParams(cfg.sigma_deg, tolerance, _checked_height(args.height), cfg.occlusion_weight,
                          cfg.map_vertical_sigma_m)
    surface, why_not = open_surface(index)
    if why_not is not None:
        print(f"viper estimate: warning: {args.db}: estimates stay on the facets' grid, not fitted on the map's "
              f"own surface: {why_not}", file=sys.stderr)
    with _dask_client(args.scheduler, args.workers) as client:
        return index, [locate_tiled(index, sky, params, box=box, client=client, source=name, surface=surface,
                                    sigma_floor_deg=cfg.sigma_floor_deg)
                       for name, sky in skylines]


@contextmanager
def _dask_client(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    """A Dask client on the given scheduler, or on a local cluster of ``workers`` processes (one
    thread each: the estimator's kernels are single-threaded per task); None for in-process."""
    if scheduler is None and workers is None:
        yield None
        return
    if workers is not None and not 1 <= workers <= 256:
        raise InputError(f"--workers {workers}: expected 1..256")
    # deferred: dask.distributed is the [cluster] extra, needed only with --scheduler or --workers
    distributed = require("distributed", "--scheduler and --workers")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(f"--scheduler {scheduler}: cannot connect ({first})") from None
        with client:
            yield client
        return
    config = require("dask.config", "--workers")
    with tempfile.TemporaryDirectory(prefix="viper-dask-", ignore_cleanup_errors=True) as scratch, \
            config.set({"temporary-directory": scratch}), \
            LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                         local_directory=scratch) as cluster, Client(cluster) as client:
        yield client  # the workers' scratch folder and its locks go with the temporary folder
