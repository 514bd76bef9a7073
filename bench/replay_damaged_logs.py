"""Damaged session logs through the replay: does an estimate from what is left ever say "ok" while wrong?

Run: .venv/bin/python bench/replay_damaged_logs.py [--count 60] [--seed 8]
     (appends to bench/results/replay_damaged_logs.md)

The log of ``viper demo --seed 11`` (made once into bench/cache/, with its jacksboro database, as
``bench/input_fuzz.py`` makes it) is cut at a random length (a power loss: 30 % of the inputs) or
mutated (bit flips, runs of random or hostile bytes, insertions, deletions: 70 %).  Each damaged log
is read and replayed as ``viper replay`` does (``read_session``, ``replay_session``).  For every
estimate the status is taken as the field would see it, without the GPS truth
(``estimate_status(db, position, None)``), and the error against the truth in the log.  Target: no
estimate says "ok" farther than two database cells from the truth.
"""

from __future__ import annotations

import argparse
import datetime
import logging
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from appliance.acquisition.replay import read_session, replay_session  # noqa: E402
from appliance.config import EstimatorConfig  # noqa: E402
from appliance.errors import ViperError  # noqa: E402
from appliance.locating.position import estimate_status  # noqa: E402
from appliance.terrain.database import load_database  # noqa: E402
from bench.input_fuzz import _demo_seed, mutate  # noqa: E402
from bench.results_file import append_result  # noqa: E402

OUT = ROOT / "bench" / "results" / "replay_damaged_logs.md"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=60)
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--no-record", action="store_true")
    args = ap.parse_args()
    logging.disable(logging.CRITICAL)
    log_path, db_path = _demo_seed()
    db = load_database(db_path)
    cell_m = max(db.grid.dx_m, db.grid.dy_m)
    data = log_path.read_bytes()
    rng = random.Random(args.seed)
    refused = no_estimate = 0
    rows = []  # (frames, status, error_m)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="viper-damaged-logs-") as tmp:
        path = Path(tmp) / "damaged.mcap"
        for _ in range(args.count):
            path.write_bytes(mutate(data, rng) if rng.random() < 0.7 else data[: rng.randrange(len(data))])
            try:
                session = read_session(path)
                res = replay_session(session, db, EstimatorConfig(), Path(tmp) / "out")
            except ViperError:
                refused += 1
                continue
            if res.position is None or res.error_m is None:
                no_estimate += 1
                continue
            rows.append((len(session.frames), estimate_status(db, res.position, None), res.error_m))
    elapsed = time.perf_counter() - t0
    ok = [r for r in rows if r[1] == "ok"]
    wrong_ok = [r for r in ok if r[2] > 2 * cell_m]
    amb = [r for r in rows if r[1] != "ok"]
    result = "pass" if not wrong_ok else f"FAIL: {len(wrong_ok)} wrong estimates say ok"
    by_frames: dict[int, list[tuple[str, float]]] = {}
    for n, status, err in rows:
        by_frames.setdefault(n, []).append((status, err))
    lines = [f"| {n} | {len(v)} | {sum(s == 'ok' for s, _ in v)} | "
             f"{statistics.median(e for _, e in v):.1f} | {max(e for _, e in v):.1f} |"
             for n, v in sorted(by_frames.items())]
    text = (f"\n## {datetime.date.today().isoformat()}: --count {args.count} --seed {args.seed} ({elapsed:.0f} s)\n\n"
            f"- {args.count} damaged logs: {refused} refused as unreadable, {no_estimate} replayed without an estimate "
            f"(too few valid azimuths), {len(rows)} estimates.\n"
            f"- Of the estimates: {len(ok)} say ok (largest error {max((r[2] for r in ok), default=0):.1f} m), "
            f"{len(amb)} say ambiguous (median error {statistics.median(r[2] for r in amb) if amb else 0:.1f} m).\n"
            f"- Estimates saying ok farther than two cells ({2 * cell_m:.0f} m) from the truth: {len(wrong_ok)}: "
            f"**{result}**.\n\n"
            "| frames read | estimates | ok | median error (m) | largest error (m) |\n|---|---|---|---|---|\n"
            + "\n".join(lines) + "\n")
    print(text)
    if not args.no_record:
        append_result(OUT, "# Damaged session logs through the replay\n\n`bench/replay_damaged_logs.py`: the demo's "
                           "log cut or mutated, then replayed; the status as the field sees it (no truth).\n"
                           "Target: no estimate says ok farther than two cells from the truth.\n", text)
    return 0 if not wrong_ok else 1


if __name__ == "__main__":
    sys.exit(main())
