"""A single photo's narrow view with no compass on the whole SRTM tile N44W072 (1.44M candidates).

Truth: tests/reference_render.py at random points between nodes (camera 1.5 m above the ground),
over a field of view of FOV degrees (default 55) starting at a random true azimuth, Gaussian noise
0.2 deg; the sensor's azimuths are off by a uniform heading error in [-180, 180) deg and the
estimate searches every heading (no compass).  Per seed: wall and CPU time of the estimate
(process CPU, both threads), the nodes rescored on every azimuth, the error to the truth (m), the
region's size and whether it holds the node nearest the truth.

``--kernel-from REV`` runs each seed's estimate also with the second pass's kernel
(search.ssd_for_shifts) of git revision REV, in alternation with the current code, and checks that
both give the same node, heading, region and count of nodes rescored.

    python bench/estimator_narrow.py [--seeds N] [--fov DEG] [--kernel-from REV]
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path
from types import ModuleType

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.estimator import SkylineGrid, estimate  # noqa: E402
from appliance.locating.position import skyline_grid  # noqa: E402
from bench.estimator_speed import tile_database  # noqa: E402
from bench.results_file import append_result  # noqa: E402
from tests.reference_render import reference_skyline  # noqa: E402

# the module whose second pass calls the kernel
rescore_module = importlib.import_module("appliance.estimator.rescore")
NOISE_DEG = 0.2
SIGMA_DEG = (0.3, 0.8)


def search_module_at(rev: str) -> ModuleType:
    """appliance/estimator/search.py as it was at git revision ``rev``, imported on its own."""
    src = subprocess.run(["git", "-C", str(HERE.parent), "show", f"{rev}:appliance/estimator/search.py"],
                         check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="viper-bench-")) / f"search_{rev.replace('/', '_')}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"search_{rev.replace('/', '_')}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def timed(grid: SkylineGrid, az: np.ndarray, el: np.ndarray, kernel: object) -> tuple[object, float, float]:
    """One no-compass estimate with the second pass's kernel ``kernel``: (result, wall s, CPU s)."""
    rescore_module.ssd_for_shifts = kernel  # type: ignore[attr-defined]
    t, c = time.perf_counter(), time.process_time()
    res = estimate(grid, az, el, SIGMA_DEG, None)
    return res, time.perf_counter() - t, time.process_time() - c


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--fov", type=float, default=55.0, help="field of view, deg")
    ap.add_argument("--kernel-from", default=None, metavar="REV")
    args = ap.parse_args()
    loaded = tile_database()
    if loaded is None:
        return 0
    dem, db = loaded
    grid = skyline_grid(db)
    cell = math.sqrt(grid.dx_m * grid.dy_m)
    kernels = {"new": rescore_module.ssd_for_shifts}
    if args.kernel_from:
        kernels = {"old": search_module_at(args.kernel_from).ssd_for_shifts, **kernels}
    n_fov = int(round(args.fov))
    rows, same = [], True
    for seed in range(args.seeds + 1):  # seed 0 warms the kernels and pages the database in
        rng = np.random.default_rng(seed)
        while True:
            r, c = rng.uniform(3, grid.n_rows - 4), rng.uniform(3, grid.n_cols - 4)
            if np.isfinite(db.offset_deg[int(round(r)) * grid.n_cols + int(round(c))]):
                break
        lon, lat = db.grid.xy_to_lonlat(*db.grid.rc_to_xy(r, c))
        true_az = rng.uniform(0.0, 360.0) + np.arange(n_fov, dtype=float)
        el = reference_skyline(dem, float(lat), float(lon), 1.5, azimuths_deg=true_az)
        el = el + rng.normal(0.0, NOISE_DEG, n_fov)
        heading_error = rng.uniform(-180.0, 180.0)
        az = (true_az - heading_error) % 360.0
        order = list(kernels) if seed % 2 else list(kernels)[::-1]
        got = {name: timed(grid, az, el, kernels[name]) for name in order}
        if seed == 0:
            continue
        nearest = int(round(r)) * grid.n_cols + int(round(c))
        res_new = got["new"][0]
        err_m = math.hypot((res_new.row - r) * grid.dy_m, (res_new.col - c) * grid.dx_m)  # type: ignore[attr-defined]
        inside = bool(np.isin(nearest, res_new.region_nodes))  # type: ignore[attr-defined]
        if "old" in got:
            a, b = got["old"][0], res_new
            agree = (a.node == b.node and a.heading_correction_deg == b.heading_correction_deg  # type: ignore[attr-defined]
                     and a.rescored == b.rescored and np.array_equal(a.region_nodes, b.region_nodes))  # type: ignore[attr-defined]
            same = same and agree
        load = os.getloadavg()[0]
        times = " | ".join(f"{got[k][1]:.1f} / {got[k][2]:.1f} s" for k in kernels)
        line = (f"| {date.today()} | {seed} | {args.fov:g} | {times} | {res_new.rescored} | "  # type: ignore[attr-defined]
                f"{err_m:.0f} m ({err_m / cell:.1f} cells) | {res_new.region_nodes.size} | {inside} | "  # type: ignore[attr-defined]
                f"{'same' if 'old' not in got or agree else 'DIFFERENT'} | {load:.1f} |\n")
        print(line, end="", flush=True)
        rows.append((line, got, err_m, inside))
    for name in kernels:
        walls = [g[name][1] for _, g, _, _ in rows]
        cpus = [g[name][2] for _, g, _, _ in rows]
        print(f"{name}: median wall {np.median(walls):.2f} s, median CPU {np.median(cpus):.2f} s, "
              f"total CPU {np.sum(cpus):.1f} s")
    errs = np.array([e for _, _, e, _ in rows])
    print(f"median error {np.median(errs):.0f} m, within 2 cells {np.mean(errs <= 2 * cell):.0%}, "
          f"region holds truth {np.mean([i for *_, i in rows]):.0%}; old and new agree: {same}")
    cols = " | ".join(f"{k} wall / CPU" for k in kernels)
    header = ("# Narrow view, no compass, whole tile (bench/estimator_narrow.py)\n\n"
              "Reference renders at random points of N44W072 (1.44M candidates), noise 0.2 deg, every heading "
              "searched.\n")
    table = (f"\n| date | seed | FOV (deg) | {cols} | rescored | error | region (cells) | truth in region | "
             f"old vs new | load |\n|{'---|' * (9 + len(kernels))}\n")
    append_result(HERE / "results" / "estimator_narrow.md", header, table + "".join(r[0] for r in rows))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
