"""Rover traverses on the jacksboro map: each stop's error alone and fused with the previous stop's
transported posterior (paper section 6.4), over many seeded traverses.

``--mode session`` (default) runs what ``viper demo --traverse N`` runs: the whole simulated session at
every stop (the twins over their wire protocols, the rover twin driving legs of 200-400 m and sending
its odometry line with 15 m of noise per axis, 640x480 frames at time rate 20, stitch, skyline
detection, the estimate alone and fused).  ``--mode skyline`` is the fast path: at each stop a skyline
rendered from the DEM and read as ``viper demo --skyline-only`` reads it (0.2 deg noise, 25 deg
occluded, 11 dropouts, compass error up to +-4 deg), the same legs and odometry noise, the same
fusion (:func:`appliance.locating.position.transported_prior`).

Errors are against the simulated true position of each stop (session mode: also against the GPS
truth the session logs).  Target (issue 16): the 90th-percentile error over the stops after the
first is lower fused than alone.

    python bench/traverse.py [--mode session|skyline] [--seeds 20] [--stops 5] [--first 1] [--jobs 2]

``--mavlink`` runs each seed with the odometry through the line and through MAVLink (the autopilot twin
and the appliance's MAVLink link over UDP, :mod:`bench.traverse_mavlink`), every estimate sent back as
GPS_INPUT and checked where the twin receives it; ``--reboot-leg K`` adds a run with the twin rebooting
halfway through leg K.  Its results go to results/traverse_mavlink.md.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.config import EstimatorConfig, SimConfig  # noqa: E402
from appliance.locating.position import (  # noqa: E402
    Move,
    estimate_status,
    locate,
    skyline_grid,
    transported_fix,
    transported_prior,
    truth_error_m,
)
from appliance.sim.demo import demo_database, sensor_reading  # noqa: E402
from appliance.sim.field_session import on_map_fn, random_position  # noqa: E402
from appliance.terrain.dem import load_dem  # noqa: E402
from appliance.terrain.horizon import render_skyline  # noqa: E402
from bench.results_file import append_result  # noqa: E402
from bench.traverse_mavlink import MavlinkLeg, p90, sum_checks  # noqa: E402

EARTH_RADIUS_M = 6_371_008.8
_STATE: dict = {}


def _setup(mode: str) -> None:
    dem = load_dem("jacksboro")
    cache = Path(tempfile.gettempdir()) / "viper-bench-db"
    cache.mkdir(exist_ok=True)
    db = demo_database(dem, cache)
    _STATE.update(dem=dem, db=db, grid=skyline_grid(db), mode=mode, on_map=on_map_fn(dem, db),
                  logs=Path(tempfile.mkdtemp(prefix="viper-bench-traverse-")))


def _stop_row(db, stop: int, alone, fused, truth, gps=None) -> dict:
    """One stop: errors (m) against the true position (and the GPS truth, when logged), statuses."""
    row = {"stop": stop, "alone_m": truth_error_m(db, alone, truth), "alone_flag": estimate_status(db, alone, gps)}
    row["fused_m"] = None if fused is None else truth_error_m(db, fused, truth)
    row["fused_flag"] = None if fused is None else estimate_status(db, fused, gps)
    if gps is not None:
        row["alone_gps_m"] = truth_error_m(db, alone, gps)
        row["fused_gps_m"] = None if fused is None else truth_error_m(db, fused, gps)
    return row


def session_traverse(seed: int, n_stops: int) -> list[dict]:
    from appliance.cli.demo import demo_config
    from appliance.sim.field_session import run_field_traverse

    st = _STATE
    out = st["logs"] / f"seed-{seed}"
    out.mkdir(exist_ok=True)
    r, truths = run_field_traverse(demo_config(out, 20.0), out, n_stops, seed=seed, dem=st["dem"], db=st["db"])
    return _session_rows(r, truths)


def _session_rows(r, truths) -> list[dict]:
    rows = []
    for s, tr in zip(r.stops, truths, strict=True):
        if s.position is None or s.alone is None:
            rows.append({"stop": s.stop, "failed": s.session.status.value})
            continue
        rows.append(_stop_row(_STATE["db"], s.stop, s.alone, s.position if s.fused else None,
                              (tr.lat_deg, tr.lon_deg), s.truth))
        rows[-1]["reset"] = bool(s.odometry is not None and s.odometry.reset)
    return rows


def session_mavlink(seed: int, n_stops: int, mavlink: bool, reboot_leg: int | None = None) -> list[dict]:
    """A whole simulated traverse (``viper demo --traverse N [--mavlink]``); with MAVLink, the twin's
    received GPS_INPUTs checked against the stops' estimates that say ok (only those are sent)."""
    import dataclasses

    from appliance.acquisition.rover_link import position_fix
    from appliance.cli.demo import demo_config
    from appliance.drivers.mavlink_output import horizontal_accuracy_m
    from appliance.sim.field_session import run_field_traverse

    st = _STATE
    out = st["logs"] / f"seed-{seed}-{'mavlink' if mavlink else 'line'}-{reboot_leg}"
    out.mkdir(exist_ok=True)
    cfg = demo_config(out, 20.0, mavlink=mavlink)
    if reboot_leg is not None:
        faults = dataclasses.replace(cfg.sim.faults, autopilot_reboot_leg=reboot_leg)
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, faults=faults))
    twins: list = []
    r, truths = run_field_traverse(cfg, out, n_stops, seed=seed, dem=st["dem"], db=st["db"],
                                   on_open=lambda d: twins.append(getattr(d, "autopilot_twin", None)))
    rows = _session_rows(r, truths)
    if mavlink and rows:
        fixes = [position_fix(s.position, 0) for s in r.stops if s.position is not None]
        ok = [f for f in fixes if f.ok]
        got = [x.message for x in twins[0].received if x.message.get_type() == "GPS_INPUT"]
        c = {"sent": len(ok), "sent_ok": len(ok), "received": len(got), "fix3_ok": 0, "fix0_not_ok": 0,
             "good_from_not_ok": max(len(got) - len(ok), 0), "accuracy_mismatch": 0, "max_accuracy_error_m": 0.0}
        for f, m in zip(ok, got):
            c["fix3_ok"] += m.fix_type == 3 and m.lat == int(round(f.lat_deg * 1e7))
            err = abs(float(m.horiz_accuracy) - horizontal_accuracy_m(f.covariance_m2))
            c["max_accuracy_error_m"] = max(c["max_accuracy_error_m"], err)
            c["accuracy_mismatch"] += err > 1e-6 * max(1.0, float(m.horiz_accuracy))
        rows[0]["checks"] = c
        rows[0]["faults"] = [p for p in r.problems if p.startswith("autopilot:")]
    return rows


def _offset(lat: float, lon: float, north_m: float, east_m: float) -> tuple[float, float]:
    return (lat + math.degrees(north_m / EARTH_RADIUS_M),
            lon + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat)))))


def skyline_traverse(seed: int, n_stops: int, mavlink: bool = False, reboot_leg: int | None = None) -> list[dict]:
    """One traverse of the fast path; ``mavlink``: the odometry through the autopilot twin and the MAVLink
    link (the same legs and skylines as the line's), every estimate sent back as GPS_INPUT and checked;
    ``reboot_leg``: the twin reboots halfway through that leg.  The first row carries the link's checks."""
    st = _STATE
    dem, db, grid, on_map = st["dem"], st["db"], st["grid"], st["on_map"]
    sim, est = SimConfig(), EstimatorConfig()
    rng = np.random.default_rng(seed)
    lat, lon = random_position(dem, db, rng)
    mav = MavlinkLeg(lat, lon, seed + 1000) if mavlink else None
    rows, belief, moved = [], None, None
    try:
        for stop in range(n_stops):
            reset = False
            if stop > 0:
                for _ in range(500):
                    length, bearing = rng.uniform(*sim.leg_length_m), rng.uniform(0.0, 2.0 * math.pi)
                    east, north = length * math.sin(bearing), length * math.cos(bearing)
                    nxt = _offset(lat, lon, north, east)
                    if on_map(*nxt):
                        break
                lat, lon = nxt
                noise = rng.normal(0.0, sim.odometry_sigma_m, 2)  # drawn in both cases: the skylines stay the same
                move: Move | None = Move(east + noise[0], north + noise[1], sim.odometry_sigma_m)
                if mav is not None:
                    move, reset = mav.leg(east, north, lat, lon, reboot=stop == reboot_leg)
                if move is None:
                    belief, moved = None, None  # the autopilot's frame was reset: no fusion across it
                else:
                    moved = move if moved is None else moved.then(move)
            truth = render_skyline(dem, lat, lon, height_m=1.5)
            sky = sensor_reading(truth.elevation_deg, rng, compass_error_deg=float(rng.uniform(-4.0, 4.0)))
            kw = dict(grid=grid, occlusion_weight=est.occlusion_weight, map_sigma_m=est.map_vertical_sigma_m)
            alone = locate(db, sky, est.sigma_deg, est.heading_tolerance_deg, **kw)
            fused = None
            if belief is not None and moved is not None:
                prior, fix = transported_prior(db, grid, belief, moved), transported_fix(db, grid, belief, moved)
                fused = locate(db, sky, est.sigma_deg, est.heading_tolerance_deg, log_prior=prior, position_prior=fix,
                               **kw)
            belief, moved = (fused or alone), Move(0.0, 0.0, 0.0)
            if mav is not None:
                mav.send(belief)
            row = _stop_row(db, stop, alone, fused, (lat, lon))
            row["reset"] = reset
            rows.append(row)
    finally:
        if mav is not None:
            mav.close()
            rows[0]["checks"], rows[0]["faults"] = mav.checks, mav.faults
    return rows


def _run(args: tuple) -> tuple[int, list[dict]]:
    seed, n_stops, *variant = args
    t = time.monotonic()
    if variant:
        rows = (session_mavlink if _STATE["mode"] == "session" else skyline_traverse)(seed, n_stops, *variant)
    else:
        rows = (session_traverse if _STATE["mode"] == "session" else skyline_traverse)(seed, n_stops)
    text = "  ".join("failed" if "failed" in r else
                     f"{r['stop']}: {r['alone_m']:.0f}" + ("" if r["fused_m"] is None else f"/{r['fused_m']:.0f}")
                     for r in rows)
    print(f"seed {seed} ({time.monotonic() - t:.0f} s): error alone/fused (m)  {text}", flush=True)
    return seed, rows


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=("session", "skyline"), default="session")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--stops", type=int, default=5)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--mavlink", action="store_true",
                    help="each seed twice, odometry through the ODO line and through MAVLink (the autopilot twin), "
                         "estimates sent back as GPS_INPUT and checked; results in results/traverse_mavlink.md")
    ap.add_argument("--reboot-leg", type=int, default=None,
                    help="with --mavlink: also each seed with the twin rebooting halfway through this leg")
    return ap.parse_args()


def main() -> int:
    args = _parse_args()
    _setup(args.mode)  # builds the database once, before any worker starts
    if args.mavlink:
        return main_mavlink(args)
    work = [(seed, args.stops) for seed in range(args.first, args.first + args.seeds)]
    t0 = time.monotonic()
    if args.jobs > 1:
        import multiprocessing

        # spawned, not forked: the parent has run numba's OpenMP kernels (building the database), and
        # GNU OpenMP kills a child forked after that; each worker loads the database the parent built
        with multiprocessing.get_context("spawn").Pool(args.jobs, initializer=_setup, initargs=(args.mode,)) as pool:
            results = sorted(pool.imap_unordered(_run, work))
    else:
        results = [_run(w) for w in work]
    wall = time.monotonic() - t0
    later = [r for _, rows in results for r in rows if r["stop"] > 0 and "failed" not in r]
    failed = sum(1 for _, rows in results for r in rows if "failed" in r)
    alone = np.array([r["alone_m"] for r in later])
    fused = np.array([r["fused_m"] if r["fused_m"] is not None else r["alone_m"] for r in later])
    amb_alone = sum(r["alone_flag"] == "ambiguous" for _, rows in results for r in rows if "failed" not in r)
    amb_fused = sum((r["fused_flag"] or r["alone_flag"]) == "ambiguous"
                    for _, rows in results for r in rows if "failed" not in r)
    n_stops = sum(1 for _, rows in results for r in rows if "failed" not in r)
    p90_a, p90_f = float(np.percentile(alone, 90)), float(np.percentile(fused, 90))
    verdict = "met" if p90_f < p90_a else "NOT met"
    gps = ""
    if args.mode == "session":
        ga = np.array([r["alone_gps_m"] for r in later])
        gf = np.array([r["fused_gps_m"] if r["fused_gps_m"] is not None else r["alone_gps_m"] for r in later])
        gps = f" {np.percentile(ga, 90):.1f} / {np.percentile(gf, 90):.1f} |"
    else:
        gps = " - |"
    summary = (f"| {date.today()} | {args.mode} | {len(results)} x {args.stops} (seeds {args.first}-"
               f"{args.first + args.seeds - 1}) | {len(later)} | {p90_a:.1f} / {p90_f:.1f} ({verdict}) |{gps} "
               f"{np.median(alone):.1f} / {np.median(fused):.1f} | {alone.max():.0f} / {fused.max():.0f} | "
               f"{amb_alone} / {amb_fused} of {n_stops} | {failed} | {wall / 60:.1f} min, {args.jobs} jobs, "
               f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} |\n")
    print(summary)
    out = HERE / "results" / "traverse.md"
    text = [summary]
    text.append("\nPer stop (seed: stop error alone / fused, m; * ambiguous):\n\n" if args.mode == "session" else "")
    if args.mode == "session":
        for seed, rows in results:
            cells = []
            for r in rows:
                if "failed" in r:
                    cells.append(f"{r['stop']}: failed")
                    continue
                a = f"{r['alone_m']:.1f}{'*' if r['alone_flag'] == 'ambiguous' else ''}"
                f = "" if r["fused_m"] is None else \
                    f" / {r['fused_m']:.1f}{'*' if r['fused_flag'] == 'ambiguous' else ''}"
                cells.append(f"{r['stop']}: {a}{f}")
            text.append(f"- seed {seed}: " + "; ".join(cells) + "\n")
        text.append("\n")
    append_result(
        out,
        "# Rover traverses (bench/traverse.py)\n\n"
        "Jacksboro, the demo's database (nodes 75 m x 92 m); legs of 200-400 m in random directions, odometry "
        "with 15 m of noise per axis (sigma 15 m).  Errors against the simulated true position of each stop, "
        "over the stops after the first (the first has nothing to fuse with).  Target: p90 fused < p90 alone.  "
        "Ambiguous: stops whose estimate says so (region too large, or in session mode the GPS truth outside "
        "the region), over every stop including the first.\n\n"
        "| date | mode | traverses x stops | stops after the first | p90 alone / fused (m) | p90 vs GPS truth "
        "alone / fused (m) | median alone / fused (m) | max alone / fused (m) | ambiguous alone / fused | "
        "stops failed | run |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n",
        "".join(text),
    )
    return 0


def _pool_map(args, work: list) -> list:
    if args.jobs > 1:
        import multiprocessing

        # spawned, not forked, as in main()
        with multiprocessing.get_context("spawn").Pool(args.jobs, initializer=_setup, initargs=(args.mode,)) as pool:
            return list(pool.imap(_run, work))
    return [_run(w) for w in work]


def _variant_summary(name: str, results: list[tuple[int, list[dict]]]) -> tuple[str, dict]:
    later = [r for _, rows in results for r in rows if r["stop"] > 0 and "failed" not in r]
    alone = [r["alone_m"] for r in later]
    fused = [r["fused_m"] if r["fused_m"] is not None else r["alone_m"] for r in later]
    n_fused = sum(r["fused_m"] is not None for r in later)
    resets = [r for r in later if r.get("reset")]
    fused_across = sum(r["fused_m"] is not None for r in resets)
    failed = sum(1 for _, rows in results for r in rows if "failed" in r)
    checks = sum_checks([rows[0]["checks"] for _, rows in results if rows and "checks" in rows[0]])
    faults = [f for _, rows in results if rows for f in rows[0].get("faults", [])]
    reboots = sum("autopilot reboot" in f for f in faults)
    row = (f"| {name} | {len(later)} | {p90(alone):.1f} | {p90(fused):.1f} | {np.median(fused):.1f} | "
           f"{max(fused):.0f} | {n_fused} | {len(resets)} | {reboots} | {fused_across} | {failed} |")
    return row, checks


def main_mavlink(args) -> int:
    """Odometry through the line and through MAVLink on the same seeds (and, with --reboot-leg, MAVLink
    with a reboot of the autopilot twin), with the GPS_INPUT checks."""
    seeds = range(args.first, args.first + args.seeds)
    variants = [("ODO line", False, None), ("MAVLink", True, None)]
    if args.reboot_leg is not None:
        variants.append((f"MAVLink, reboot on leg {args.reboot_leg}", True, args.reboot_leg))
    t0 = time.monotonic()
    table, checks_text = [], []
    for name, mavlink, reboot_leg in variants:
        results = _pool_map(args, [(seed, args.stops, mavlink, reboot_leg) for seed in seeds])
        row, checks = _variant_summary(name, results)
        table.append(row)
        print(row, flush=True)
        if mavlink:
            checks_text.append(
                f"- {name}: {checks['sent']} estimates sent ({checks['sent_ok']} ok), {checks['received']} received "
                f"by the twin; fix_type 3 for {checks['fix3_ok']} of the ok ones, fix_type 0 for "
                f"{checks['fix0_not_ok']} of the {checks['sent'] - checks['sent_ok']} not ok; good fix from a not-ok "
                f"estimate: {checks['good_from_not_ok']}; horiz_accuracy off sqrt(trace(covariance)) by more than "
                f"1e-6 relative: {checks['accuracy_mismatch']} (largest difference "
                f"{checks['max_accuracy_error_m']:.2g} m, float32)\n")
    wall = time.monotonic() - t0
    text = (f"\n## {date.today()}: {args.mode} mode, {args.seeds} traverses x {args.stops} stops (seeds {args.first}-"
            f"{args.first + args.seeds - 1}), {wall / 60:.1f} min, {args.jobs} jobs, {os.cpu_count()} cores, "
            f"load {os.getloadavg()[0]:.1f}\n\n"
            "| odometry | stops after the first | p90 alone (m) | p90 fused (m) | median fused (m) | max fused (m) | "
            "fused stops | stops after a reset | reboot faults logged | fused across a reset | stops failed |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n" + "\n".join(table) + "\n\n" + "".join(checks_text))
    print(text)
    append_result(HERE / "results" / "traverse_mavlink.md", MAVLINK_HEADER, text)
    return 0


MAVLINK_HEADER = """# Rover traverses with the odometry over MAVLink (bench/traverse.py --mavlink)

    python bench/traverse.py --mavlink [--mode skyline|session] [--seeds 20] [--stops 5] [--reboot-leg 2] [--jobs 2]

Each seed runs the same traverse twice: the legs' odometry through the ODO line (15 m of Gaussian noise
per axis, sigma 15 m) and through MAVLink: the autopilot twin (appliance/sim/autopilot_twin.py) drives
the true leg with a dead-reckoning drift of 0.05 m per metre (10-20 m on legs of 200-400 m) and speaks
MAVLink 2 over a real UDP socket to the appliance's link (appliance/drivers/mavlink_reader.py), which
cuts the stream into stops where the rover stands still and gives each displacement with a sigma of
0.05 m per metre.  The skylines, legs and estimates alone are the same in both; only the odometry
differs.  Every estimate is sent back to the twin as GPS_INPUT (ambiguous ones too in skyline mode,
as fix_type 0: output_ambiguous; in session mode only the ok ones, the demo's configuration) and what
the twin receives is checked.  With --reboot-leg the twin also reboots halfway through that leg of
every traverse (its frame and time since boot restart): the link must log the fault and the stop
after it must not be fused.  Errors against the simulated true position of each stop, over the
stops after the first; target: p90 fused through MAVLink no worse than through the line.
"""


if __name__ == "__main__":
    sys.exit(main())
