"""Estimates on a tiled skyline database: per estimate, in process and on a 2-worker Dask LocalCluster.

A small tiled database of the jacksboro map (tiles x tiles ordinary builds, cut by
tests/tiled_build.py) is built once into bench/cache/; skylines rendered at a few places are then
located over every tile, one after the other in this process and as one Dask task per tile.
Whether the answers agree is checked, and the machine's load (uptime) is recorded beside the times:
two cores are shared with other work, and a cluster of two processes only pays on an idle machine.

    python bench/estimator_tiled.py [--tiles 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.locating.tile_cache import SearchParams  # noqa: E402
from appliance.locating.tiled_index import open_tiled  # noqa: E402
from appliance.locating.tiled_search import locate_tiled  # noqa: E402
from appliance.skyline import Skyline  # noqa: E402
from appliance.terrain.dem import load_dem  # noqa: E402
from appliance.terrain.horizon import render_skyline  # noqa: E402
from bench.results_file import append_result  # noqa: E402
from tests.tiled_build import build_tiled  # noqa: E402

AREA = (-84.30, 36.55, -84.24, 36.60)
MAX_RANGE_M = 10_000.0
PLACES = [(36.5731, -84.2887), (36.5652, -84.2795), (36.5905, -84.2530)]
PARAMS = SearchParams((0.3, 1.2), 4.0)


def uptime_load() -> str:
    out = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    return out.split("load average:")[-1].split(",")[0].strip() if "load average" in out else "?"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiles", type=int, default=2, help="tiles per side")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    folder = HERE / "cache" / f"tiled_jacksboro_{args.tiles}x{args.tiles}"
    dem = load_dem("jacksboro")
    if not (folder / "index.json").exists():
        build_tiled(dem, folder, AREA, (args.tiles, args.tiles), MAX_RANGE_M)
    index = open_tiled(folder)
    skies = [Skyline(np.arange(360.0), render_skyline(dem, lat, lon, max_range_m=MAX_RANGE_M).elevation_deg
                     + np.random.default_rng(k).normal(0.0, 0.2, 360)) for k, (lat, lon) in enumerate(PLACES)]

    def per_estimate(client: object) -> tuple[float, float, list[dict]]:
        for sky in skies:
            locate_tiled(index, sky, PARAMS, client=client)  # warm: compile, page in
        ts, recs = [], []
        for _ in range(args.repeats):
            for sky in skies:
                t = time.perf_counter()
                res = locate_tiled(index, sky, PARAMS, client=client)
                ts.append(time.perf_counter() - t)
                recs.append(res.to_json(index))
        return float(np.median(ts)), float(np.min(ts)), recs

    load0 = uptime_load()
    serial = per_estimate(None)
    load1 = uptime_load()
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        parallel = per_estimate(client)
    load2 = uptime_load()
    same = all({k: v for k, v in a.items() if k != "elapsed_ms"} == {k: v for k, v in b.items() if k != "elapsed_ms"}
               for a, b in zip(serial[2], parallel[2]))
    res = HERE / "results" / "estimator_tiled.md"
    nodes = sum(t.n_rows * t.n_cols for t in index.tiles)
    n = len(index.tiles)
    rows = [
        f"| {date.today()} | in process, serial | {n} | {nodes} | {serial[0] * 1e3:.0f} ms | {serial[1] * 1e3:.0f} ms "
        f"| - | {load0} -> {load1} |\n",
        f"| {date.today()} | LocalCluster 2 workers x 1 thread | {n} | {nodes} | {parallel[0] * 1e3:.0f} ms "
        f"| {parallel[1] * 1e3:.0f} ms | {'yes' if same else 'NO'} | {load1} -> {load2} |\n",
    ]
    append_result(res, "# Estimates on a tiled database (bench/estimator_tiled.py)\n\n"
                  "| date | case | tiles | nodes | median | best | same answer | load (uptime) |\n"
                  "|---|---|---|---|---|---|---|---|\n", "".join(rows))
    sys.stdout.writelines(rows)
    print(f"cores {len(os.sched_getaffinity(0))}, {len(skies)} skylines x {args.repeats} repeats, compass +-4 deg")
    print("in process, per skyline: " + "; ".join(
        f"{r['status']} {r['rms_residual_deg']:.3f} deg RMS, sigma {r['sigma_deg']}, "
        f"region {r['region']['n_cells']} cells"
        for r in serial[2][: len(skies)]))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
