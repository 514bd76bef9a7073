"""``viper capture``: one session now (level, compass, GPS truth, capture, onboard estimate).

The session's result goes to stdout; what went wrong with the log (a full disk) to stderr, and the
exit status is then non-zero."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from appliance.acquisition.daemon import run_one_session
from appliance.cli._platform import add_live_option, live_server, session_runner, warn_if_simulated
from appliance.config import load_config
from appliance.logsetup import StatusLine

LOG = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("capture", help="run one field session now and write its MCAP log")
    p.add_argument("--config", metavar="FILE", help="TOML configuration (default: built-in defaults)")
    p.add_argument("--log-dir", metavar="DIR", help="override logbook.log_dir")
    p.add_argument("--seed", type=int, help="seed of the simulated platform (platform.kind = 'sim')")
    add_live_option(p)
    p.set_defaults(func=_capture)


def _capture(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    warn_if_simulated("capture", config, args.config)
    log_dir = Path(args.log_dir) if args.log_dir else config.logbook.log_dir
    with live_server(args.live, args.live_linger) as live, StatusLine("capture") as status:
        result = run_one_session(session_runner(config, args.seed, publisher=live), log_dir, on_status=status)
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
    if result.log_error is not None:
        LOG.error("%s", result.log_error)
        return 1
    if result.frames == 0:
        LOG.error("no frame captured: the session measured nothing")
        return 1
    return 0 if result.status.value != "failed" else 1
