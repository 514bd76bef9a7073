"""Speed of the skyline database: jacksboro (344 x 403 nodes) and the whole SRTM tile N44W072
(1201 x 1201 nodes), 360 azimuths each; horizon samples per second and peak memory.

Targets: jacksboro at most 3 s; N44W072 at most 60 s with peak memory at most 2 GB.

    python bench/terrain_speed.py [--only jacksboro|n44w072]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"
CASES = {
    "jacksboro": ("jacksboro", 3.0),
    "n44w072": (str(SHARED / "dem_srtm_hgt" / "N44W072.hgt"), 60.0),
}


def run_one(dem_path: str) -> None:
    """Child process: build one database, print seconds, nodes and peak RSS."""
    sys.path.insert(0, str(HERE.parent))
    from appliance.terrain.database import build_database
    from appliance.terrain.dem import load_dem
    from appliance.terrain.sweep import horizon_tan_grid

    dem = load_dem(dem_path)
    import numpy as np

    horizon_tan_grid(np.zeros((8, 8)), 30.0, 30.0, 10.0, 1.5, 6.4e6)  # compile outside the timing
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        header = build_database(dem, Path(tmp) / "db.viperdb", progress=None)
        seconds = time.perf_counter() - t0
        size = (Path(tmp) / "db.viperdb").stat().st_size
    g = header["grid"]
    nodes = g["n_rows"] * g["n_cols"]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"{seconds:.3f} {nodes} {header['n_azimuths']} {peak_mb:.0f} {size}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", choices=sorted(CASES))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        run_one(args.child)
        return 0
    rows = []
    load = os.getloadavg()[0]
    for name, (path, target) in CASES.items():
        if args.only and name != args.only:
            continue
        if path != "jacksboro" and not Path(path).exists():
            print(f"{name}: {path} absent, skipped")
            continue
        out = subprocess.run([sys.executable, __file__, "--child", path], capture_output=True, text=True, check=True)
        seconds, nodes, n_az, peak_mb, size = out.stdout.split()
        seconds_f, nodes_i, n_az_i = float(seconds), int(nodes), int(n_az)
        rate = nodes_i * n_az_i / seconds_f
        print(f"{name}: {nodes_i} nodes x {n_az_i} azimuths in {seconds_f:.1f} s (target {target:.0f} s), "
              f"{rate / 1e6:.1f} M horizon samples/s, peak {peak_mb} MB, {int(size) / nodes_i:.0f} bytes/skyline")
        rows.append(f"| {date.today()} | {name} | {nodes_i} | {seconds_f:.1f} s | {target:.0f} s | "
                    f"{rate / 1e6:.1f} M/s | "
                    f"{peak_mb} MB | {int(size) / nodes_i:.0f} | {os.cpu_count()} cores {platform.machine()}, "
                    f"load {load:.1f} |\n")
    res = HERE / "results" / "terrain_speed.md"
    if not res.exists():
        res.write_text("# Skyline database speed (bench/terrain_speed.py)\n\n"
                       "360 azimuths, camera 1.5 m, whole map as the search area; compile time excluded.\n\n"
                       "| date | map | nodes | time | target | horizon samples/s | peak memory | bytes/skyline "
                       "| machine |\n|---|---|---|---|---|---|---|---|---|\n")
    with res.open("a") as fh:
        fh.writelines(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
