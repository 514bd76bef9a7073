"""Commands end to end, each a fresh process as the appliance runs them: process start to output.

- ``viper --help``: target at most 0.3 s;
- ``viper skyline`` on a 300 x 3500 panorama: at most 0.6 s;
- ``viper estimate --json`` on jacksboro with a compass (+-4 deg): at most 0.4 s;
- ``viper estimate --json`` on the whole N44W072 tile with a compass: at most 0.6 s; without one: at most 1.5 s;
- ``viper locate --json`` of a 60-degree photo over a 10 km^2 circle, its database cached: at most 2 s (issue 31).

Each command runs once unmeasured (numba's cache, the page cache), then ``--repeats`` times.  With ``--busy`` a
second process spins on one core beside it for the whole run.  With ``--served`` a ``viper serve`` of the bench's
own runs the forwarded commands (estimate, locate, render, skyline) in its warm process, as on an
appliance with the commands' units installed; the bench checks that every run went through it.  Without,
no command is forwarded.  The databases are built once into bench/cache/.

    python bench/startup.py [--repeats N] [--busy] [--served] [--only NAME]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
from appliance.cli._forward import FORWARDED  # noqa: E402
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
    cases["locate photo 60 deg 10 km2"] = locate_case()
    return cases


#: the photo of `viper locate`'s case: a jacksboro ridge seen through a 60-degree lens, EXIF focal length only
PHOTO_LAT, PHOTO_LON, PHOTO_POSE = 36.50392834558151, -84.14421287272029, (185.5, -2.1, -2.7)


def locate_case() -> list[str]:
    """`viper locate` of a 1280 x 720 photo with EXIF (60-degree view, unknown yaw, pitch and roll) over a
    10 km^2 circle of jacksboro (radius 1784 m, its centre 700 m from the camera): the database for the circle
    is built into bench/cache/locate-maps by the first (unmeasured) run, and cached for the measured ones."""
    import io
    import math

    from PIL import ExifTags, Image

    from appliance.terrain.dem import demo_dem_path, load_dem
    from appliance.vision.intrinsics import CameraIntrinsics
    from appliance.vision.synth import render_photo

    photo = CACHE / "startup-photo60.jpg"
    if not photo.exists():
        cam = CameraIntrinsics.from_fov(1280, 720, 60.0)
        image = render_photo(load_dem("jacksboro"), PHOTO_LAT, PHOTO_LON, 1.5, *PHOTO_POSE, cam,
                             np.random.default_rng(5), weather="cloudy", scene_seed=5)
        exif = Image.Exif()
        exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = round(
            cam.fx * 43.2666 / math.hypot(1280, 720))
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(image[..., ::-1])).save(buf, "JPEG", quality=92, exif=exif)
        photo.write_bytes(buf.getvalue())
    near = f"{PHOTO_LAT + 0.004:.6f},{PHOTO_LON - 0.005:.6f},1784"
    return [VIPER, "locate", str(photo), "--map", str(demo_dem_path()), "--near", near, "--cache",
            str(CACHE / "locate-maps"), "--json"]


TARGETS = {"locate photo 60 deg 10 km2": 2.0,
           "help": 0.3, "skyline": 0.6, "estimate jacksboro +-4": 0.4, "estimate tile +-4": 0.6,
           "estimate tile no compass": 1.5}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--busy", action="store_true", help="run a spinning process beside the commands")
    ap.add_argument("--only", help="run the cases whose name starts with this")
    ap.add_argument("--served", action="store_true", help="a `viper serve` runs the forwarded commands")
    args = ap.parse_args()
    cases = prepare()
    with tempfile.TemporaryDirectory() as where:
        return measure(cases, args, Path(where))


def start_server(where: Path) -> tuple[subprocess.Popen, Path, Path, float]:
    """A `viper --log-level debug serve` on a socket in ``where``: the process, its socket, its log and the
    seconds it took to start serving."""
    sock, log = where / "commands.sock", where / "serve.log"
    t = time.perf_counter()
    with log.open("w") as err:
        server = subprocess.Popen([VIPER, "--log-level", "debug", "serve", "--socket", str(sock)],
                                  stderr=err, env=dict(os.environ, VIPER_SOCKET=""))
    while "serving" not in log.read_text():
        if server.poll() is not None:
            raise SystemExit(f"viper serve ended: {log.read_text()}")
        time.sleep(0.01)
    return server, sock, log, time.perf_counter() - t


def measure(cases: dict[str, list[str]], args: argparse.Namespace, where: Path) -> int:
    chosen = {name: cmd for name, cmd in cases.items() if not args.only or name.startswith(args.only)}
    server = None
    env = dict(os.environ, VIPER_SOCKET="")
    if args.served:
        server, sock, log, start_s = start_server(where)
        env["VIPER_SOCKET"] = str(sock)
        print(f"viper serve started in {start_s:.2f} s")
    stop = multiprocessing.Event()
    busy = multiprocessing.Process(target=spin, args=(stop,), daemon=True) if args.busy else None
    if busy is not None:
        busy.start()
    rows = []
    try:
        for name, cmd in chosen.items():
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
            ts = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
                ts.append(time.perf_counter() - t)
            load = os.getloadavg()[0]
            med, best = float(np.median(ts)), float(np.min(ts))
            ok = "met" if med <= TARGETS[name] else "missed"
            print(f"{name:28s} median {med * 1e3:6.0f} ms  best {best * 1e3:6.0f} ms  "
                  f"target {TARGETS[name] * 1e3:.0f} ms ({ok}), load {load:.1f}")
            condition = "beside a busy process" if args.busy else "no spinner added"
            if args.served and cmd[1] in FORWARDED:
                condition += ", through viper serve"
            rows.append(f"| {date.today()} | {name} | {med * 1e3:.0f} ms | {best * 1e3:.0f} ms | "
                        f"{TARGETS[name] * 1e3:.0f} ms | {condition}, "
                        f"load {load:.1f}, {os.cpu_count()} cores {platform.machine()} |")
    finally:
        stop.set()
        if busy is not None:
            busy.join()
        if server is not None:
            server.terminate()
            server.wait()
    if server is not None:
        served = sum(1 for line in log.read_text().splitlines() if "worker " in line)
        expected = sum(args.repeats + 1 for cmd in chosen.values() if cmd[1] in FORWARDED)
        print(f"runs through the server: {served} of {expected}")
        if served != expected:
            raise SystemExit("some runs did not go through the server: no rows written")
    out = HERE / "results" / "startup.md"
    append_result(out, "# Commands end to end (bench/startup.py)\n\n"
                  "Process start to output, fresh process each run.\n\n"
                  "| date | command | median | best | target | conditions |\n|---|---|---|---|---|---|\n",
                  "\n".join(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
