"""Speed of the estimator on the SRTM tile N44W072 (1201 x 1201 nodes, 360 azimuths).

- 172k candidates (the size of Viper's Pittsburgh grid: the tile's first 144 rows x 1201 columns)
  x 360 azimuths x 9 headings (compass +-4 deg), refinement included: target at most 20 ms per skyline;
- the same with no compass (every heading): target at most 1 s;
- the whole tile (1.44M candidates) at +-4 deg: target at most 40 ms; with no compass at most 0.5 s;
- peak memory beside the database's size.

The database is built once into bench/cache/.

    python bench/estimator_speed.py [--repeats N]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import resource
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.estimator import SkylineGrid, estimate  # noqa: E402
from appliance.locating.position import skyline_grid  # noqa: E402
from appliance.terrain.database import SkylineDatabase, build_database, load_database  # noqa: E402
from appliance.terrain.dem import Dem, load_dem  # noqa: E402
from bench.results_file import append_result  # noqa: E402

TILE = HERE.parent.parent / "shared" / "data" / "dem_srtm_hgt" / "N44W072.hgt"


TILE_DB = HERE / "cache" / "n44w072-full.viperdb"


def tile_database() -> tuple[Dem, SkylineDatabase] | None:
    """The tile's DEM and its whole database, built once into bench/cache/; None (said on stdout) where
    the DEM is absent."""
    if not TILE.exists():
        print(f"{TILE} absent: nothing to measure")
        return None
    dem = load_dem(TILE)
    if not TILE_DB.exists():
        TILE_DB.parent.mkdir(exist_ok=True)
        t = time.perf_counter()
        build_database(dem, TILE_DB, progress=None)
        print(f"built {TILE_DB.name} in {time.perf_counter() - t:.0f} s")
    return dem, load_database(TILE_DB, dem)


def bench_skyline(db: SkylineDatabase) -> tuple[np.ndarray, np.ndarray]:
    """The measured skyline every case is timed on: a node's own, turned 2 azimuths, 0.2 deg of noise,
    a tenth of the azimuths missing."""
    rng = np.random.default_rng(3)
    node = 70 * db.grid.n_cols + 600
    el = np.roll(db.skylines_deg(node), -2) + rng.normal(0, 0.2, 360)
    el[rng.choice(360, 36, replace=False)] = np.nan
    return np.arange(360.0), el


def cpu_s() -> float:
    """CPU time of the whole process (every thread), s."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(grid: SkylineGrid, az: np.ndarray, el: np.ndarray, tol: float | None,
          repeats: int) -> tuple[float, float, float]:
    """Median and least wall time of one estimate (s), and its median CPU time over every thread."""
    estimate(grid, az, el, (0.3, 0.8), tol)  # warm: compile and page in
    ts, cs = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), cpu_s()
        estimate(grid, az, el, (0.3, 0.8), tol)
        ts.append(time.perf_counter() - t)
        cs.append(cpu_s() - c)
    return float(np.median(ts)), float(np.min(ts)), float(np.median(cs))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--busy", action="store_true", help="run a spinning process beside the estimates")
    args = ap.parse_args()
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.busy else None
    try:
        return run(args)
    finally:
        if busy is not None:
            busy.kill()


def run(args: argparse.Namespace) -> int:
    loaded = tile_database()
    if loaded is None:
        return 0
    _, db = loaded
    full = skyline_grid(db)
    n_sub = 144 * full.n_cols
    # the tile's first 144 rows, with everything the estimator uses (parallax, exact renders, first pass)
    t = full.terrain
    assert t is not None and full.first_pass is not None and full.distance_codes is not None
    sub = dataclasses.replace(
        full, codes=full.codes[:n_sub], offset_deg=full.offset_deg[:n_sub], step_deg=full.step_deg[:n_sub],
        n_rows=144, distance_codes=full.distance_codes[:n_sub],
        ground_m=None if full.ground_m is None else full.ground_m[:n_sub],
        terrain=dataclasses.replace(t, convergence_deg=np.asarray(t.convergence_deg)[:n_sub]),
        first_pass=tuple(a[:n_sub] for a in full.first_pass))
    az, el = bench_skyline(db)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows = []
    for label, grid, tol, target in (
        ("172k candidates, compass +-4 deg (9 headings)", sub, 4.0, 0.02),
        ("172k candidates, no compass (360 headings)", sub, None, 1.0),
        ("1.44M candidates (whole tile), compass +-4 deg", full, 4.0, 0.04),
        ("1.44M candidates (whole tile), no compass", full, None, 0.5),
    ):
        med, best, cpu = timed(grid, az, el, tol, args.repeats)
        print(f"{label}: median {med * 1e3:.0f} ms, best {best * 1e3:.0f} ms, CPU {cpu * 1e3:.0f} ms"
              f" (target {target * 1e3:.0f} ms)")
        rows.append(f"| {date.today()} | {label} | {med * 1e3:.0f} ms | {best * 1e3:.0f} ms | {target * 1e3:.0f} ms |"
                    f" {os.cpu_count()} cores, {'beside a busy process, ' if args.busy else ''}"
                    f"load {os.getloadavg()[0]:.1f}, CPU {cpu * 1e3:.0f} ms (median, every thread) |\n")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    db_mb = TILE_DB.stat().st_size / 2**20
    print(f"peak memory {peak:.0f} MB (before the runs {rss0:.0f} MB); database {db_mb:.0f} MB")
    rows.append(f"| {date.today()} | peak memory | {peak:.0f} MB | | database {db_mb:.0f} MB |"
                f" {platform.machine()} |\n")
    res = HERE / "results" / "estimator_speed.md"
    append_result(res, "# Estimator speed (bench/estimator_speed.py)\n\n"
                  "| date | case | median | best | target | machine |\n|---|---|---|---|---|---|\n", "".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
