"""``viper daemon session``: the unattended session daemon (systemd Type=notify, watchdog)."""

from __future__ import annotations

import argparse
from pathlib import Path

from appliance.acquisition.daemon import SessionDaemon
from appliance.acquisition.notify import Notifier
from appliance.acquisition.retention import check_retention
from appliance.cli._platform import add_live_option, live_server, session_runner, warn_if_simulated
from appliance.config import load_config


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("daemon", help="run the appliance's daemons (under systemd)")
    sub = p.add_subparsers(dest="daemon_command", metavar="DAEMON", required=True)
    s = sub.add_parser("session", help="run sessions on the schedule of [session]; SIGTERM ends cleanly")
    s.add_argument("--config", metavar="FILE", help="TOML configuration (default: built-in defaults)")
    s.add_argument("--log-dir", metavar="DIR", help="override logbook.log_dir")
    add_live_option(s)
    s.set_defaults(func=_session)


def _session(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    warn_if_simulated("daemon session", config, args.config)
    log_dir = Path(args.log_dir) if args.log_dir else config.logbook.log_dir
    check_retention(config.logbook, log_dir)
    with live_server(args.live, args.live_linger) as live:
        daemon = SessionDaemon(config, log_dir, Notifier.from_environment(), session_runner(config, publisher=live))
        daemon.install_signal_handlers()
        return daemon.run()
