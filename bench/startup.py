"""Commands end to end, each a fresh process as the appliance runs them: process start to output.

- ``viper --help``: target at most 0.3 s;
- ``viper skyline`` on a 300 x 3500 panorama: at most 0.6 s;
- ``viper estimate --json`` on jacksboro with a compass (+-4 deg): at most 0.4 s;
- ``viper estimate --json`` on the whole N44W072 tile with a compass: at most 0.6 s; without one: at most 1.5 s.

Each command runs once unmeasured (numba's cache, the page cache), then ``--repeats`` times.  With ``--busy`` a
second process spins on one core beside it for the whole run.  The databases are built once into bench/cache/.

    python bench/startup.py [--repeats N] [--busy] [--only NAME]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
from bench.results_file import append_result  # noqa: E402

CACHE = HERE / "cache"
TILE = ROOT.parent / "shared" / "data" / "dem_srtm_hgt" / "N44W072.hgt"
VIPER = str(Path(sys.executable).with_name("viper"))


def spin(stop: multiprocessing.synchronize.Event) -> None:  # type: ignore[name-defined]
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def prepare() -> dict[str, list[str]]:
    """Inputs in bench/cache: the panorama, the databases and one skyline per map."""
    from appliance.errors import DatabaseError
    from appliance.terrain.database import build_database, load_database
    from appliance.terrain.dem import load_dem
    from appliance.vision.panorama import save_panorama
    from appliance.vision.synth import analytic_skyline_fn, render_panorama

    CACHE.mkdir(exist_ok=True)
    pano_path = CACHE / "startup-pano.png"
    if not pano_path.exists():
        synth = render_panorama(analytic_skyline_fn(seed=4), np.random.default_rng(4), px_per_rad=557.0, height_px=300)
        save_panorama(synth.panorama, pano_path)
    cases: dict[str, list[str]] = {
        "help": [VIPER, "--help"],
        "skyline": [VIPER, "skyline", str(pano_path), "--out", str(CACHE / "startup-sky.csv"), "--force"],
    }
    maps = [("jacksboro", "jacksboro", CACHE / "jacksboro-native.viperdb", 36.5521, -84.1911)]
    if TILE.exists():
        maps.append(("tile", str(TILE), CACHE / "n44w072-full.viperdb", 44.27, -71.30))
    for name, dem_name, db_path, lat, lon in maps:
        dem = load_dem(dem_name)
        try:
            load_database(db_path, dem)
        except DatabaseError:  # absent, or of another format version
            build_database(dem, db_path, progress=None)
        sky = CACHE / f"startup-{name}.csv"
        if not sky.exists():
            subprocess.run([VIPER, "render", dem_name, "--lat", str(lat), "--lon", str(lon), "--out", str(sky)],
                           check=True)
        cases[f"estimate {name} +-4"] = [VIPER, "estimate", str(db_path), str(sky), "--heading-tolerance", "4",
                                         "--json"]
        if name == "tile":
            cases["estimate tile no compass"] = [VIPER, "estimate", str(db_path), str(sky), "--unknown-heading",
                                                 "--json"]
    return cases


TARGETS = {"help": 0.3, "skyline": 0.6, "estimate jacksboro +-4": 0.4, "estimate tile +-4": 0.6,
           "estimate tile no compass": 1.5}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--busy", action="store_true", help="run a spinning process beside the commands")
    ap.add_argument("--only", help="run the cases whose name starts with this")
    args = ap.parse_args()
    cases = prepare()
    stop = multiprocessing.Event()
    busy = multiprocessing.Process(target=spin, args=(stop,), daemon=True) if args.busy else None
    if busy is not None:
        busy.start()
    rows = []
    try:
        for name, cmd in cases.items():
            if args.only and not name.startswith(args.only):
                continue
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            ts = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
                ts.append(time.perf_counter() - t)
            load = os.getloadavg()[0]
            med, best = float(np.median(ts)), float(np.min(ts))
            ok = "met" if med <= TARGETS[name] else "missed"
            print(f"{name:28s} median {med * 1e3:6.0f} ms  best {best * 1e3:6.0f} ms  "
                  f"target {TARGETS[name] * 1e3:.0f} ms ({ok}), load {load:.1f}")
            condition = "beside a busy process" if args.busy else "no spinner added"
            rows.append(f"| {date.today()} | {name} | {med * 1e3:.0f} ms | {best * 1e3:.0f} ms | "
                        f"{TARGETS[name] * 1e3:.0f} ms | {condition}, "
                        f"load {load:.1f}, {os.cpu_count()} cores {platform.machine()} |")
    finally:
        stop.set()
        if busy is not None:
            busy.join()
    out = HERE / "results" / "startup.md"
    append_result(out, "# Commands end to end (bench/startup.py)\n\n"
                  "Process start to output, fresh process each run.\n\n"
                  "| date | command | median | best | target | conditions |\n|---|---|---|---|---|---|\n",
                  "\n".join(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
