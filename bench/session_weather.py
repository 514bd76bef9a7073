"""The demo's session chain under weather: camera twin frames -> panorama -> skyline -> estimate.

As bench/session_chain.py (a random position on the jacksboro demo map, random platform heading,
compass off by up to +-3 deg, tilt up to +-0.3 deg, the capture ring's frames stitched by their
tags, ``detect_skyline``, the estimate on the demo database), with each frame rendered under a
weather drawn per seed (:mod:`appliance.sim.weather`; the clouds drift between frames).

Per class: the share of estimates within two cells, the wrong answers that say ok (target 0), the
ok share among the right ones; and the detection, scored against the weather twin's truth at each
1-degree azimuth (the panorama's azimuths are the compass's, so the truth is read at the azimuth
less the compass error): where the skyline is visible, the share found within 0.2 deg; among the
azimuths found, the share more than 0.5 deg below the true skyline (visible or not).  The pooled
reliability of the detector's per-azimuth confidence (found within 0.2 deg, by confidence bin)
is written below the table.

    python bench/session_weather.py --weather all --per-class 20 --first 5001 [--jobs 2]

Seeds: class k of the run (cumulus, overcast, haze, low_sun, snow for ``all``) takes seeds
``first + k * per_class`` onwards.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import sys
import time
from datetime import date
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.acquisition.onboard import stitch_frames  # noqa: E402
from appliance.acquisition.platform import Frame  # noqa: E402
from appliance.acquisition.procedures import TaggedFrame, capture_angles  # noqa: E402
from appliance.atomic import write_bytes_atomic  # noqa: E402
from appliance.locating.position import locate  # noqa: E402
from appliance.sim.field_session import random_position  # noqa: E402
from appliance.sim.weather import SkyCondition, draw_weather, render_weather_photo, weather_truth  # noqa: E402
from appliance.vision.camera import CameraPose  # noqa: E402
from appliance.vision.panorama import Panorama, Projection  # noqa: E402
from appliance.vision.skyline_detect import detect_skyline  # noqa: E402
from bench import session_chain as chain  # noqa: E402
from bench.results_file import append_result  # noqa: E402

ALL = ("cumulus", "overcast", "haze", "low_sun", "snow")
BINS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.01)


def weather_panorama(seed: int, condition: str, cache: Path | None = None) -> dict:
    """The stitched panorama of ``seed``'s session under ``condition``, the truth (lat, lon) and the
    weather twin's skyline at each panorama column (elevation, visible) and the frames' motion map
    (:attr:`Panorama.motion`); with ``cache``, kept there (``<condition>_<seed>.png`` and ``.npz``)
    and read back on later runs."""
    st = chain._STATE
    dem, db, intr, ses = st["dem"], st["db"], st["intr"], st["ses"]
    png = None if cache is None else cache / f"{condition}_{seed}.png"
    if png is not None and png.exists():
        img = cv2.imread(str(png), cv2.IMREAD_COLOR)
        with np.load(png.with_suffix(".npz")) as z:
            meta = {k: z[k] for k in z.files}
        return dict(image=img, **meta)
    rng = np.random.default_rng(seed)
    lat, lon = random_position(dem, db, rng)
    heading = float(rng.uniform(0.0, 360.0))
    compass_error = float(rng.uniform(-3.0, 3.0))
    pitch, roll = (float(v) for v in rng.uniform(-0.3, 0.3, 2))
    fn = chain.world_skyline_fn(dem, lat, lon, 1.5)
    scene = draw_weather(condition, seed, fn)
    frames = []
    for i, stage in enumerate(capture_angles(intr.hfov_deg, ses.capture_overlap)):
        true_yaw = (heading + stage) % 360.0
        img = render_weather_photo(fn, CameraPose(true_yaw, pitch, roll), intr, rng, scene, frame_index=i)
        frames.append(TaggedFrame(i, Frame(i, img), float(stage), (true_yaw + compass_error) % 360.0, roll, pitch))
    pano = stitch_frames(frames, intr)
    # the panorama's azimuths are the compass's: the truth is read at the azimuth less its error
    az = pano.column_azimuth_deg(np.arange(pano.width, dtype=np.float64))
    true_el, visible = weather_truth(scene, fn, az - compass_error)
    meta = dict(lat=np.float64(lat), lon=np.float64(lon), true_el=true_el, visible=visible)
    if pano.motion is not None:
        # the frames' disagreement (appliance.vision.temporal) goes with the image: detection reads it
        meta["motion"] = pano.motion
    if png is not None:
        ok, buf = cv2.imencode(".png", pano.image)
        if ok:
            write_bytes_atomic(png, buf.tobytes())
        stream = io.BytesIO()
        np.savez_compressed(stream, **meta)
        write_bytes_atomic(png.with_suffix(".npz"), stream.getvalue())
    return dict(image=pano.image, **meta)


def weather_session(seed: int, condition: str, cache: Path | None = None) -> dict:
    """One session under ``condition``: the estimate's error (cells, NaN without an estimate), its
    ambiguity, and the detection's per-azimuth scores."""
    st = chain._STATE
    dem, db, intr, est = st["dem"], st["db"], st["intr"], st["est"]
    got = weather_panorama(seed, condition, cache)
    lat, lon = float(got["lat"]), float(got["lon"])
    # the geometry stitch_frames gives every panorama of this camera (posed_stitch.stitch_posed)
    width = int(round(2 * math.pi * intr.fx))
    # (a panorama kept by an earlier version of this bench has no motion map: detected without it)
    pano = Panorama(got["image"], Projection.CYLINDRICAL, width / (2 * math.pi), 0.0, (intr.height - 1) / 2.0, True,
                    motion=got.get("motion"))
    if st.get("only"):
        return {}
    sky = detect_skyline(pano)
    cols = pano.azimuth_to_column(sky.azimuth_deg)
    true_el = np.interp(cols, np.arange(pano.width), got["true_el"], period=pano.width)
    visible = got["visible"][np.round(cols).astype(np.int64) % pano.width]
    # and inside the panorama's rows (a near hill may rise above the frames' top)
    top_deg, bottom_deg = pano.row_elevation_deg(np.array([0.0, pano.height - 1.0]))
    visible = visible & np.isfinite(true_el) & (true_el < top_deg - 1.0) & (true_el > bottom_deg + 1.0)
    found = np.isfinite(sky.elevation_deg)
    err = np.where(found, sky.elevation_deg - true_el, np.nan)
    within = found & (np.abs(np.nan_to_num(err, nan=99.0)) <= 0.2)
    below = found & (np.nan_to_num(err, nan=0.0) < -0.5)
    conf = sky.confidence if sky.confidence is not None else found.astype(float)
    out = dict(seed=seed, condition=condition, visible=int(visible.sum()), found_visible=int((within & visible).sum()),
               found=int(found.sum()), below=int(below.sum()), below_hidden=int((below & ~visible).sum()),
               conf=conf[found].tolist(), within=within[found].tolist(), cells=float("nan"), ambiguous=True)
    if sky.valid_fraction >= est.min_valid_fraction:
        pos = locate(db, sky, est.sigma_deg, est.heading_tolerance_deg, grid=st["grid"],
                     occlusion_weight=est.occlusion_weight, map_sigma_m=est.map_vertical_sigma_m,
                     sigma_floor_deg=est.sigma_floor_deg)
        _, _, dist_m = dem.geod.inv(lon, lat, pos.lon, pos.lat)
        out.update(cells=float(dist_m) / st["cell_m"], ambiguous=bool(pos.result.ambiguous))
    print(f"seed {seed} {condition}: {out['cells']:.2f} cells, {'ambiguous' if out['ambiguous'] else 'ok'}; "
          f"found {out['found_visible']}/{out['visible']} visible within 0.2 deg, {out['found']} found, "
          f"{out['below']} below by > 0.5 deg ({out['below_hidden']} of them hidden)", flush=True)
    return out


def _worker_setup(threads: int, cache: Path | None, only: bool) -> None:
    import numba  # deferred: only a spawned worker sets its share of the cores

    numba.set_num_threads(threads)
    chain._setup()
    chain._STATE.update(pano_cache=cache, only=only)


def _run(job: tuple[int, str]) -> dict:
    return weather_session(job[0], job[1], chain._STATE.get("pano_cache"))


def class_row(condition: str, rows: list[dict]) -> str:
    if not rows:
        return f"| {condition} | 0 | - | - | - | - | - | - |"
    cells = np.array([r["cells"] for r in rows])
    amb = np.array([r["ambiguous"] for r in rows], dtype=bool)
    right = np.nan_to_num(cells, nan=np.inf) <= 2.0
    wrong_ok = int(np.sum(~right & ~amb))
    ok_right = f"{100 * np.mean(~amb[right]):.0f} %" if right.any() else "-"
    vis = sum(r["visible"] for r in rows)
    fv = sum(r["found_visible"] for r in rows)
    found = sum(r["found"] for r in rows)
    below = sum(r["below"] for r in rows)
    seeds = f"{rows[0]['seed']}-{rows[-1]['seed']}" if rows else "-"
    return (f"| {condition} | {len(rows)} ({seeds}) | {100 * right.mean():.0f} % (>= 95) | {wrong_ok} (0) | "
            f"{ok_right} | "
            f"{100 * fv / max(vis, 1):.1f} % of {vis} (>= 90) | {100 * below / max(found, 1):.2f} % of {found} "
            f"(<= 1) | {100 * vis / (360 * len(rows)):.0f} % |")


def reliability(rows: list[dict]) -> str:
    conf = np.concatenate([np.asarray(r["conf"], dtype=float) for r in rows]) if rows else np.zeros(0)
    within = np.concatenate([np.asarray(r["within"], dtype=bool) for r in rows]) if rows else np.zeros(0, bool)
    lines = ["| confidence | azimuths | within 0.2 deg |", "|---|---|---|"]
    lo = 0.0
    for hi in BINS:
        sel = (conf >= lo) & (conf < hi)
        share = f"{100 * within[sel].mean():.1f} %" if sel.any() else "-"
        lines.append(f"| {lo:.2f}-{min(hi, 1.0):.2f} | {int(sel.sum())} | {share} |")
        lo = hi
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--weather", default="all", help="a class of appliance.sim.weather, or all")
    ap.add_argument("--per-class", type=int, default=20)
    ap.add_argument("--first", type=int, default=5001)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--panoramas", type=Path, help="keep each seed's stitched panorama and truth in this folder "
                    "and read them from there on later runs (the detector and estimator alone are then rerun)")
    ap.add_argument("--panoramas-only", action="store_true", help="only render, stitch and keep the panoramas")
    ap.add_argument("--cached-only", action="store_true", help="only the seeds whose panorama is kept already")
    ap.add_argument("--no-record", action="store_true", help="print only; leave bench/results alone")
    args = ap.parse_args()
    classes = ALL if args.weather == "all" else (SkyCondition.parse(args.weather).value,)
    # round robin over the classes: a run cut short has about as many seeds of each
    jobs = [(args.first + k * args.per_class + j, c) for j in range(args.per_class) for k, c in enumerate(classes)]
    if args.panoramas is not None:
        args.panoramas.mkdir(parents=True, exist_ok=True)
        if args.cached_only:
            jobs = [(seed, c) for seed, c in jobs if (args.panoramas / f"{c}_{seed}.png").exists()]
    chain._setup()
    chain._STATE.update(pano_cache=args.panoramas, only=args.panoramas_only)
    t0 = time.monotonic()
    if args.jobs > 1:
        import multiprocessing  # deferred: only a parallel run needs it

        ctx = multiprocessing.get_context("spawn")
        threads = max(1, (os.cpu_count() or 1) // args.jobs)
        with ctx.Pool(args.jobs, initializer=_worker_setup,
                      initargs=(threads, args.panoramas, args.panoramas_only)) as pool:
            results = pool.map(_run, jobs, chunksize=1)
        results = [r for r in results if r]
    else:
        results = [_run(j) for j in jobs]
    wall = time.monotonic() - t0
    if args.panoramas_only:
        return 0
    table = [class_row(c, [r for r in results if r["condition"] == c]) for c in classes]
    text = (f"\n## {date.today()}: {len(results)} seeds ({args.per_class} per class from {args.first}), "
            f"{wall / 60:.0f} min, {os.cpu_count()} cores shared\n\n"
            "| class | seeds | within 2 cells | wrong and ok | ok among right | found within 0.2 deg where "
            "visible | found > 0.5 deg below truth | visible |\n|---|---|---|---|---|---|---|---|\n"
            + "\n".join(table) + "\n\nReliability of the per-azimuth confidence (all classes pooled):\n\n"
            + reliability(results) + "\n")
    print(text)
    if not args.no_record:
        append_result(HERE / "results" / "session_weather.md",
                      "# The session chain under weather (bench/session_weather.py)\n\n"
                      "Frames from the camera twin under a weather drawn per seed (appliance/sim/weather.py), "
                      "stitched by their tags, skyline detected, estimated on the demo database (jacksboro). "
                      "Within 2 cells: estimate error over the node spacing (no estimate counts as a miss). "
                      "Detection per 1-degree azimuth against the twin's truth.\n", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
