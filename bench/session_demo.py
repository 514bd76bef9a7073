"""The demo's whole simulated session: wall-clock time after setup, and the estimate's error.

Runs ``viper demo``'s session (twins at time rate 20, 640x480 frames, the full jacksboro database)
for a few seeds; writes bench/results/session_demo.md.  Target: under two minutes after setup.
"""

from __future__ import annotations

import datetime as dt
import tempfile
import time
from pathlib import Path

import numpy as np

from appliance.atomic import write_text_atomic
from appliance.cli.demo import demo_config
from appliance.locating.position import truth_error_m
from appliance.sim.demo import demo_database
from appliance.sim.field_session import run_field_session
from appliance.terrain.dem import load_dem

SEEDS = (1, 2, 3, 4, 5)
TARGET_S = 120.0


def main() -> None:
    out = Path(tempfile.mkdtemp(prefix="viper-bench-"))
    t0 = time.monotonic()
    dem = load_dem("jacksboro")
    (Path(tempfile.gettempdir()) / "viper-bench-db").mkdir(exist_ok=True)
    db = demo_database(dem, Path(tempfile.gettempdir()) / "viper-bench-db")
    setup_s = time.monotonic() - t0
    rows = []
    for seed in SEEDS:
        t = time.monotonic()
        r, sim_truth = run_field_session(demo_config(out, 20.0), out, seed=seed, dem=dem, db=db)
        wall = time.monotonic() - t
        lat, lon = sim_truth.lat_deg, sim_truth.lon_deg
        true_err = None if r.estimate is None else truth_error_m(db, r.estimate, (lat, lon))
        rows.append((seed, wall, r.error_m, true_err, r.status.value))
        print(f"seed {seed}: {wall:.1f} s, error vs GPS truth {r.error_m} m, vs true position {true_err} m")
    walls = [w for _, w, *_ in rows]
    errs = [e for *_, e, _s in rows if e is not None]
    lines = [
        "# session_demo",
        "",
        f"Date {dt.date.today()}, machine: 2 cores.  Database setup (cached or built): {setup_s:.0f} s.",
        "",
        "| seed | session wall time (s) | error vs GPS truth (m) | error vs true position (m) | status |",
        "|---|---|---|---|---|",
        *[f"| {s} | {w:.1f} | {'' if g is None else f'{g:.1f}'} | {'' if e is None else f'{e:.1f}'} | {st} |"
          for s, w, g, e, st in rows],
        "",
        f"Max session time {max(walls):.1f} s (target < {TARGET_S:.0f} s after setup); "
        f"median error vs true position {np.median(errs):.1f} m over {len(errs)} sessions.",
    ]
    Path("bench/results").mkdir(parents=True, exist_ok=True)
    write_text_atomic("bench/results/session_demo.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
