"""``viper dem info DEM [--json]``: what a map holds."""

from __future__ import annotations

import argparse
import json

from appliance.terrain.dem import load_dem


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dem", help="inspect a DEM")
    dsub = p.add_subparsers(dest="dem_command", metavar="ACTION", required=True)
    info = dsub.add_parser("info", help="print a DEM's CRS, body, shape, resolution, bounds and range")
    info.add_argument("dem", help="DEM file (GeoTIFF, USGS .dem, SRTM .hgt, PDS .LBL/.IMG, .npz, .e00) or 'jacksboro'")
    info.add_argument("--crs", help="CRS for a file that carries none (e.g. EPSG:32632)")
    info.add_argument("--json", action="store_true", help="one JSON object")
    info.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    dem = load_dem(args.dem, crs=args.crs)
    info = dem.info()
    if args.json:
        print(json.dumps(info))
        return 0
    for key, value in info.items():
        print(f"{key:16s} {value}")
    return 0
