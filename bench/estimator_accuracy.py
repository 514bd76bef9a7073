"""Accuracy of the position estimator against truth skylines from the dense reference renderer.

Truth: tests/reference_render.py (geodesic rays, quarter-cell steps, exact sphere) at random
points between grid nodes, camera 1.5 m above the ground.  Measured skyline: the truth read by a
heading sensor with a uniform error, Gaussian noise, one contiguous occlusion plus scattered
dropouts.  Figures: error of the estimate in metres and in cells (cell = geometric mean of the
node spacing), and whether the region holds the node nearest the truth.

    python bench/estimator_accuracy.py [--map jacksboro|white-mountains] [--trials N] [--unknown-heading]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.estimator import estimate  # noqa: E402
from appliance.locating.position import skyline_grid  # noqa: E402
from appliance.terrain.database import build_database, load_database  # noqa: E402
from appliance.terrain.dem import load_dem  # noqa: E402
from bench.results_file import append_result  # noqa: E402
from tests.reference_render import reference_skyline  # noqa: E402

SHARED = HERE.parent.parent / "shared" / "data"
MAPS = {
    "jacksboro": ("jacksboro", None),
    # a 0.2 x 0.15 degree window around the Presidential Range, the whole tile around it for the horizon
    "white-mountains": (str(SHARED / "dem_srtm_hgt" / "N44W072.hgt"), (-71.40, 44.20, -71.20, 44.35)),
}


def measured_skyline(truth: np.ndarray, rng: np.random.Generator, noise_deg: float, missing: float,
                     compass_deg: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A sensor's reading of the true skyline (1-degree true azimuths): returns (az, el, correction)."""
    n = truth.size
    az = np.arange(n, dtype=float)
    err = rng.uniform(-compass_deg, compass_deg)
    # the sensor reads azimuth a where the true azimuth is a + err
    el = np.interp((az + err) % 360.0, np.arange(n, dtype=float), truth, period=360.0)
    el = el + rng.normal(0.0, noise_deg, n)
    n_miss = int(round(missing * n))
    block = int(round(0.7 * n_miss))
    start = rng.integers(0, n)
    el[(start + np.arange(block)) % n] = np.nan
    rest = rng.choice(np.nonzero(np.isfinite(el))[0], n_miss - block, replace=False)
    el[rest] = np.nan
    return az, el, err


def map_database(name: str, spacing_m: float | None = None):
    """The map's DEM and its database (at ``spacing_m``, else the map's own), built once into bench/cache."""
    dem_path, bounds = MAPS[name]
    dem = load_dem(dem_path)
    cache = HERE / "cache"
    cache.mkdir(exist_ok=True)
    db_path = cache / f"{name}-{spacing_m or 'native'}.viperdb"
    if not db_path.exists():
        t = time.perf_counter()
        build_database(dem, db_path, search_bounds=bounds, spacing_m=spacing_m, progress=None)
        print(f"database built in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return dem, load_database(db_path, dem)


def between_nodes(db, grid, rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A random point between the nodes of ``grid`` (three nodes from its edges, at a node with a
    skyline): fractional (row, col) and (lat, lon)."""
    while True:
        r = rng.uniform(3, grid.n_rows - 4)
        c = rng.uniform(3, grid.n_cols - 4)
        if np.isfinite(db.offset_deg[int(round(r)) * grid.n_cols + int(round(c))]):
            lon, lat = db.grid.xy_to_lonlat(*db.grid.rc_to_xy(r, c))
            return r, c, float(lat), float(lon)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--map", default="jacksboro", choices=sorted(MAPS))
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--unknown-heading", action="store_true")
    ap.add_argument("--sigma", default="0.3,0.8")
    ap.add_argument("--spacing", type=float, default=None, help="database node spacing (m)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    sigma = tuple(float(v) for v in args.sigma.split(","))
    noise, missing, compass = (0.5, 0.25, 180.0) if args.unknown_heading else (0.2, 0.10, 4.0)
    dem, db = map_database(args.map, args.spacing)
    grid = skyline_grid(db)
    cell = float(np.sqrt(grid.dx_m * grid.dy_m))
    rng = np.random.default_rng(args.seed)
    errors, inside, region_cells, times = [], [], [], []
    for trial in range(args.trials):
        r, c, lat, lon = between_nodes(db, grid, rng)
        truth = reference_skyline(dem, float(lat), float(lon), 1.5)
        az, el, err = measured_skyline(truth, rng, noise, missing, compass)
        res = estimate(grid, az, el, sigma, None if args.unknown_heading else compass)
        d_m = float(np.hypot((res.row - r) * grid.dy_m, (res.col - c) * grid.dx_m))
        nearest = int(round(r)) * grid.n_cols + int(round(c))
        errors.append(d_m)
        inside.append(bool(np.isin(nearest, res.region_nodes)))
        region_cells.append(int(res.region_nodes.size))
        times.append(res.elapsed_s)
        print(f"{trial:3d} error {d_m:8.1f} m ({d_m / cell:5.2f} cells) heading {res.heading_correction_deg:+7.2f} "
              f"(true {err:+7.2f}) region {res.region_nodes.size:6d} cells truth in region {inside[-1]} "
              f"rms {res.rms_residual_deg:.2f}", file=sys.stderr)
    e = np.array(errors) / cell
    summary = {
        "map": args.map, "trials": args.trials, "unknown_heading": args.unknown_heading,
        "noise_deg": noise, "missing_fraction": missing,
        "compass_error_deg": None if args.unknown_heading else compass,
        "sigma_deg": list(sigma), "cell_m": round(cell, 1),
        "candidates": int(np.isfinite(grid.offset_deg).sum()),
        "median_error_m": round(float(np.median(errors)), 1), "median_error_cells": round(float(np.median(e)), 2),
        "within_1_cell": round(float(np.mean(e <= 1.0)), 3), "within_2_cells": round(float(np.mean(e <= 2.0)), 3),
        "region_holds_truth": round(float(np.mean(inside)), 3),
        "median_region_cells": int(np.median(region_cells)),
        "median_estimate_ms": round(1e3 * float(np.median(times)), 1),
    }
    print(json.dumps(summary))
    out = HERE / "results" / "estimator_accuracy.md"
    out.parent.mkdir(exist_ok=True)
    label = args.map if args.spacing is None else f"{args.map}, nodes every {args.spacing:g} m"
    line = (f"| {date.today()} | {label} | {'none' if args.unknown_heading else '±4°'} | {noise} | "
            f"{int(missing * 100)}% | {sigma[0]}–{sigma[1]} | {args.trials} | {summary['median_error_m']} m "
            f"({summary['median_error_cells']}) | {100 * summary['within_2_cells']:.0f}% | "
            f"{100 * summary['region_holds_truth']:.0f}% | {summary['median_region_cells']} | "
            f"{summary['median_estimate_ms']} ms | {platform.machine()} |\n")
    append_result(
        out,
        "# Estimator accuracy (bench/estimator_accuracy.py)\n\n"
        "Truth from the dense reference ray march at random points between nodes, camera 1.5 m.\n"
        "Targets: with compass, median <= 1 cell, >= 90% within 2 cells, region holds truth >= 90%;\n"
        "no compass: median <= 2 cells, >= 80% within 2 cells.\n\n"
        "| date | map | compass | noise (deg) | missing | sigma (deg) | trials | median error (cells) | "
        "within 2 cells | region holds truth | median region (cells) | median time | machine |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        line,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
