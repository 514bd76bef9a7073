"""``viper gps SOURCE [--json]``: print the fixes of a GPS receiver (port, pyserial URL or log file)."""

from __future__ import annotations

import argparse
import json
import logging
import sys

from appliance.drivers.gps_reader import GpsSourceOptions, open_gps
from appliance.drivers.policy import ErrorPolicy
from appliance.errors import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "gps",
        help="print GPS fixes from a serial port, pyserial URL or recorded NMEA log",
        description="Print one fix per line; with --json one JSON object per fix "
        "(time UTC ISO 8601, lat, lon, alt_msl_m, alt_ellipsoid_m, quality, satellites, hdop, sigma_m).",
    )
    p.add_argument("source", help="log file, device path (/dev/ttyUSB0) or pyserial URL (socket://host:port)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--baud", type=int, default=9600, help="serial baud rate (default 9600)")
    p.add_argument("--count", type=int, default=0, help="stop after this many fixes (0: never)")
    p.add_argument("--stats", action="store_true", help="print skipped-record counts to stderr at the end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.count < 0:
        raise InputError(f"--count {args.count}: must be 0 (never stop) or a positive number of fixes")
    if args.baud <= 0:
        raise InputError(f"--baud {args.baud}: must be positive")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    reader = open_gps(args.source, GpsSourceOptions(baudrate=args.baud), ErrorPolicy.LOG)
    n = 0
    try:
        for fix in reader.fixes():
            if args.json:
                print(json.dumps(fix.to_json_dict(), allow_nan=False), flush=True)
            else:
                d = fix.to_json_dict()
                print(
                    f"{d['time'] or '-'} {fix.lat_deg:.8f} {fix.lon_deg:.8f} alt_msl={fix.alt_msl_m} m "
                    f"{d['quality']} sats={fix.satellites} hdop={fix.hdop} sigma={d['sigma_m']} m",
                    flush=True,
                )
            n += 1
            if args.count and n >= args.count:
                break
    finally:
        reader.close()
        if args.stats:
            print(json.dumps(reader.counts()), file=sys.stderr)
    return 0
