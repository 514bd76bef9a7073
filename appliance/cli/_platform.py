"""Shared by the commands that run sessions: the notice printed when a run drives the simulated platform only
because no ``[platform]`` was given, and the ``--live`` option (the Foxglove live view)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.config import Config

if TYPE_CHECKING:
    from appliance.logbook.live import LiveServer

LOG = logging.getLogger(__name__)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


def platform_given(config_path: str | Path | None) -> bool:
    """True when the configuration file has a ``[platform]`` table (the file was already read once)."""
    if config_path is None:
        return False
    try:
        return "platform" in tomllib.loads(Path(config_path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def simulated_notice(command: str, config: Config, config_path: str | Path | None) -> str | None:
    """The one line to print on stderr, or None when the platform was chosen explicitly or is hardware."""
    if config.platform.kind != "sim" or platform_given(config_path):
        return None
    source = "no --config given" if config_path is None else f"{config_path} has no [platform] table"
    return (f"viper {command}: running the SIMULATED platform ({source}); set [platform] kind = \"hardware\" "
            "to drive the devices")


def warn_if_simulated(command: str, config: Config, config_path: str | Path | None) -> None:
    line = simulated_notice(command, config, config_path)
    if line is not None:
        LOG.warning(line)


def add_live_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--live", metavar="[HOST:]PORT",
        help="serve the session live to Foxglove (WebSocket) on PORT, bound to 127.0.0.1 unless HOST is given "
             "(off by default)")


@contextmanager
def live_server(address: str | None) -> Iterator[LiveServer | None]:
    """The live view of ``--live`` (None when the option was not given), stopped on exit."""
    if address is None:
        yield None
        return
    from appliance.logbook.live import LiveServer, parse_address

    host, port = parse_address(address)
    server = LiveServer(host, port)
    try:
        yield server
    finally:
        server.close()
