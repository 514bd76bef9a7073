"""``viper devices [--config FILE] [--seconds S]``: open the platform and print what each device says.

One JSON object per device reading on stdout (``device`` names it); a device that fails prints its
error instead of a value.  With ``[platform] kind = "sim"`` (the default) this runs the twins.
"""

from __future__ import annotations

import argparse
import json
import time

from appliance.cli._platform import open_devices, warn_if_simulated
from appliance.config import load_config
from appliance.errors import DeviceError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("devices", help="open the sensor platform (hardware or sim) and print a reading of each")
    p.add_argument("--config", metavar="FILE", help="TOML configuration (default: built-in defaults, simulated)")
    p.add_argument("--seconds", type=float, default=3.0, help="how long to wait for a GPS fix (default 3)")
    p.add_argument("--pan", type=float, default=None, help="also move the stage to this angle (deg)")
    p.set_defaults(func=run)


def _emit(device: str, read) -> object:  # type: ignore[no-untyped-def]
    try:
        value = read()
    except DeviceError as exc:
        print(json.dumps({"device": device, "error": str(exc)}), flush=True)
        return None
    print(json.dumps({"device": device, **value}), flush=True)
    return value


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    warn_if_simulated("devices", config, args.config)
    with open_devices(config) as p:
        fix = None
        if p.gps is not None:
            end = time.monotonic() + args.seconds
            while fix is None and time.monotonic() < end:
                fixes = p.gps.poll()
                fix = fixes[-1] if fixes else None
            print(json.dumps({"device": "gps", **(fix.to_json_dict() if fix else {"error": "no fix"})}), flush=True)
        if p.tilt is not None:
            _emit("tilt", lambda: {k: v for k, v in vars(p.tilt.read_tilt()).items()})
        if p.heading is not None:
            if fix is not None:
                p.heading.position = fix
            _emit("heading", lambda: dict(vars(p.heading.read_heading())))
        if p.stage is not None and args.pan is not None:
            _emit("stage", lambda: {"reached_deg": p.stage.move_to(args.pan)})
        if p.camera is not None:
            _emit("camera", lambda: {"shape": list(p.camera.capture().image.shape)})
    return 0
