"""``viper precompute DEM... --out DB``: the skyline database of a candidate grid.

Several DEM files (adjacent tiles) are read as one mosaic.  ``--tiles`` (or an ``--out`` that is an
existing folder) builds a tiled database in that folder, one Dask task per tile, on a local cluster
of ``--workers`` processes or on the cluster at ``--scheduler``; a rerun completes an interrupted
build; the local cluster's scratch folder is a temporary folder removed when the build ends.  The
temporaries a killed build left in the output's folder are removed when the next one starts there,
whatever their output's name.  ``--tiles --whole-body`` builds a map of a whole body (the LOLA Moon) as
facets, each on its own metric grid (:mod:`appliance.terrain.whole_body`); ``--search-bounds`` then chooses the facets.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from appliance.atomic import check_output_folder, check_output_path, remove_dead_writers_temporaries
from appliance.errors import InputError
from appliance.estimator.estimate import COARSE_STRIDE
from appliance.extras import require
from appliance.logsetup import ProgressCallback
from appliance.terrain.database import build_database
from appliance.terrain.dem import load_dem
from appliance.terrain.grid import plan_grids
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
from appliance.terrain.mosaic import MOSAIC_VRT, open_map
from appliance.terrain.tiled import DEFAULT_TILE_NODES, TiledPlan, build_tiled, plan_tiles, remove_tile_temporaries
from appliance.terrain.whole_body import DEFAULT_BAND_DEG, DEFAULT_CAP_DEG, build_whole_body

MAX_TERRAIN_NODES = 50_000_000  # the terrain grid the horizons are swept over (float64 work arrays)
MAX_DATABASE_BYTES = 16 * 2**30  # the skylines of one build: spilled to disk as they are swept, then written


def parse_bounds(text: str) -> tuple[float, float, float, float]:
    try:
        w, s, e, n = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--search-bounds {text!r}: expected W,S,E,N in degrees") from None
    return w, s, e, n


def parse_tile_nodes(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--tile-nodes {text!r}: expected ROWS,COLS, e.g. 1201,1201") from None
    if rows < 1 or cols < 1:
        raise InputError(f"--tile-nodes {text!r}: both counts must be positive")
    return rows, cols


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("precompute", help="render the skyline of every candidate node into a database")
    p.add_argument("dem", nargs="+", help="DEM file, several adjacent DEM files (one mosaic), a GDAL VRT, or "
                   "'jacksboro'")
    p.add_argument("--out", required=True, help="database file to write (a folder with --tiles)")
    p.add_argument("--search-bounds", type=parse_bounds, help="W,S,E,N (deg) of the candidates")
    p.add_argument("--spacing", type=float, help="node spacing (m); default the DEM's own grid (with --whole-body: "
                   "half the map's pixel size)")
    p.add_argument("--height", type=float, default=DEFAULT_HEIGHT_M, help="camera height (m)")
    p.add_argument("--azimuths", type=int, default=360, help="azimuths per skyline (default 360)")
    p.add_argument("--max-range", type=float, help=f"terrain reach (m); default {DEFAULT_MAX_RANGE_M:.0f}, and with "
                   "--whole-body the distance at which the map's highest point sinks below the horizon of its lowest "
                   "(about 260 km on the Moon)")
    p.add_argument("--refraction", type=float, help="refraction coefficient (default: the body's)")
    p.add_argument("--crs", help="CRS for a DEM file that carries none")
    p.add_argument("--force", action="store_true", help="replace the database if it exists")
    p.add_argument("--tiles", action="store_true", help="build a tiled database into the folder --out")
    p.add_argument("--whole-body", action="store_true",
                   help="with --tiles: a map of the whole body (wrapping in longitude, reaching both poles) as "
                   f"facets on their own grids: {DEFAULT_BAND_DEG:.0f}-degree latitude bands cut into boxes about as "
                   f"wide as high, and two polar caps beyond +-{DEFAULT_CAP_DEG:.0f} degrees; --search-bounds builds "
                   "only the facets it meets; --tile-nodes does not apply")
    p.add_argument("--tile-nodes", type=parse_tile_nodes, default=DEFAULT_TILE_NODES,
                   help="rows,cols of candidate nodes per tile (default %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes of a tiled build (default 2)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler for a tiled build")
    p.set_defaults(func=run)


def check_size(dem: object, args: argparse.Namespace) -> None:
    """Refuse a grid too large to build, from its node counts, before anything is allocated."""
    cand, terr, _ = plan_grids(dem, args.search_bounds, args.spacing, args.max_range)  # type: ignore[arg-type]
    n_terrain = terr.n_rows * terr.n_cols
    n_bytes = cand.n_rows * cand.n_cols * max(args.azimuths, 1) * 5
    if n_terrain > MAX_TERRAIN_NODES or n_bytes > MAX_DATABASE_BYTES:
        raise InputError(
            f"--spacing {cand.dx_m:.3g} m gives {cand.n_rows} x {cand.n_cols} candidate nodes over a "
            f"{terr.n_rows} x {terr.n_cols} terrain grid ({n_bytes / 2**30:.3g} GiB of skylines); at most "
            f"{MAX_TERRAIN_NODES:,} terrain nodes and {MAX_DATABASE_BYTES / 2**30:.0f} GiB: give a larger --spacing "
            "or smaller --search-bounds"
        )


def check_tile_size(plan: TiledPlan, args: argparse.Namespace) -> None:
    """Refuse tiles too large for one task (its terrain window, its skylines), before any work."""
    n_terrain = max(t.terrain[2] * t.terrain[3] for t in plan.tiles)
    n_bytes = max(t.n_rows * t.n_cols for t in plan.tiles) * max(args.azimuths, 1) * 5
    if n_terrain > MAX_TERRAIN_NODES or n_bytes > MAX_DATABASE_BYTES:
        raise InputError(
            f"a tile of --tile-nodes {args.tile_nodes[0]},{args.tile_nodes[1]} needs a terrain window of "
            f"{n_terrain:,} nodes and {n_bytes / 2**30:.3g} GiB of skylines; at most {MAX_TERRAIN_NODES:,} and "
            f"{MAX_DATABASE_BYTES / 2**30:.0f} GiB: give smaller --tile-nodes, a larger --spacing or a shorter "
            "--max-range"
        )


def run(args: argparse.Namespace) -> int:
    if args.azimuths % COARSE_STRIDE:
        raise InputError(f"--azimuths {args.azimuths}: must be a multiple of {COARSE_STRIDE} (the estimator's "
                         f"coarse pass averages runs of {COARSE_STRIDE} azimuths)")
    if args.spacing is not None and args.spacing <= 0:
        raise InputError(f"--spacing {args.spacing} m must be positive")
    if args.max_range is not None and not args.max_range > 0:
        raise InputError(f"--max-range {args.max_range} m must be positive")
    if args.whole_body and not args.tiles:
        raise InputError("--whole-body builds a tiled database: give --tiles too")
    if args.max_range is None and not args.whole_body:
        args.max_range = DEFAULT_MAX_RANGE_M
    if args.tiles or Path(args.out).is_dir():
        return run_tiled(args)
    out = check_output_path(args.out, args.dem, args.force)
    remove_dead_writers_temporaries(out.parent if str(out.parent) else Path("."))
    t0 = time.perf_counter()
    if len(args.dem) == 1:
        dem = load_dem(args.dem[0], crs=args.crs)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            source = open_map(args.dem, Path(tmp) / MOSAIC_VRT, args.crs)
            check_size(source.header(), args)  # from the mosaic's shape, before its heights are read
            dem = source.load()
    check_size(dem, args)
    header = build_database(
        dem, args.out, args.search_bounds, args.spacing, args.height, args.azimuths,
        args.refraction, args.max_range, progress=ProgressCallback("azimuth"),
    )
    g = header["grid"]
    n = g["n_rows"] * g["n_cols"]
    print(
        f"{args.out}: {n} skylines ({g['n_rows']} x {g['n_cols']} nodes, "
        f"{g['dx_m']:.1f} x {g['dy_m']:.1f} m) x {header['n_azimuths']} azimuths "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    return 0


def run_tiled(args: argparse.Namespace) -> int:
    """The tiled build: a local cluster of single-threaded worker processes unless --scheduler."""
    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: at least 1")
    out = check_output_folder(args.out, args.dem)
    remove_dead_writers_temporaries(out)
    source = open_map(args.dem, out / MOSAIC_VRT if len(args.dem) > 1 else None, args.crs)
    if not args.whole_body:
        check_tile_size(plan_tiles(source.header(), args.search_bounds, args.spacing, args.max_range,
                                   args.tile_nodes), args)
    t0 = time.perf_counter()
    with _dask_client(args, out) as client:
        if args.whole_body:
            result = build_whole_body(source, out, args.search_bounds, args.spacing, args.height, args.azimuths,
                                      args.refraction, args.max_range, client=client, force=args.force,
                                      progress=ProgressCallback("facet"))
        else:
            result = build_tiled(source, out, args.search_bounds, args.spacing, args.height, args.azimuths,
                                 args.refraction, args.max_range, args.tile_nodes, client, args.force,
                                 progress=ProgressCallback("tile"))
    if args.whole_body:
        wb = result.index["whole_body"]
        print(f"{out}: {len(result.index['tiles'])} facets ({len(result.built)} built, {len(result.kept)} kept) at "
              f"{wb['spacing_m']:.1f} m x {result.index['n_azimuths']} azimuths, reach "
              f"{result.index['max_range_m'] / 1000:.0f} km, in {time.perf_counter() - t0:.1f} s")
        return 0
    lat = result.index["lattice"]
    void = f", {len(result.void)} wholly on nodata left out" if result.void else ""
    print(f"{out}: {len(result.index['tiles'])} tiles ({len(result.built)} built, {len(result.kept)} kept{void}) of "
          f"{lat['n_rows']} x {lat['n_cols']} nodes ({lat['dx_m']:.1f} x {lat['dy_m']:.1f} m) x "
          f"{result.index['n_azimuths']} azimuths in {time.perf_counter() - t0:.1f} s")
    return 0


@contextmanager
def _dask_client(args: argparse.Namespace, out: Path) -> Iterator[Any]:
    """A client of the scheduler at --scheduler, or of a local cluster of --workers single-threaded
    processes whose scratch folder (the workers' files and locks) is a temporary folder, removed with it."""
    terminal = sys.stderr.isatty()
    # deferred: dask.distributed is the [cluster] extra, needed only by a tiled build
    distributed = require("distributed", "a tiled build (--tiles)")
    if args.scheduler:
        try:
            client = distributed.Client(args.scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {args.scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    config = require("dask.config", "a tiled build (--tiles)")
    with tempfile.TemporaryDirectory(prefix="viper-dask-", ignore_cleanup_errors=True) as scratch, \
            config.set({"temporary-directory": scratch}):  # the scheduler's scratch folder too
        try:
            with distributed.LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                                          dashboard_address=":0" if terminal else None, local_directory=scratch,
                                          silence_logs=logging.WARNING if terminal else logging.CRITICAL
                                          ) as cluster, distributed.Client(cluster) as client:
                if terminal and client.dashboard_link:
                    print(f"dashboard: {client.dashboard_link}", file=sys.stderr)
                yield client
        finally:
            remove_tile_temporaries(out)  # the local workers are gone: their unfinished tiles with them
