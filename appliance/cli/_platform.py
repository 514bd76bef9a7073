"""The command line chooses the platform: the hardware of ``[devices]`` or the simulated twins of
``[sim]`` (``[platform] kind``), and prints a notice when it drives the simulated platform only
because no ``[platform]`` was given.  Nothing below the command line imports the simulator.  Also
the ``--live`` option (the Foxglove live view) of the commands that run sessions."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from viper_calibration.device_file import load_device_calibration

from appliance.config import Config, PlatformKind, read_config_toml
from appliance.errors import ConfigError, InputError

if TYPE_CHECKING:
    from appliance.acquisition.session import SessionResult
    from appliance.drivers.factory import Devices
    from appliance.logbook.live import LiveServer, Publisher

LOG = logging.getLogger(__name__)

def platform_given(config_path: str | Path | None) -> bool:
    """True when the configuration file has a ``[platform]`` table (the file was already read once)."""
    if config_path is None:
        return False
    try:
        return "platform" in read_config_toml(Path(config_path))
    except ConfigError:
        return False


def simulated_notice(command: str, config: Config, config_path: str | Path | None) -> str | None:
    """The one line to print on stderr, or None when the platform was chosen explicitly or is hardware."""
    if config.platform.kind is not PlatformKind.SIM or platform_given(config_path):
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
    parser.add_argument(
        "--live-linger", metavar="SECONDS", type=float, default=2.0,
        help="with --live, wait at most this long at the end for the clients to receive everything sent "
             "(default 2; 0: exit at once)")


@contextmanager
def live_server(address: str | None, linger_s: float = 2.0) -> Iterator[LiveServer | None]:
    """The live view of ``--live`` (None when the option was not given), stopped on exit: after a
    normal exit once its clients have received everything (at most ``linger_s`` seconds), at once
    after an error."""
    if address is None:
        yield None
        return
    if not linger_s >= 0:
        raise InputError(f"--live-linger {linger_s}: expected a number of seconds >= 0")
    # the live view's SDK loads only when --live is given
    from appliance.logbook.live import LiveServer, parse_address

    host, port = parse_address(address)
    with LiveServer(host, port, linger_s=linger_s) as server:
        yield server


def open_devices(config: Config) -> Devices:
    """The devices of ``[platform] kind``, with the calibrations of ``[devices]`` (file or inline)."""
    calibration = load_device_calibration(config.devices)
    if config.platform.kind is PlatformKind.HARDWARE:
        # a command imports only the platform it drives: the hardware's drivers or the twins
        from appliance.drivers.factory import open_hardware_platform

        return open_hardware_platform(config, calibration)
    from appliance.sim.platform import open_sim_platform  # the twins, only when simulating

    return open_sim_platform(config, calibration=calibration)


def session_runner(config: Config, seed: int | None = None, publisher: Publisher | None = None
                   ) -> Callable[[Path, Callable[[], bool], Callable[[str], None]], SessionResult]:
    """What one session of ``viper capture`` or the session daemon runs: on the hardware, a session
    with the ``[session] database``; in simulation, a whole field session at a random position of the
    ``[sim] dem`` map (``seed`` chooses it); every logged message also goes to ``publisher``, the
    live view, when given.  With ``[traverse] stops``, a session is a rover's traverse of that many
    stops (in simulation, the rover twin drives the platform between them)."""

    def run(log_dir: Path, should_stop: Callable[[], bool], on_status: Callable[[str], None]) -> SessionResult:
        stops = config.traverse.stops
        if config.platform.kind is PlatformKind.SIM:
            # the session's modules (the estimator's compiled kernels, OpenCV) load when a session runs
            from appliance.sim.field_session import run_field_session, run_field_traverse

            if stops:
                traverse, _ = run_field_traverse(config, log_dir, stops, seed=seed, should_stop=should_stop,
                                                 on_status=on_status, publisher=publisher)
                return traverse
            result, _ = run_field_session(config, log_dir, seed=seed, should_stop=should_stop, on_status=on_status,
                                         publisher=publisher)
            return result
        from appliance.acquisition.onboard import load_session_database  # as above: when a session runs

        on_status("loading the skyline database")
        db = load_session_database(config.session)
        if stops:
            from appliance.acquisition.traverse import run_platform_traverse  # when a traverse runs

            return run_platform_traverse(open_devices, config, log_dir, db, should_stop, on_status, publisher)
        from appliance.acquisition.session import run_platform_session  # when a session runs

        return run_platform_session(open_devices, config, log_dir, db, should_stop, on_status, publisher)

    return run
