"""NMEA fuzzing: mutated sentences from the real logs through the framer and every decoder.

Run: .venv/bin/python bench/nmea_fuzz.py [--count 1000000] [--seed 1]   (appends to bench/results/nmea_fuzz.md)

Each input is one sentence of the receiver and compass logs in ../shared/data (nmea_gps,
heading_attitude) with one to three mutations (a field replaced by a hostile value, a byte
changed, a field inserted, deleted or duplicated, the line cut, random bytes appended); three in
four get a valid checksum again so that the mutation reaches the field decoders.  Inputs are fed
in batches of 50 to one framer, GPS decoder and heading decoder with the RAISE policy, so epochs
span mutated sentences too.  Target: no exception other than the project's own (ViperError).
"""

from __future__ import annotations

import argparse
import collections
import datetime
import logging
import random
import sys
import time
from pathlib import Path

import pynmea2

from appliance.drivers.gps import GpsDecoder
from appliance.drivers.heading import HeadingDecoder
from appliance.drivers.nmea_framer import NmeaFramer
from appliance.drivers.policy import ErrorPolicy
from appliance.errors import ViperError

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "bench" / "results" / "nmea_fuzz.md"
sys.path.insert(0, str(ROOT))
from bench.results_file import append_result  # noqa: E402

HOSTILE = [
    "", "99999999999999999999", "999999999999999999999999999999", "-1", "nan", "NaN", "inf", "-inf", "1e999",
    "1_000", "0x1F", "+", "-", ".", "..", "1.2.3", " ", "00", "60", "99", "235960.99", "9999", "0000", "-0",
    "1e-400", "4916.4X", "A", "V", "N", "S", "~", "12345678901234567890.12345", "-99999999999999999999",
]
PRINTABLE = [chr(c) for c in range(0x20, 0x7F) if chr(c) not in "*,$!"]


def sentences() -> list[str]:
    out = []
    for folder in ("nmea_gps", "heading_attitude"):
        for p in sorted((DATA / folder).glob("*.log")):
            for raw in p.read_bytes().splitlines():
                text = raw.decode("ascii", "replace").strip().lstrip("|")
                if text.startswith(("$", "!")) and "*" in text:
                    out.append(text)
    return out


def mutate(text: str, rng: random.Random) -> bytes:
    body = text[1:text.index("*")]
    fields = body.split(",")
    for _ in range(rng.randint(1, 3)):
        kind = rng.choice(("field", "field", "field", "byte", "insert", "delete", "cut", "dup"))
        i = rng.randrange(len(fields))
        if kind == "field" and len(fields) > 1:
            fields[max(1, i)] = (rng.choice(HOSTILE) if rng.random() < 0.7
                                 else "".join(rng.choice(PRINTABLE) for _ in range(rng.randint(0, 12))))
        elif kind == "byte" and fields[i]:
            j = rng.randrange(len(fields[i]))
            fields[i] = fields[i][:j] + rng.choice(PRINTABLE) + fields[i][j + 1:]
        elif kind == "insert":
            fields.insert(i, rng.choice(HOSTILE))
        elif kind == "delete" and len(fields) > 1:
            del fields[max(1, i)]
        elif kind == "cut":
            fields = fields[: max(1, i)]
        elif kind == "dup":
            fields = fields + fields[1:]
    body = ",".join(fields)
    if rng.random() < 0.75:
        line = f"${body}*{pynmea2.NMEASentence.checksum(body):02X}".encode("ascii", "replace")
    else:
        line = ("$" + body + rng.choice(("", "*", "*0", "*ZZ", "*00"))).encode("ascii", "replace")
    if rng.random() < 0.05:
        line += bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
    return line + b"\r\n"


def fuzz(count: int, seed: int) -> tuple[int, collections.Counter[str], list[str]]:
    rng = random.Random(seed)
    pool = sentences()
    if not pool:
        raise SystemExit(f"no NMEA logs in {DATA}")
    errors: collections.Counter[str] = collections.Counter()
    foreign: list[str] = []
    done = 0
    while done < count:
        batch = [mutate(rng.choice(pool), rng) for _ in range(min(50, count - done))]
        framer, gps, heading = NmeaFramer(), GpsDecoder(ErrorPolicy.RAISE), HeadingDecoder(ErrorPolicy.RAISE)
        for line in batch:
            try:
                for s in framer.feed(line, 0):
                    for decoder in (gps, heading):
                        try:
                            decoder.feed([s])
                        except ViperError as exc:
                            errors[type(exc).__name__] += 1
            except Exception as exc:  # what the fuzzing looks for: anything not the project's own
                foreign.append(f"{type(exc).__name__}: {exc}: {line!r}")
        try:
            gps.flush()
        except ViperError as exc:
            errors[type(exc).__name__] += 1
        except Exception as exc:
            foreign.append(f"{type(exc).__name__} at flush: {exc}")
        done += len(batch)
    return done, errors, foreign


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-record", action="store_true", help="do not append to the results file")
    args = ap.parse_args()
    logging.disable(logging.CRITICAL)
    t0 = time.perf_counter()
    n, errors, foreign = fuzz(args.count, args.seed)
    elapsed = time.perf_counter() - t0
    kinds = ", ".join(f"{k} {v}" for k, v in errors.most_common()) or "none"
    result = "pass" if not foreign else f"FAIL: {len(foreign)} foreign exceptions"
    print(f"{n} mutated inputs (seed {args.seed}) in {elapsed:.0f} s: project errors raised: {kinds}; "
          f"foreign exceptions: {len(foreign)} -> {result}")
    for line in foreign[:20]:
        print("  " + line)
    if not args.no_record:
        append_result(OUT,
                      "# NMEA fuzzing\n\n`bench/nmea_fuzz.py`: mutated sentences of the real logs through the "
                      "framer, the GPS decoder and the heading decoder (RAISE policy).\n"
                      "Target: no exception other than the project's own.\n\n"
                      "| date | inputs | seed | ProtocolErrors raised | foreign exceptions | result |\n"
                      "|---|---|---|---|---|---|\n",
                      f"| {datetime.date.today().isoformat()} | {n} | {args.seed} | "
                      f"{sum(errors.values())} | {len(foreign)} | {result} |\n")
    return 0 if not foreign else 1


if __name__ == "__main__":
    sys.exit(main())
