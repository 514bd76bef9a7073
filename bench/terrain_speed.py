"""Speed of the skyline database: jacksboro (344 x 403 nodes), the whole SRTM tile N44W072
(1201 x 1201 nodes) and a 20 x 20 km window inside it, 360 azimuths each; horizon samples per second
and peak memory (the whole process) beside the database's size plus the DEM's.

Targets: jacksboro at most 1.0 s idle, and at most 1.5x that beside a busy process; the tile at most
15 s; the window at most 20 % of the tile's time; peak memory at most the database plus the DEM.

    python bench/terrain_speed.py [--only NAME] [--busy] [--repeats N]
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
TILE = str(SHARED / "dem_srtm_hgt" / "N44W072.hgt")
#: name: (DEM, search bounds W,S,E,N or "", target seconds)
CASES = {
    "jacksboro": ("jacksboro", "", 1.0),
    "n44w072": (TILE, "", 15.0),
    "n44w072 20x20 km window": (TILE, "-71.48,44.41,-71.23,44.59", 0.2 * 15.0),
}


def run_one(dem_path: str, bounds: str, repeats: int) -> None:
    """Child process: build one database ``repeats`` times, print the median seconds, nodes, peak RSS,
    database size and the DEM's size in memory."""
    sys.path.insert(0, str(HERE.parent))
    from appliance.terrain.database import build_database
    from appliance.terrain.dem import load_dem
    from appliance.terrain.sweep import horizon_tan_grid

    dem = load_dem(dem_path)
    import numpy as np

    horizon_tan_grid(np.zeros((8, 8)), 30.0, 30.0, 10.0, 1.5, 6.4e6)  # compile outside the timing
    box = tuple(float(v) for v in bounds.split(",")) if bounds else None
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            t0 = time.perf_counter()
            header = build_database(dem, Path(tmp) / "db.viperdb", box, progress=None)  # type: ignore[arg-type]
            times.append(time.perf_counter() - t0)
        size = (Path(tmp) / "db.viperdb").stat().st_size
    seconds = sorted(times)[len(times) // 2]
    g = header["grid"]
    nodes = g["n_rows"] * g["n_cols"]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"{seconds:.3f} {nodes} {header['n_azimuths']} {peak_mb:.0f} {size} {dem.elevation_m.nbytes}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", help="the cases whose name starts with this")
    ap.add_argument("--busy", action="store_true", help="run a spinning process beside the builds")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--bounds", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        run_one(args.child, args.bounds, args.repeats)
        return 0
    rows = []
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.busy else None
    try:
        rows = run_cases(args)
    finally:
        if busy is not None:
            busy.kill()
    res = HERE / "results" / "terrain_speed.md"
    sys.path.insert(0, str(HERE.parent))
    from bench.results_file import append_result

    append_result(res, "", "".join(rows))
    return 0


def run_cases(args: argparse.Namespace) -> list[str]:
    rows = []
    for name, (path, bounds, target) in CASES.items():
        if args.only and not name.startswith(args.only):
            continue
        if path != "jacksboro" and not Path(path).exists():
            print(f"{name}: {path} absent, skipped")
            continue
        cmd = [sys.executable, __file__, "--repeats", str(args.repeats), "--child", path, f"--bounds={bounds}"]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        seconds, nodes, n_az, peak_mb, size, dem_bytes = out.stdout.split()
        seconds_f, nodes_i, n_az_i = float(seconds), int(nodes), int(n_az)
        rate = nodes_i * n_az_i / seconds_f
        load = os.getloadavg()[0]
        budget_mb = (int(size) + int(dem_bytes)) / 2**20
        print(f"{name}: {nodes_i} nodes x {n_az_i} azimuths in {seconds_f:.2f} s (target {target:.1f} s), "
              f"{rate / 1e6:.1f} M horizon samples/s, peak {peak_mb} MB (database + DEM {budget_mb:.0f} MB), "
              f"{int(size) / nodes_i:.0f} bytes/skyline, load {load:.1f}")
        rows.append(f"| {date.today()} | {name} | {nodes_i} | {seconds_f:.2f} s | {target:.1f} s | "
                    f"{rate / 1e6:.1f} M/s | {peak_mb} MB (db + DEM {budget_mb:.0f} MB) | {int(size) / nodes_i:.0f} | "
                    f"{os.cpu_count()} cores {platform.machine()}, {'beside a busy process, ' if args.busy else ''}"
                    f"load {load:.1f} |\n")
    return rows


if __name__ == "__main__":
    sys.exit(main())
