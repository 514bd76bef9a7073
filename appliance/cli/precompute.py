"""``viper precompute DEM --out DB``: the skyline database of a candidate grid."""

from __future__ import annotations

import argparse
import time

from appliance.atomic import check_output_path
from appliance.errors import InputError
from appliance.estimator.estimate import COARSE_STRIDE
from appliance.logsetup import ProgressCallback
from appliance.terrain.database import build_database
from appliance.terrain.dem import load_dem
from appliance.terrain.grid import plan_grids
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M

MAX_TERRAIN_NODES = 50_000_000  # the terrain grid the horizons are swept over (float64 work arrays)
MAX_DATABASE_BYTES = 16 * 2**30  # the skylines held in memory while they are built


def parse_bounds(text: str) -> tuple[float, float, float, float]:
    try:
        w, s, e, n = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--search-bounds {text!r}: expected W,S,E,N in degrees") from None
    return w, s, e, n


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("precompute", help="render the skyline of every candidate node into a database")
    p.add_argument("dem", help="DEM file or 'jacksboro'")
    p.add_argument("--out", required=True, help="database file to write")
    p.add_argument("--search-bounds", type=parse_bounds, help="W,S,E,N (deg) of the candidates")
    p.add_argument("--spacing", type=float, help="node spacing (m); default the DEM's own grid")
    p.add_argument("--height", type=float, default=DEFAULT_HEIGHT_M, help="camera height (m)")
    p.add_argument("--azimuths", type=int, default=360, help="azimuths per skyline (default 360)")
    p.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE_M, help="terrain reach (m)")
    p.add_argument("--refraction", type=float, help="refraction coefficient (default: the body's)")
    p.add_argument("--crs", help="CRS for a DEM file that carries none")
    p.add_argument("--force", action="store_true", help="replace the database if it exists")
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


def run(args: argparse.Namespace) -> int:
    if args.azimuths % COARSE_STRIDE:
        raise InputError(f"--azimuths {args.azimuths}: must be a multiple of {COARSE_STRIDE} (the estimator's "
                         f"coarse pass averages runs of {COARSE_STRIDE} azimuths)")
    if args.spacing is not None and args.spacing <= 0:
        raise InputError(f"--spacing {args.spacing} m must be positive")
    check_output_path(args.out, [args.dem], args.force)
    dem = load_dem(args.dem, crs=args.crs)
    check_size(dem, args)
    t0 = time.perf_counter()
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
