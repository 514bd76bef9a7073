"""Estimates across the 7 deg E seam of the SRTM mosaic N43E006 + N43E007, over the whole mosaic.

The tiled database of the whole mosaic (bench/tiled_build.py's map, tiles and azimuths, on a
2-worker LocalCluster) is built once into bench/cache/, keyed by its parameters.  Skylines are
rendered by the production renderer (appliance.terrain.horizon.render_skyline) at the database's
camera height, azimuths and maximum range, at random positions less than 5 km east or west of
7 deg E, on land (sea and voids skipped and counted).  Each is read by a compass with a uniform
error within +-4 deg and Gaussian noise of 0.2 deg (bench/estimator_accuracy.py's sensor, no
dropouts), and located over every tile (no search box) with the +-4 deg compass window: first in
this process, each locate call timed after one warm-up call, then on a LocalCluster of 2 workers x
1 thread, whose answers (best lat/lon, status, region) must be the in-process ones.

The horizon reach (60 km) is longer than half the mosaic's north-south extent (111 km), so no
position can lie a reach away from the northern and southern edges; positions keep LAT_MARGIN_M
from them instead and see, like the database's nodes, the terrain the map holds.  East and west, the
seam is 80 km from either edge: more than a reach.

    python bench/estimator_seam.py [--n 20] [--seed 17] [--profile 3]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.atomic import write_text_atomic  # noqa: E402
from appliance.bodies import body_named, geodesic_distance_m  # noqa: E402
from appliance.config import EstimatorConfig  # noqa: E402
from appliance.locating.position import Position  # noqa: E402
from appliance.locating.tile_cache import SearchParams  # noqa: E402
from appliance.locating.tile_combination import best_tile  # noqa: E402
from appliance.locating.tile_search import search_tile, tile_floor  # noqa: E402
from appliance.locating.tiled_index import TiledIndex, open_tiled  # noqa: E402
from appliance.locating.tiled_search import _run, locate_tiled  # noqa: E402
from appliance.skyline import Skyline  # noqa: E402
from appliance.terrain.dem import Dem  # noqa: E402
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M, render_skyline  # noqa: E402
from appliance.terrain.mosaic import open_map  # noqa: E402
from bench.tiled_build import TILES  # noqa: E402

SEAM_LON = 7.0
SEAM_HALF_WIDTH_M = 5000.0
LAT_MARGIN_M = 3000.0
N_AZIMUTHS = 360
TILE_NODES = (600, 600)
COMPASS_DEG = 4.0
NOISE_DEG = 0.2
TARGET_WITHIN = 0.95
TARGET_SECONDS = 1.0
RESULTS = HERE / "results" / "estimator_seam.md"


def compass_reading(truth: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """The sensor of bench/estimator_accuracy.py without dropouts: the sensor reads azimuth a where
    the true azimuth is a + err (err uniform within +-COMPASS_DEG), plus Gaussian noise."""
    n = truth.size
    az = np.arange(n) * (360.0 / n)
    err = float(rng.uniform(-COMPASS_DEG, COMPASS_DEG))
    el = np.interp((az + err) % 360.0, az, truth, period=360.0) + rng.normal(0.0, NOISE_DEG, n)
    return az, el, err


def uptime() -> str:
    out = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    return out.split("load average:")[-1].strip() if "load average" in out else "?"


def cache_folder() -> Path:
    """The tiled database's folder under bench/cache/, named after what it depends on."""
    key = json.dumps({"tiles": [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in TILES],
                      "n_azimuths": N_AZIMUTHS, "tile_nodes": TILE_NODES, "max_range_m": DEFAULT_MAX_RANGE_M,
                      "height_m": DEFAULT_HEIGHT_M}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return HERE / "cache" / f"seam_N43E006+N43E007_az{N_AZIMUTHS}_t{TILE_NODES[0]}x{TILE_NODES[1]}_{digest}"


def build_or_reuse(folder: Path) -> float:
    """Build the tiled database in ``folder`` unless it is complete there (an interrupted build is
    completed: build_tiled keeps the tiles already built); the build's seconds (0 if reused)."""
    from appliance.errors import DatabaseError

    try:
        open_tiled(folder)
        return 0.0
    except DatabaseError:
        pass
    from distributed import Client, LocalCluster

    from appliance.terrain.tiled import build_tiled

    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=50) as cluster, Client(cluster) as client:
        source = open_map(TILES, folder / "mosaic.vrt")
        build_tiled(source, folder, n_azimuths=N_AZIMUTHS, tile_nodes=TILE_NODES, client=client)
    return time.perf_counter() - t0


def draw_positions(dem: Dem, n: int, rng: np.random.Generator) -> tuple[list[tuple[float, float]], int, int]:
    """``n`` positions within SEAM_HALF_WIDTH_M (east-west) of the seam, on land; draws and skips."""
    radius = body_named(dem.body.name.value).radius_m
    lat_lo, lat_hi = 43.0 + math.degrees(LAT_MARGIN_M / radius), 44.0 - math.degrees(LAT_MARGIN_M / radius)
    out: list[tuple[float, float]] = []
    drawn = skipped = 0
    while len(out) < n:
        drawn += 1
        lat = float(rng.uniform(lat_lo, lat_hi))
        dlon = math.degrees(SEAM_HALF_WIDTH_M / (radius * math.cos(math.radians(lat))))
        lon = float(rng.uniform(SEAM_LON - dlon, SEAM_LON + dlon))
        z = float(dem.sample_lonlat(np.array([lon]), np.array([lat]))[0])
        if not (np.isfinite(z) and z > 0.0):
            skipped += 1
            continue
        out.append((lat, lon))
    return out, drawn, skipped


def answer(pos: Position, index: TiledIndex, truth: tuple[float, float]) -> dict:
    """What must not change between the two runs: best position, status and region."""
    est = pos.tiled
    assert est is not None
    return {"lat": est.lat, "lon": est.lon, "tile": est.tile, "status": est.status(index, truth),
            "ambiguous": est.ambiguous, "log_lower": est.log_lower, "log_upper": est.log_upper,
            "region": sorted((c.tile, c.node) for c in est.region)}


def run(index: TiledIndex, skies: list[Skyline], truths: list[tuple[float, float]], params: SearchParams,
        client: Any) -> tuple[list[float], list[dict], list[Position]]:
    locate_tiled(index, skies[0], params, client=client)  # warm-up: page in, compile
    times, answers, ests = [], [], []
    for sky, truth in zip(skies, truths):
        t = time.perf_counter()
        est = locate_tiled(index, sky, params, client=client)
        times.append(time.perf_counter() - t)
        answers.append(answer(est, index, truth))
        ests.append(est)
    return times, answers, ests


def profile(index: TiledIndex, skies: list[Skyline], params: SearchParams) -> dict[str, float]:
    """Where an in-process estimate's time goes: locate_tiled's rounds, run over the tiles as the
    search runs them (tiled_search._run: side by side on a thread per core), medians; the floors
    make each tile's first pass, which the later rounds reuse."""
    from appliance.terrain.database import load_database

    rows: dict[str, list[float]] = {"load": [], "floor": [], "grid": [], "refine": [], "combine": [],
                                    "n_refined": []}
    for sky in skies:
        t = time.perf_counter()
        for tile in index.tiles:
            load_database(index.path(tile))
        rows["load"].append(time.perf_counter() - t)
        t = time.perf_counter()
        floor = max(_run(index, tile_floor, index.tiles, None, sky, params))
        rows["floor"].append(time.perf_counter() - t)
        t = time.perf_counter()
        first = _run(index, search_tile, index.tiles, None, sky, params, refine=False, rescore_floor=floor,
                     region=False)
        rows["grid"].append(time.perf_counter() - t)
        t = time.perf_counter()
        best = best_tile(first)
        rows["combine"].append(time.perf_counter() - t)
        t = time.perf_counter()
        _run(index, search_tile, [t for t in index.tiles if t.file == best], None, sky, params, refine=True,
             rescore_floor=floor)
        rows["refine"].append(time.perf_counter() - t)
        rows["n_refined"].append(1)
    return {k: float(np.median(v)) for k, v in rows.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=20, help="positions")
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--profile", type=int, default=3, help="skylines to profile tile by tile (0: none)")
    args = ap.parse_args()
    folder = cache_folder()
    build_s = build_or_reuse(folder)
    print(f"database {folder.name}: " + (f"built in {build_s:.0f} s" if build_s else "reused"), flush=True)
    index = open_tiled(folder)
    lattice = index.raw["lattice"]
    dx, dy = float(lattice["dx_m"]), float(lattice["dy_m"])
    cell = math.sqrt(dx * dy)
    dem = open_map(TILES, folder / "mosaic.vrt").load()
    rng = np.random.default_rng(args.seed)
    truths, drawn, skipped = draw_positions(dem, args.n, rng)
    az = np.arange(index.n_azimuths) * (360.0 / index.n_azimuths)
    skies: list[Skyline] = []
    offsets = []
    for lat, lon in truths:
        truth = render_skyline(dem, lat, lon, height_m=index.height_m, azimuths_deg=az,
                               max_range_m=index.max_range_m).elevation_deg
        a, el, err = compass_reading(np.asarray(truth), rng)
        skies.append(Skyline(a, el))
        offsets.append(err)
    print(f"{len(truths)} positions ({drawn} drawn, {skipped} in the sea or voids), skylines rendered", flush=True)
    cfg = EstimatorConfig()
    params = SearchParams(cfg.sigma_deg, COMPASS_DEG, occlusion_weight=cfg.occlusion_weight,
                          map_sigma_m=cfg.map_vertical_sigma_m)
    load_before = uptime()  # after the build and the renders: the load the estimates start under

    t_serial, a_serial, e_serial = run(index, skies, truths, params, None)
    body = body_named(index.body)
    errors = np.array([geodesic_distance_m(e.lat, e.lon, t[0], t[1], body) for e, t in zip(e_serial, truths)])
    for k, (e, t, err, sec) in enumerate(zip(e_serial, truths, errors, t_serial)):
        side = "E" if t[1] >= SEAM_LON else "W"
        print(f"{k:2d} truth {t[0]:.5f},{t[1]:.5f} ({side}) -> {e.lat:.5f},{e.lon:.5f} in {e.tiled.tile}: "
              f"{err:7.1f} m ({err / cell:5.2f} cells), {a_serial[k]['status']}, region {len(e.tiled.region)} cells, "
              f"heading {e.heading_correction_deg:+.2f} (true {offsets[k]:+.2f}), {sec:.2f} s", flush=True)
    load_mid = uptime()
    prof = profile(index, skies[: args.profile], params) if args.profile else {}
    if prof:
        print("profile (median s): " + ", ".join(f"{k} {v:.3f}" for k, v in prof.items()), flush=True)

    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=50) as cluster, Client(cluster) as client:
        t_dask, a_dask, _ = run(index, skies, truths, params, client)
    load_after = uptime()
    differ = [k for k, (a, b) in enumerate(zip(a_serial, a_dask)) if a != b]
    same = not differ

    cells = errors / cell
    within = float(np.mean(cells <= 2.0))
    within_max_axis = float(np.mean(errors <= 2.0 * max(dx, dy)))
    ok = sum(1 for a in a_serial if a["status"] == "ok")
    ts = np.array(t_serial)
    td = np.array(t_dask)
    prof_cell = (f"mapping {prof['load']:.2f} / floors {prof['floor']:.2f} / grid {prof['grid']:.2f} / combination "
                 f"{prof['combine']:.2f} / refinement {prof['refine']:.2f} s ({prof['n_refined']:.0f} tiles)"
                 if prof else "-")
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    row = (f"| {stamp} | {len(truths)} ({drawn} drawn, {skipped} sea/void) | {100 * within:.0f}% "
           f"({100 * within_max_axis:.0f}%) | {ok}/{len(truths)} | {np.median(errors):.0f} m ({np.median(cells):.2f}) "
           f"| {errors.max():.0f} m ({cells.max():.2f}) | {np.median(ts):.2f} / {np.percentile(ts, 90):.2f} / "
           f"{ts.max():.2f} s | {np.median(td):.2f} / {td.max():.2f} s | {'yes' if same else 'NO: ' + str(differ)} "
           f"| {prof_cell} | {load_before} -> {load_mid} -> {load_after} |")
    header = (
        "# Estimates across the seam (bench/estimator_seam.py)\n\n"
        "Issue 17's benchmark.  Map: SRTM N43E006 + N43E007 as one VRT mosaic, tiled database of the whole "
        f"mosaic ({lattice['n_rows']} x {lattice['n_cols']} nodes, {dx:.1f} x {dy:.1f} m, {len(index.tiles)} tiles "
        f"of {TILE_NODES[0]} x {TILE_NODES[1]}, {index.n_azimuths} azimuths, camera {index.height_m:g} m, range "
        f"{index.max_range_m / 1000:.0f} km).  Skylines from render_skyline at random land positions within "
        f"{SEAM_HALF_WIDTH_M / 1000:.0f} km (east-west) of 7 deg E and {LAT_MARGIN_M / 1000:.0f} km or more from "
        f"the 43 and 44 deg N edges; compass error uniform within +-{COMPASS_DEG:g} deg, noise {NOISE_DEG} deg; "
        f"search over every tile (no box), compass window +-{COMPASS_DEG:g} deg, sigma {cfg.sigma_deg}, occlusion "
        f"weight {cfg.occlusion_weight}.  Cell = geometric mean of the spacing ({cell:.1f} m); in brackets, "
        f"within 2 x the larger spacing ({2 * max(dx, dy):.0f} m).  Times per locate call after one warm-up.\n"
        "Targets: >= 95% within 2 cells; <= 1 s per estimate in process; the same answer on Dask.\n\n"
        "| date | positions | within 2 cells | status ok | median error (cells) | max error (cells) | in process "
        "median / p90 / max | LocalCluster 2x1 median / max | same answer | "
        "in-process profile, medians: mapping every tile (checksums verified) / floors (every tile's best "
        "first-pass bound) / grid pass on every tile / combination / refinement (tiles refined) | "
        "load (uptime 1/5/15 min: before -> "
        "after in-process -> after Dask) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = RESULTS.read_text().split("\n") if RESULTS.exists() else header.split("\n")
    last = max(k for k, line in enumerate(lines) if line.startswith("|"))
    write_text_atomic(RESULTS, "\n".join(lines[: last + 1] + [row] + lines[last + 1:]))
    print(row)
    print(f"targets: within 2 cells {100 * within:.0f}% (>= {100 * TARGET_WITHIN:.0f}%: "
          f"{'met' if within >= TARGET_WITHIN else 'missed'}); in process {np.median(ts):.2f} s median, "
          f"{ts.max():.2f} s max (<= {TARGET_SECONDS:g} s: {'met' if ts.max() <= TARGET_SECONDS else 'missed'}); "
          f"same answer on Dask: {'met' if same else 'missed'}")
    print(f"wrote {RESULTS}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
