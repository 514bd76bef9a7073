"""``viper log info LOG.mcap`` and ``viper log recover BROKEN.mcap --out FIXED.mcap``."""

from __future__ import annotations

import argparse
import json

from appliance.logbook.recover import recover_log
from appliance.logbook.summary import summarize_log


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("log", help="inspect and repair session logs (MCAP)")
    sub = p.add_subparsers(dest="log_command", metavar="ACTION", required=True)

    info = sub.add_parser("info", help="topics, counts, time span, estimate vs GPS truth")
    info.add_argument("logs", nargs="+", metavar="LOG.mcap")
    info.add_argument("--json", action="store_true",
                      help="the same facts as one JSON object on stdout (a list of them for several logs)")
    info.set_defaults(func=_info)

    rec = sub.add_parser("recover", help="rewrite a truncated log (power cut, kill) into a valid one")
    rec.add_argument("broken", metavar="BROKEN.mcap")
    rec.add_argument("--out", required=True, metavar="FIXED.mcap")
    rec.add_argument("--force", action="store_true", help="replace FIXED.mcap if it exists")
    rec.set_defaults(func=_recover)


def _info(args: argparse.Namespace) -> int:
    incomplete = 0
    if args.json:
        summaries = [summarize_log(path) for path in args.logs]
        objects = [s.to_json() for s in summaries]
        print(json.dumps(objects[0] if len(objects) == 1 else objects, allow_nan=False))
        return 1 if any(not s.complete for s in summaries) else 0
    for i, path in enumerate(args.logs):
        summary = summarize_log(path)
        if i:
            print()
        print("\n".join(summary.lines()))
        incomplete += not summary.complete
    return 1 if incomplete else 0


def _recover(args: argparse.Namespace) -> int:
    report = recover_log(args.broken, args.out, overwrite=args.force)
    print(f"{args.out}: {report.describe()}")
    if report.problem:
        print(f"{args.broken}: {report.problem}")
    return 0
