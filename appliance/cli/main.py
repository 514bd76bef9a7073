"""Entry point of the ``viper`` console command."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import sys
import typing
from collections.abc import Sequence

import appliance.cli as cli_pkg
from appliance import __version__
from appliance.atomic import describe_os_error, forget_created_folders, remove_created_folders
from appliance.errors import ViperError
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
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="viper",
        description="Viper field appliance: position from the skyline, matched against a DEM.",
    )
    parser.add_argument("--version", action="version", version=f"viper {__version__}")
    parser.add_argument("--log-level", choices=LEVELS, default="info",
                        help="messages on stderr at this level and above (default info); under systemd each "
                             "line carries its journal priority")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(cli_pkg.__path__), key=lambda m: m.name):
        if info.name == "main" or info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{cli_pkg.__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(join_negative_values(sys.argv[1:] if argv is None else argv))
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
    print(f"viper {args.command}: error: {' '.join(message.split())}", file=sys.stderr)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
