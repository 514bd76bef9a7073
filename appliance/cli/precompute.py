"""``viper precompute DEM --out DB``: the skyline database of a candidate grid."""

from __future__ import annotations

import argparse
import time

from appliance.atomic import check_output_path
from appliance.errors import InputError
from appliance.terrain.database import build_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M


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


def run(args: argparse.Namespace) -> int:
    if args.spacing is not None and args.spacing <= 0:
        raise InputError(f"--spacing {args.spacing} m must be positive")
    check_output_path(args.out, [args.dem], args.force)
    dem = load_dem(args.dem, crs=args.crs)
    t0 = time.perf_counter()
    header = build_database(
        dem, args.out, args.search_bounds, args.spacing, args.height, args.azimuths,
        args.refraction, args.max_range,
    )
    g = header["grid"]
    n = g["n_rows"] * g["n_cols"]
    print(
        f"{args.out}: {n} skylines ({g['n_rows']} x {g['n_cols']} nodes, "
        f"{g['dx_m']:.1f} x {g['dy_m']:.1f} m) x {header['n_azimuths']} azimuths "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    return 0
