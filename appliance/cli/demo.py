"""``viper demo``: the README's main command, a whole simulated field session on the jacksboro map.

Level, calibrate the compass, GPS ground truth, capture, estimate, on the simulated platform (the
real drivers over the twins) at a random position; prints the estimate against the GPS truth and
leaves the MCAP log and the report in ``--out``.  ``--skyline-only`` is the quicker synthetic-skyline
demo (:func:`appliance.sim.demo.run_demo`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from appliance.atomic import check_output_folder
from appliance.config import CameraDeviceConfig, Config, DevicesConfig, LogbookConfig, SessionConfig, SimConfig
from appliance.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="a whole simulated field session on the embedded jacksboro map")
    p.add_argument("--out", default="viper-demo", help="folder for the log and the report (default ./viper-demo)")
    p.add_argument("--seed", type=int, help="random seed (default: a new position each run)")
    p.add_argument("--skyline-only", action="store_true",
                   help="only locate a synthetic noisy skyline (no platform, no images)")
    p.add_argument("--time-rate", type=float, default=20.0, help="simulated seconds per real second (default 20)")
    p.set_defaults(func=run)


def demo_config(out: Path, time_rate: float) -> Config:
    return Config(
        logbook=LogbookConfig(log_dir=out),
        session=SessionConfig(level_tolerance_deg=0.3),
        devices=DevicesConfig(camera=CameraDeviceConfig(width=640, height=480)),
        sim=SimConfig(time_rate=time_rate),
    )


def run(args: argparse.Namespace) -> int:
    if not args.time_rate > 0:
        raise InputError(f"--time-rate {args.time_rate}: must be a positive number")
    if args.skyline_only:
        return run_skyline_only(args)
    from appliance.acquisition.replay import session_report
    from appliance.position import truth_error_m
    from appliance.sim.demo import DEMO_DEM, demo_database
    from appliance.sim.field_session import run_field_session
    from appliance.terrain.dem import load_dem

    out = check_output_folder(args.out)
    print("Viper demo: a simulated field session on the jacksboro DEM (Cumberland Mountains, Tennessee)")
    t0 = time.monotonic()
    dem = load_dem(DEMO_DEM)
    db = demo_database(dem, out)
    print(f"  setup      skyline database {db.path} ready in {time.monotonic() - t0:.0f} s")
    t1 = time.monotonic()

    def status(text: str) -> None:
        print(f"  {time.monotonic() - t1:6.1f} s  {text}", flush=True)

    config = demo_config(out, args.time_rate)
    r, sim_truth = run_field_session(config, out, seed=args.seed, dem=dem, db=db, on_status=status)
    lat, lon = sim_truth.lat_deg, sim_truth.lon_deg
    print(f"  session    {r.status.value}: " + ", ".join(f"{k} {v}" for k, v in r.outcomes.items()))
    for problem in r.problems:
        print(f"  problem    {problem}")
    print(f"  true       {lat:.6f}, {lon:.6f}  (simulated; camera {sim_truth.mast_height_m} m above the ground)")
    if r.truth is not None and r.truth.lat_deg is not None and r.truth.lon_deg is not None:
        print(f"  GPS truth  {r.truth.lat_deg:.6f}, {r.truth.lon_deg:.6f}  ({r.truth.used} fixes, "
              f"sigma {r.truth.sigma_m:.1f} m)")
    if r.estimate is not None:
        p = r.estimate
        cell = (p.cell_size_m[0] * p.cell_size_m[1]) ** 0.5
        err = "no GPS truth" if r.error_m is None else f"{r.error_m:.0f} m from the GPS truth"
        flag = "AMBIGUOUS" if p.result.ambiguous else "ok"
        print(f"  estimate   {p.lat:.6f}, {p.lon:.6f}  {flag}: {err} ({truth_error_m(db, p, (lat, lon)):.0f} m "
              f"from the true position; database nodes {cell:.0f} m apart)")
        for note in p.result.notes:
            print(f"  note       {note}")
        print(f"  region     {p.result.region_area_m2 / 1e6:.3f} km^2 ({p.result.region_nodes.size} cells), "
              f"heading correction {p.result.heading_correction_deg:+.1f} deg, "
              f"{360 - p.result.n_valid} of 360 azimuths missing")
        page = session_report(r, db, out, "Viper demo: a simulated field session on the jacksboro map")
        print(f"  report     {page}")
    print(f"  log        {r.log_path}  (open in Foxglove; 'viper log info', 'viper replay')")
    print(f"  time       {time.monotonic() - t1:.0f} s for the session after setup")
    return 0 if r.estimate is not None else 1


def run_skyline_only(args: argparse.Namespace) -> int:
    from appliance.sim.demo import run_demo

    check_output_folder(args.out)
    r = run_demo(args.out, args.seed)
    p = r.position
    cell = (p.cell_size_m[0] * p.cell_size_m[1]) ** 0.5
    print("Viper demo on the jacksboro DEM (Cumberland Mountains, Tennessee)")
    print(f"  truth      {r.truth_lat:.6f}, {r.truth_lon:.6f}  (camera 1.5 m above the ground)")
    print(f"  skyline    {r.skyline_path}: noise 0.2 deg, {360 - p.result.n_valid} of 360 azimuths missing, "
          f"compass error {r.compass_error_deg:+.1f} deg")
    print(f"  estimate   {p.lat:.6f}, {p.lon:.6f}  {'AMBIGUOUS' if p.result.ambiguous else 'ok'}"
          f"  heading correction {p.result.heading_correction_deg:+.1f} deg"
          f"  in {p.result.elapsed_s * 1e3:.0f} ms over {p.result.candidates} candidates")
    print(f"  error      {r.error_m:.0f} m ({r.error_m / cell:.2f} cells of {cell:.0f} m)")
    print(f"  region     {p.result.region_area_m2 / 1e6:.3f} km^2 ({p.result.region_nodes.size} cells)"
          f"  lower {p.result.lower:.3g} upper {p.result.upper:.3g}")
    for note in p.result.notes:
        print(f"  note       {note}")
    print(f"  picture    {r.picture_path}")
    return 0
