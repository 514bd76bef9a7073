"""``viper render DEM --lat --lon``: the skyline one should see from a point, as CSV."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from appliance.atomic import check_output_path
from appliance.errors import InputError
from appliance.skyline import format_skyline_csv, write_skyline_csv
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M, render_skyline

#: The highest camera a render is made for (m above the ground): a mast, a balloon, a high aircraft.
MAX_HEIGHT_M = 100_000.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render the skyline seen from a point of a DEM")
    p.add_argument("dem", help="DEM file or 'jacksboro'")
    p.add_argument("--lat", type=float, required=True, help="latitude (deg)")
    p.add_argument("--lon", type=float, required=True, help="longitude (deg)")
    p.add_argument("--height", type=float, default=DEFAULT_HEIGHT_M, help="camera height above ground (m)")
    p.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE_M, help="farthest terrain (m)")
    p.add_argument("--refraction", type=float, help="refraction coefficient (default: the body's)")
    p.add_argument("--azimuths", type=int, default=360, help="number of azimuths (default 360)")
    p.add_argument("--crs", help="CRS for a DEM file that carries none")
    p.add_argument("--out", help="CSV file to write (default: standard output)")
    p.add_argument("--force", action="store_true", help="replace the CSV if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.azimuths <= 36000:
        raise InputError(f"--azimuths {args.azimuths} outside [1, 36000]")
    if args.height < 0:
        raise InputError(f"--height {args.height} m is negative")
    if not -180.0 <= args.lon <= 360.0:
        raise InputError(f"--lon {args.lon} outside [-180, 360]")
    if not -90.0 <= args.lat <= 90.0:
        raise InputError(f"--lat {args.lat} outside [-90, 90]")
    if not math.isfinite(args.height):
        raise InputError(f"--height {args.height}: not a number of metres")
    if args.height > MAX_HEIGHT_M:
        raise InputError(f"--height {args.height:g} m: more than {MAX_HEIGHT_M:g} m above the ground "
                         "(a render is of a camera on or over the terrain)")
    if not (math.isfinite(args.max_range) and args.max_range > 0):
        raise InputError(f"--max-range {args.max_range}: must be a positive number of metres")
    if args.refraction is not None and not -1.0 < args.refraction < 1.0:
        raise InputError(f"--refraction {args.refraction}: outside (-1, 1)")
    if args.out:
        check_output_path(args.out, [args.dem], args.force)
    dem = load_dem(args.dem, crs=args.crs)
    az = np.arange(args.azimuths) * (360.0 / args.azimuths)
    horizon = render_skyline(dem, args.lat, args.lon, args.height, az, args.max_range, args.refraction)
    if args.out:
        write_skyline_csv(horizon, args.out)
    else:
        sys.stdout.write(format_skyline_csv(horizon))
    return 0
