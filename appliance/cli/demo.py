"""``viper demo``: the README's main command."""

from __future__ import annotations

import argparse

from appliance.demo import run_demo


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="locate a simulated platform on the embedded jacksboro map")
    p.add_argument("--out", default="viper-demo", help="folder for the outputs (default ./viper-demo)")
    p.add_argument("--seed", type=int, help="random seed (default: a new position each run)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    r = run_demo(args.out, args.seed)
    p = r.position
    cell = (p.cell_size_m[0] * p.cell_size_m[1]) ** 0.5
    print("Viper demo on the jacksboro DEM (Cumberland Mountains, Tennessee)")
    print(f"  truth      {r.truth_lat:.6f}, {r.truth_lon:.6f}  (camera 1.5 m above the ground)")
    print(f"  skyline    {r.skyline_path}: noise 0.2 deg, {360 - p.result.n_valid} of 360 azimuths missing, "
          f"compass error {r.compass_error_deg:+.1f} deg")
    print(f"  estimate   {p.lat:.6f}, {p.lon:.6f}  heading correction {p.result.heading_correction_deg:+.1f} deg"
          f"  in {p.result.elapsed_s * 1e3:.0f} ms over {p.result.candidates} candidates")
    print(f"  error      {r.error_m:.0f} m ({r.error_m / cell:.2f} cells of {cell:.0f} m)")
    print(f"  region     {p.result.region_area_m2 / 1e6:.3f} km^2 ({p.result.region_nodes.size} cells)"
          f"  lower {p.result.lower:.3g} upper {p.result.upper:.3g}")
    for note in p.result.notes:
        print(f"  note       {note}")
    print(f"  picture    {r.picture_path}")
    return 0
