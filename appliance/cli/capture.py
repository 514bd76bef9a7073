"""``viper capture``: one session now (level, compass, GPS truth, capture, onboard estimate).

The session's result goes to stdout (``--json``: as one JSON object); what went wrong with the log (a
full disk) to stderr, and the exit status is then non-zero.  With an estimate, the map's layers (the
posteriors as GeoTIFF, the region and the points as GeoJSON with their QGIS styles) are written beside
the log, named after it."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from appliance.acquisition.daemon import run_one_session
from appliance.acquisition.result_json import capture_json, dumps
from appliance.acquisition.retention import check_retention
from appliance.acquisition.session import SessionResult
from appliance.cli._platform import add_live_option, live_server, session_runner, warn_if_simulated
from appliance.config import Config, LogEncoding, load_config, override
from appliance.logsetup import StatusLine

LOG = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("capture", help="run one field session now and write its MCAP log")
    p.add_argument("--config", metavar="FILE", help="TOML configuration (default: built-in defaults)")
    p.add_argument("--log-dir", metavar="DIR", help="override logbook.log_dir")
    p.add_argument("--seed", type=int, help="seed of the simulated platform (platform.kind = 'sim')")
    add_log_encoding_option(p)
    p.add_argument("--json", action="store_true", help="print the result as one JSON object on stdout")
    add_live_option(p)
    p.set_defaults(func=_capture)


def add_log_encoding_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log-encoding", choices=[e.value for e in LogEncoding],
                   help="messages of the MCAP log: Foxglove protobuf or standard ROS 2 messages "
                        "(default: [logbook] encoding, protobuf)")


def with_log_encoding(config: Config, encoding: str | None) -> Config:
    """``config`` with ``[logbook] encoding`` replaced by ``--log-encoding`` when given."""
    if encoding is None:
        return config
    logbook = override(config.logbook, "--log-encoding", encoding=LogEncoding(encoding))
    return dataclasses.replace(config, logbook=logbook)


def _capture(args: argparse.Namespace) -> int:
    config = with_log_encoding(load_config(args.config), args.log_encoding)
    warn_if_simulated("capture", config, args.config)
    log_dir = Path(args.log_dir) if args.log_dir else config.logbook.log_dir
    check_retention(config.logbook, log_dir)
    with live_server(args.live, args.live_linger) as live, StatusLine("capture") as status:
        result = run_one_session(session_runner(config, args.seed, publisher=live), log_dir, on_status=status,
                                 logbook=config.logbook)
    layers = result.map_layers
    if args.json:
        print(dumps({**capture_json(result), "map_layers": [str(p) for p in layers]}))
    else:
        _print_result(result)
        if layers:
            print(f"map layers: {', '.join(str(p) for p in layers)}")
    if result.log_error is not None:
        LOG.error("%s", result.log_error)
        return 1
    if result.layers_error is not None:
        return 1
    if result.frames == 0:
        LOG.error("no frame captured: the session measured nothing")
        return 1
    return 0 if result.status.value != "failed" else 1


def _print_result(result: SessionResult) -> None:
    print(f"log: {result.log_path}")
    print(f"session {result.session_id}: {result.status.value}; frames {result.frames}")
    for name, outcome in result.outcomes.items():
        print(f"  {name}: {outcome}")
    for problem in result.problems:
        print(f"  problem: {problem}")
    if result.estimate is not None:
        e = result.estimate
        err = "no GPS truth" if result.error_m is None else f"{result.error_m:.0f} m from the GPS truth"
        area = e.result.region_area_m2 / 1e6
        print(f"estimate: lat {e.lat:.6f} lon {e.lon:.6f} (region {area:.3f} km^2), {err}")
