"""Entry point of the ``viper`` console command."""

from __future__ import annotations

import argparse
import atexit
import gc
import importlib
import os
import re
import sys
import typing
from collections.abc import Sequence

from appliance import __version__
from appliance.atomic import describe_os_error, forget_created_folders, remove_created_folders
from appliance.cli._forward import FORWARDED, forward
from appliance.errors import ViperError
from appliance.extras import missing_extra
from appliance.logsetup import LEVELS, configure_logging

#: Options whose value is a comma-separated list of numbers that may start with a minus sign.
NUMBER_LIST_OPTIONS = frozenset({"--truth", "--move", "--search-bounds", "--sigma", "--stage-angles", "--lat",
                                 "--lon", "--heading-offset", "--azimuth-offset", "--known-bearing-deg", "--mask"})
_NEGATIVE_LIST = re.compile(r"^-[0-9.]")


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--truth -36.5,84.2`` as ``--truth=-36.5,84.2``: argparse would take the value for an option."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in NUMBER_LIST_OPTIONS and i + 1 < len(argv) and _NEGATIVE_LIST.match(argv[i + 1]):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr (``viper CMD: error: ...``), exit status 2;
    ``viper CMD --help`` shows the usage."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {printable(message)}\n")


#: Every subcommand: its module under appliance.cli (whose ``register`` adds its parser) and the one-line
#: help that ``viper --help`` lists.  Only the module of the command being run is imported, so that a
#: command starts without loading what the others need (a test checks this table against the modules).
COMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("calibrate", "calibrate the theodolite sigma, camera, compass, inclinometers"),
    "capture": ("capture", "run one field session now and write its MCAP log"),
    "daemon": ("daemon", "run the appliance's daemons (under systemd)"),
    "dem": ("dem", "inspect a DEM"),
    "demo": ("demo", "a whole simulated field session on the embedded jacksboro map"),
    "devices": ("devices", "open the sensor platform (hardware or sim) and print a reading of each"),
    "estimate": ("estimate", "estimate the position from skyline CSVs and a skyline database"),
    "gps": ("gps", "print GPS fixes from a serial port, pyserial URL or recorded NMEA log"),
    "locate": ("locate", "locate a photo or a panorama on a map: position and orientation, in one command"),
    "log": ("log", "inspect and repair session logs (MCAP)"),
    "precompute": ("precompute", "render the skyline of every candidate node into a database"),
    "render": ("render", "render the skyline seen from a point of a DEM"),
    "replay": ("replay", "rerun stitch, skyline and estimate from session logs; report"),
    "serve": ("serve", "run estimate, locate, render and skyline in a warm process, so that they start at once"),
    "skyline": ("skyline", "detect the skyline in a panorama or a photo and write the azimuth/elevation CSV"),
    "stitch": ("stitch", "stitch images taken at known stage angles into a panorama"),
}


#: global options (before the command) that take a value: their value is never the command
GLOBAL_VALUE_OPTIONS = frozenset({"--log-level"})


def command_of(argv: Sequence[str]) -> str | None:
    """The subcommand named on the command line (the first word that names one, other than the
    value of a global option such as ``--log-level``), if any."""
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a in GLOBAL_VALUE_OPTIONS:
            skip = True
        elif a in COMMANDS:
            return a
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``viper`` parser; ``command``'s module is imported and its full parser registered, every
    other command is listed by name and help only (all of them when ``command`` is "*")."""
    parser = OneLineParser(
        prog="viper",
        description="Viper field appliance: position from the skyline, matched against a DEM.",
    )
    parser.add_argument("--version", action="version", version=f"viper {__version__}")
    parser.add_argument("--log-level", choices=LEVELS, default="info",
                        help="messages on stderr at this level and above (default info); under systemd each "
                             "line carries its journal priority")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        if command in (name, "*"):
            importlib.import_module(f"appliance.cli.{module_name}").register(sub)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command line (``sys.argv`` when ``argv`` is None: the console command, which a
    ``viper serve`` of this user may run in its warm process instead, see
    :mod:`appliance.cli._forward`)."""
    from_shell = argv is None
    argv = join_negative_values(sys.argv[1:] if argv is None else argv)
    command = command_of(argv)
    if from_shell:
        status = forward(argv, command)
        if status is not None:
            return status
        # the process is this one command: what its imports make lives to its end, and the objects alive at its
        # end are left to the exit.  So the cyclic collector is off while the command's modules are imported
        # (their objects are not garbage; its collections there took 0.05-0.08 s before a viper locate), and
        # what they made is frozen out of its reach afterwards: neither the collections of the command's own
        # garbage nor the interpreter's teardown traverse it (the teardown's took 0.25 s after a viper locate)
        gc.disable()
        atexit.register(gc.freeze)
        if command in FORWARDED:
            # a one-shot command that no server took: its compiled kernels' threads (GNU OpenMP's, loaded at the
            # first parallel kernel) sleep between kernels instead of spinning on a core for a while after each
            # (0.1-0.15 s of CPU over a viper locate, which a loaded machine takes from the command's own
            # threads); a policy set in the environment stays.  Not for a server: its environment is compared
            # with its clients' as they start
            os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        parser = build_parser(command)
    except ModuleNotFoundError as exc:  # an optional library the command's module imports at its top
        error = missing_extra(exc)
        if error is None:
            raise
        print(f"viper {command}: error: {printable(str(error))}", file=sys.stderr)
        return error.exit_code
    finally:
        if from_shell:
            gc.freeze()
            gc.enable()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help(sys.stderr)
        return 2
    configure_logging(args.log_level)
    forget_created_folders()
    try:
        return int(func(args) or 0)
    except BrokenPipeError:
        return 0
    except ViperError as exc:
        message = str(exc)
        code = exc.exit_code
    except ModuleNotFoundError as exc:
        error = missing_extra(exc)
        if error is None:
            raise
        message, code = str(error), error.exit_code
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        message, code = f"{where}{describe_os_error(exc)}", 1
    except MemoryError:
        message, code = "out of memory", 1
    except KeyboardInterrupt:
        remove_created_folders()
        print(f"viper {args.command}: interrupted", file=sys.stderr)
        return 130
    remove_created_folders()
    print(f"viper {args.command}: error: {printable(message)}", file=sys.stderr)
    return code


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def printable(message: str) -> str:
    """``message`` as one line a terminal shows as it is: runs of white space made one space, and every
    other control character (an ANSI escape from a file name or a TOML key) written as ``\\xNN``."""
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", " ".join(message.split()))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
