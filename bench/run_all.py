"""Run the quick benchmarks one after another (``make bench``); each records its own results in
bench/results/.  The long campaigns are left out: the 100-seed session chain, the world-gap
cameras, the valley positions and the full-count fuzzers run by hand (README, Benchmarks).

    .venv/bin/python bench/run_all.py            # all quick benchmarks
    .venv/bin/python bench/run_all.py --list     # what would run
    .venv/bin/python bench/run_all.py terrain_speed drivers_gps   # a selection
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent

#: Benchmark script and its arguments, quick settings (minutes at most each on two cores).
QUICK: dict[str, list[str]] = {
    "terrain_speed": [],
    "terrain_accuracy": [],
    "estimator_speed": [],
    "estimator_accuracy": ["--trials", "20"],
    "estimator_fusion": ["--trials", "10"],
    "estimator_tiled": ["--repeats", "2"],
    "vision_skyline": [],
    "drivers_gps": [],
    "logbook_write": [],
    "session_demo": [],
    "nmea_fuzz": ["--count", "100000"],
    "input_fuzz": ["--count", "2000", "--index-count", "500", "--image-count", "100", "--log-count", "100",
                   "--replay-count", "5"],
    "replay_damaged_logs": ["--count", "20"],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help=f"benchmarks to run (default all: {', '.join(QUICK)})")
    ap.add_argument("--list", action="store_true", help="print the commands and exit")
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in QUICK]
    if unknown:
        print(f"run_all: unknown benchmark {unknown[0]!r} (known: {', '.join(QUICK)})", file=sys.stderr)
        return 2
    failed = []
    for name in args.names or list(QUICK):
        cmd = [sys.executable, str(BENCH / f"{name}.py"), *QUICK[name]]
        print("$ " + " ".join([f"bench/{name}.py", *QUICK[name]]), flush=True)
        if args.list:
            continue
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, cwd=BENCH.parent, check=False).returncode
        print(f"# {name}: exit {rc} in {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"run_all: {len(failed)} benchmark(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
