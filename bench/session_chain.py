"""The demo's field-session chain over many seeds, without waiting in simulated time.

For each seed, as ``viper demo`` draws it (``simulated_config``): a random position on the
jacksboro map away from its edges, a random platform heading and tripod tilt.  Then the chain the
session runs, on the same parts: the camera twin's photo-like frames (``render_photo_from``) at
the capture ring's stage angles, tagged with a compass heading off by up to +-3 deg and with the
tilt left after levelling (up to +-0.3 deg); the panorama stitched by the session's
``stitch_frames``; the skyline found by ``detect_skyline``; the estimate on the demo's database
with the session's estimator settings.  The serial protocols and the simulated clock are left out:
they do not change what the estimator sees.

Targets (issue: confidence): >= 98 % within two cells; of those, >= 95 % say ok; no wrong answer
says ok; the truth inside the 95 % region in 95-99 % of cases and inside the 95 % covariance ellipse
in 90-99 %.

    python bench/session_chain.py [--seeds 100] [--first 1] [--skylines DIR [--skylines-only]]

With --skylines the detected skylines are kept (and read back on later runs), so the estimator
alone can be rerun over the same seeds in seconds.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.acquisition.onboard import stitch_frames  # noqa: E402
from appliance.acquisition.platform import Frame  # noqa: E402
from appliance.acquisition.procedures import TaggedFrame, capture_angles  # noqa: E402
from appliance.atomic import write_text_atomic  # noqa: E402
from appliance.config import EstimatorConfig, SessionConfig  # noqa: E402
from appliance.locating.position import fix_status, locate, skyline_grid, truth_in_ellipse, truth_in_region  # noqa: E402
from appliance.sim.demo import demo_database  # noqa: E402
from appliance.sim.field_session import random_position  # noqa: E402
from appliance.skyline import Skyline, format_skyline_csv, parse_skyline_csv  # noqa: E402
from appliance.terrain.dem import load_dem  # noqa: E402
from appliance.terrain.horizon import render_skyline  # noqa: E402
from appliance.vision.camera import CameraPose  # noqa: E402
from appliance.vision.intrinsics import CameraIntrinsics  # noqa: E402
from appliance.vision.skyline_detect import detect_skyline  # noqa: E402
from appliance.vision.synth import render_photo_from  # noqa: E402
from bench.results_file import append_result  # noqa: E402

#: The world's skyline is rendered once per seed at this azimuth step and interpolated.
WORLD_STEP_DEG = 0.2


def world_skyline_fn(dem, lat: float, lon: float, height_m: float):
    az = np.arange(0.0, 360.0, WORLD_STEP_DEG)
    h = render_skyline(dem, lat, lon, height_m=height_m, azimuths_deg=az)
    el, dist = h.elevation_deg, h.distance_m

    def fn(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
        return np.interp(a, az, el, period=360.0), np.interp(a, az, dist, period=360.0)

    return fn


def session_skyline(seed: int, dem, db, intr: CameraIntrinsics, ses: SessionConfig,
                    cache: Path | None = None) -> tuple[float, float, Skyline]:
    """The true (lat, lon) of ``seed`` and the skyline its session detects; with ``cache``, kept
    there as ``seed_N.csv`` (the truth in its first line's comment) and read back on the next run."""
    path = None if cache is None else cache / f"seed_{seed}.csv"
    if path is not None and path.exists():
        head, _, body = path.read_text().partition("\n")
        lat, lon = (float(v) for v in head.lstrip("# ").split(","))
        return lat, lon, parse_skyline_csv(body, str(path))
    rng = np.random.default_rng(seed)
    lat, lon = random_position(dem, db, rng)
    heading = float(rng.uniform(0.0, 360.0))
    compass_error = float(rng.uniform(-3.0, 3.0))
    pitch, roll = (float(v) for v in rng.uniform(-0.3, 0.3, 2))
    fn = world_skyline_fn(dem, lat, lon, 1.5)
    frames = []
    for i, stage in enumerate(capture_angles(intr.hfov_deg, ses.capture_overlap)):
        true_yaw = (heading + stage) % 360.0
        img = render_photo_from(fn, CameraPose(true_yaw, pitch, roll), intr, rng, scene_seed=seed)
        frame = Frame(i, img)
        frames.append(TaggedFrame(i, frame, float(stage), (true_yaw + compass_error) % 360.0, roll, pitch))
    sky = detect_skyline(stitch_frames(frames, intr))
    if path is not None:
        write_text_atomic(path, f"# {lat!r},{lon!r}\n" + format_skyline_csv(sky))
    return lat, lon, sky


def one_session(seed: int, dem, db, grid, intr: CameraIntrinsics, est: EstimatorConfig, ses: SessionConfig,
                cache: Path | None = None):
    lat, lon, sky = session_skyline(seed, dem, db, intr, ses, cache)
    # as the session's onboard estimate does (acquisition/onboard.locate_skyline)
    pos = locate(db, sky, est.sigma_deg, est.heading_tolerance_deg, grid=grid, occlusion_weight=est.occlusion_weight,
                 map_sigma_m=est.map_vertical_sigma_m, sigma_floor_deg=est.sigma_floor_deg)
    _, _, err = dem.geod.inv(lon, lat, pos.lon, pos.lat)
    inside = truth_in_region(db, pos, (lat, lon)), truth_in_ellipse(db, pos, (lat, lon))
    return float(err), pos, inside, float(np.isfinite(sky.elevation_deg).mean())


_STATE: dict = {}


def _setup() -> None:
    dem = load_dem("jacksboro")
    cache = Path(tempfile.gettempdir()) / "viper-bench-db"
    cache.mkdir(exist_ok=True)
    db = demo_database(dem, cache)
    _STATE.update(dem=dem, db=db, grid=skyline_grid(db), intr=CameraIntrinsics.from_fov(640, 480, 60.0),
                  est=EstimatorConfig(), ses=SessionConfig(), cell_m=float(np.sqrt(db.grid.dx_m * db.grid.dy_m)))


def _worker_setup(cache: Path | None, only: bool, threads: int) -> None:
    """A spawned worker's state: the database the parent built (read from its cache), and its share
    of the cores for numba's parallel kernels."""
    import numba

    numba.set_num_threads(threads)
    _STATE.update(cache=cache, only=only)
    _setup()


def _run(seed: int) -> tuple:
    st = _STATE
    if st.get("only"):
        session_skyline(seed, st["dem"], st["db"], st["intr"], st["ses"], st["cache"])
        print(f"seed {seed}: skyline kept", flush=True)
        return None
    err, pos, inside, seen = one_session(seed, st["dem"], st["db"], st["grid"], st["intr"], st["est"], st["ses"],
                                         st["cache"])
    r = pos.result
    cells = err / st["cell_m"]
    in_region, in_ellipse = inside
    print(f"seed {seed}: {err:7.1f} m ({cells:5.2f} cells), region {r.region_nodes.size} cells, truth "
          f"{'inside' if in_region else 'OUTSIDE'} (ellipse {'inside' if in_ellipse else 'OUTSIDE'}), "
          f"{fix_status(pos)}, sigma {r.sigma_deg[0]:.3f}-{r.sigma_deg[1]:.3f} deg, "
          f"{r.independent_azimuths:.0f} independent azimuths, skyline {seen:.0%}, "
          f"estimate {r.elapsed_s * 1e3:.0f} ms", flush=True)
    return seed, cells, in_region, r.region_nodes.size, r.ambiguous, r.elapsed_s, in_ellipse


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (each loads the database)")
    ap.add_argument("--skylines", type=Path, help="keep each seed's detected skyline in this folder, and "
                    "read it from there on later runs (the estimator alone is then rerun)")
    ap.add_argument("--skylines-only", action="store_true", help="only detect and keep the skylines")
    args = ap.parse_args()
    if args.skylines is not None:
        args.skylines.mkdir(parents=True, exist_ok=True)
    _STATE.update(cache=args.skylines, only=args.skylines_only)
    _setup()  # builds the database once, before any worker starts
    cell_m = _STATE["cell_m"]
    seeds = list(range(args.first, args.first + args.seeds))
    t0 = time.monotonic()
    if args.jobs > 1:
        import multiprocessing

        # spawned, not forked: the parent has run numba's OpenMP kernels (building the database), and
        # GNU OpenMP kills a child forked after that; each worker loads the database the parent built
        ctx = multiprocessing.get_context("spawn")
        threads = max(1, (os.cpu_count() or 1) // args.jobs)
        setup = (args.skylines, args.skylines_only, threads)
        with ctx.Pool(args.jobs, initializer=_worker_setup, initargs=setup) as pool:
            rows = sorted(pool.map(_run, seeds, chunksize=1))
    else:
        rows = [_run(seed) for seed in seeds]
    wall = time.monotonic() - t0
    if args.skylines_only:
        return 0
    cells = np.array([x[1] for x in rows])
    inside = np.array([x[2] for x in rows])
    region = np.array([x[3] for x in rows])
    amb = np.array([x[4] for x in rows])
    ms = np.array([x[5] for x in rows]) * 1e3
    ellipse = np.array([x[6] for x in rows])
    right = cells <= 2.0
    confident_wrong = int(np.sum(~right & ~amb))
    ok_right = float(np.mean(~amb[right])) if right.any() else float("nan")
    summary = (
        f"| {date.today()} | {len(rows)} (from {args.first}) | {cell_m:.0f} m | {100 * right.mean():.1f} % (>= 98) | "
        f"{np.median(cells):.3f} (<= 0.15) | {100 * ok_right:.1f} % (>= 95) | {confident_wrong} (0) | "
        f"{100 * inside.mean():.1f} % (95-99) | {100 * ellipse.mean():.1f} % (90-99) | "
        f"{np.median(region[right]) if right.any() else float('nan'):.0f} | {100 * amb.mean():.0f} % | "
        f"{np.median(ms):.0f} ms | {wall / 60:.1f} min, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} |\n"
    )
    print(summary)
    out = HERE / "results" / "session_chain_confidence.md"
    append_result(
        out,
        "# The demo's session chain over many seeds, with the confidence learned from the skyline "
        "(bench/session_chain.py; earlier rows, before it: session_chain.md)\n\n"
        "Frames from the camera twin, stitched, skyline detected, estimated on the demo database (jacksboro at "
        "its own spacing), compass error up to +-3 deg, tilt up to +-0.3 deg.  Cells: error over the geometric "
        "mean node spacing.  Region: median over the estimates within two cells.\n\n"
        "| date | seeds | cell | within 2 cells | median (cells) | ok among those within 2 cells | "
        "wrong and ok | truth in 95 % region | truth in 95 % ellipse | median region (cells) | ambiguous | "
        "estimate time | run |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        summary,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
