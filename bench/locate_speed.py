"""How long `viper locate` takes on a cached database, a fresh process each run (issue 31, speed target).

Target: `viper locate PHOTO --map MAP ...` of a 60 deg photo over a 10 km^2 search area, its database
cached, in at most 2 s of wall clock for the whole command (process start to answer).

Cases:
  jacksboro-seedN  bench/photo_locate.py's synthetic photo of seed N (60 deg, 1280 x 720, EXIF focal
                   length only) over its 10 km^2 circle, `--map` the jacksboro DEM (the circle's database
                   built into WORK/cache by the unmeasured first run): the target case.
  finse-2019, finse-2022
                   bench/photo_finse.py's command: the real Finse photos, the lens from `viper calibrate
                   pose` (run once into WORK/finse), a 600 m circle on the 4 m DSM.  Skipped without
                   ../shared/data.

Each case runs once unmeasured (the database, numba's cache, the page cache), then --repeats times; per
run the wall clock (perf_counter around the subprocess) and the CPU time (user + system of the child,
from getrusage).  Every run's answer (lat, lon, status, yaw, pitch, roll, focal length) must be the same;
--save writes them to a JSON file, --compare reads such a file and prints how far each answer moved
(metres, degrees): the check that a change of speed changed no answer.

--phases runs each case once more in a process that times the command's own steps (the functions of
PHASES, inclusive, by wall clock; nested ones say so) and the imports (process start to the command's
parser).  --busy runs `python -c 'while True: pass'` beside the measured runs.  No server: VIPER_SOCKET
is empty for every run.

    python bench/locate_speed.py [--seeds 1000-1004] [--no-finse] [--repeats 3] [--phases] [--busy]
                                 [--viper PATH] [--baseline PATH] [--work DIR] [--save FILE] [--compare FILE]
                                 [--record]

--baseline runs another viper (e.g. a checkout of the commit before a change) alternately with --viper on
every case, so that both see the same load, and says whether their answers are the same.

--record appends a row per case to bench/results/locate_speed.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

from appliance.atomic import write_text_atomic  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402

VIPER = REPO / ".venv" / "bin" / "viper"
WORK = Path(tempfile.gettempdir()) / "viper-locate-speed"
RESULTS = HERE / "results" / "locate_speed.md"
TARGET_S = 2.0

#: The steps timed by --phases: (module, attribute) patched where the command looks them up, and the
#: name printed.  Inclusive wall clock, summed over the calls; "render" is every exact render of the
#: photo's fits, inside the steps after it.
PHASES = (
    ("appliance.cli.locate", "read_image", "read image"),
    ("appliance.cli.locate", "detect_photo", "detect skyline"),
    ("appliance.cli.locate", "open_map", "open map (cached database)"),
    ("appliance.locating.photo_pose", "skyline_grid", "skyline grid"),
    ("appliance.locating.photo_pose", "_screen_and_fit", "screen + hypotheses' exact fits"),
    ("appliance.locating.photo_pose", "screen", "  of which screening"),
    ("appliance.locating.photo_pose", "_exact_hypotheses", "  of which exact fits"),
    ("appliance.locating.photo_pose", "_refit", "hypotheses' orientations (each)"),
    ("appliance.locating.photo_pose", "locate", "estimates (solved orientation)"),
    ("appliance.locating.photo_pose", "refine_jointly", "joint fit"),
    ("appliance.locating.photo_pose", "_with_joint_covariance", "joint covariance"),
    ("appliance.locating.photo_pose", "refit_rivals", "rivals refitted"),
    ("appliance.locating.photo_pose", "solve_orientation", "orientation fits (all)"),
    ("appliance.locating.photo_pose", "render", "renders of the photo's fits (all)"),
    ("appliance.estimator.exact", "render", "renders of the exact fits (all)"),
)

#: Run in a fresh interpreter by --phases: argv[1] is the JSON list of PHASES, the rest the command line.
PHASE_RUNNER = r"""
import json, sys, time
t_start = time.perf_counter()
c_start = time.process_time()
import importlib
from appliance.cli.main import build_parser, main
build_parser(sys.argv[2])
imports = (time.perf_counter() - t_start, time.process_time() - c_start)
spent = {}
def timed(fn, label):
    def wrapper(*a, **k):
        t = time.perf_counter()
        c = time.process_time()
        try:
            return fn(*a, **k)
        finally:
            n, s, u = spent.get(label, (0, 0.0, 0.0))
            spent[label] = (n + 1, s + time.perf_counter() - t, u + time.process_time() - c)
    return wrapper
for module, attr, label in json.loads(sys.argv[1]):
    m = importlib.import_module(module)
    setattr(m, attr, timed(getattr(m, attr), label))
t = time.perf_counter()
c = time.process_time()
code = main(sys.argv[2:])
run = time.perf_counter() - t
main_cpu = time.thread_time()  # this (the main) thread's, from the start: what a free core cannot take over
print(json.dumps({"imports_s": imports[0], "imports_cpu_s": imports[1], "run_s": run,
                  "run_cpu_s": time.process_time() - c, "main_thread_cpu_s": main_cpu, "exit": code,
                  "phases": spent}), file=sys.stderr)
"""


def seed_range(text: str) -> list[int]:
    a, sep, b = text.partition("-")
    lo, hi = int(a), int(b) if sep else int(a)
    return list(range(lo, hi + 1))


def jacksboro_cases(seeds: list[int], viper: Path, work: Path) -> dict[str, list[str]]:
    """bench/photo_locate.py's commands for ``seeds`` at 60 deg (its photos rendered once into ``work``)."""
    from bench import photo_locate

    world = photo_locate.make_world("jacksboro")
    cases = {}
    for seed in seeds:
        spec = photo_locate.draw_spec(world, seed, 60.0)
        photo, _ = photo_locate.cached_photo(work, world, spec)
        cases[f"jacksboro-seed{seed}"] = photo_locate.locate_command(viper, photo, world, spec, work / "cache")
    return cases


def finse_cases(viper: Path, work: Path) -> dict[str, list[str]]:
    """bench/photo_finse.py's commands (the lens calibrated once into ``work``/finse)."""
    from bench import photo_finse, vision_finse

    if not vision_finse.FINSE.is_dir():
        print(f"{vision_finse.FINSE} is absent: no Finse cases", file=sys.stderr)
        return {}
    folder = work / "finse"
    folder.mkdir(parents=True, exist_ok=True)
    camera = folder / "camera.toml"
    if not camera.is_file():
        vision_finse.VIPER = viper
        camera, _ = vision_finse.calibrate(folder)
    centre = photo_finse.near_centre(60.0)
    return {f"finse-{photo[:4]}": photo_finse.locate_command(viper, photo, camera, centre, folder / "cache")
            for photo in vision_finse.PHOTOS}


#: The answer's fields that are not the answer: times and the cache's path.
VOLATILE = frozenset({"timing", "elapsed_ms", "database"})


def answer_of(stdout: str) -> dict | None:
    """The fields of the locator's JSON answer that a speed-up must not change."""
    try:
        out = json.loads(stdout)
    except ValueError:
        return None
    o = out.get("orientation") or {}
    rest = {k: v for k, v in out.items() if k not in VOLATILE}
    return {"lat": out.get("lat"), "lon": out.get("lon"), "status": out.get("status"),
            "yaw_deg": o.get("yaw_deg"), "pitch_deg": o.get("pitch_deg"), "roll_deg": o.get("roll_deg"),
            "focal_px": o.get("focal_px"), "radius95_m": out.get("radius95_m"),
            "total_s": (out.get("timing") or {}).get("total_s"), "json": json.dumps(rest, sort_keys=True)}


def run_once(cmd: list[str], env: dict[str, str]) -> tuple[float, float, dict | None, str]:
    """Wall clock (s), CPU time of the child (user + system, s), its answer and its stderr."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, answer_of(out.stdout) if out.returncode == 0 else None, out.stderr


def phases(cmd: list[str], env: dict[str, str]) -> dict:
    """One run of ``cmd`` (a viper command line) in a process that times its steps (PHASE_RUNNER)."""
    python = os.environ.get("VIPER_PYTHON", sys.executable)
    # -P: the working folder is not put before REPO on the path (another checkout's package could be there)
    run = subprocess.run([python, "-P", "-c", PHASE_RUNNER, json.dumps(PHASES), *cmd[1:]], capture_output=True,
                         text=True, env=dict(env, PYTHONPATH=str(REPO)))
    for line in reversed(run.stderr.strip().splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    raise SystemExit(f"the timed run failed: {run.stderr.strip()[-500:]}")


def moved(a: dict, b: dict) -> dict[str, float | bool]:
    """How far answer ``b`` lies from ``a``: metres, degrees, focal pixels, and whether the status is the same."""
    from pyproj import Geod

    _, _, d = Geod(ellps="WGS84").inv(a["lon"], a["lat"], b["lon"], b["lat"])
    out: dict[str, float | bool] = {"position_m": round(float(d), 4), "same_status": a["status"] == b["status"],
                                    "whole_json_same": a.get("json") == b.get("json")}
    for k in ("yaw_deg", "pitch_deg", "roll_deg", "focal_px"):
        if a.get(k) is not None and b.get(k) is not None:
            diff = float(b[k]) - float(a[k])
            out[k] = round((diff + 180.0) % 360.0 - 180.0 if k == "yaw_deg" else diff, 4)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1000-1004", help="jacksboro seeds A-B (bench/photo_locate.py's photos)")
    ap.add_argument("--no-finse", action="store_true", help="leave out the Finse photos")
    ap.add_argument("--only", help="run the cases whose name starts with this")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--phases", action="store_true", help="time the command's steps in one more run per case")
    ap.add_argument("--busy", action="store_true", help="a spinning python process beside the measured runs")
    ap.add_argument("--viper", type=Path, default=VIPER)
    ap.add_argument("--baseline", type=Path, help="another viper: its runs alternate with --viper's, both reported")
    ap.add_argument("--baseline-label", help="what the baseline is, for the rows (default: its checkout's commit)")
    ap.add_argument("--work", type=Path, default=WORK)
    ap.add_argument("--save", type=Path, help="write the answers to this JSON file")
    ap.add_argument("--compare", type=Path, help="a --save file: print how far each answer moved from it")
    ap.add_argument("--record", action="store_true", help=f"append a row per case to {RESULTS.name}")
    ap.add_argument("--note", default="")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, VIPER_SOCKET="")
    cases = jacksboro_cases(seed_range(args.seeds), args.viper, args.work) if args.seeds else {}
    if not args.no_finse:
        cases.update(finse_cases(args.viper, args.work))
    if args.only:
        cases = {k: v for k, v in cases.items() if k.startswith(args.only)}
    reference = json.loads(args.compare.read_text()) if args.compare else {}
    commit = checkout_commit(args.viper)
    answers: dict[str, dict] = {}
    rows = []
    busy = None
    try:
        for name, cmd in cases.items():
            vipers = {"": cmd} if args.baseline is None else {"": cmd, " (baseline)": [str(args.baseline), *cmd[1:]]}
            firsts = {}
            for tag, c in vipers.items():  # the first run of all builds the database
                _, _, firsts[tag], err = run_once(c, env)
                if firsts[tag] is None:
                    raise SystemExit(f"{name}{tag}: failed: {err.strip()[-400:]}")
            if args.busy and busy is None:
                busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                time.sleep(1.0)
            walls: dict[str, list[float]] = {tag: [] for tag in vipers}
            cpus: dict[str, list[float]] = {tag: [] for tag in vipers}
            for i in range(args.repeats):
                for tag in (list(vipers) if i % 2 == 0 else list(reversed(vipers))):  # alternated
                    wall, cpu, answer, err = run_once(vipers[tag], env)
                    if answer is None:
                        raise SystemExit(f"{name}{tag}: failed: {err.strip()[-400:]}")
                    if answer["json"] != firsts[tag]["json"]:
                        print(f"{name}{tag}: the answer changed between runs: {firsts[tag]} / {answer}",
                              file=sys.stderr)
                    walls[tag].append(wall)
                    cpus[tag].append(cpu)
            load = os.getloadavg()[0]
            first = answers[name] = firsts[""]
            for tag in vipers:
                med_wall, med_cpu = float(np.median(walls[tag])), float(np.median(cpus[tag]))
                f = firsts[tag]
                line = (f"{name + tag:18s} wall median {med_wall:5.2f} s (best {min(walls[tag]):5.2f}), CPU median "
                        f"{med_cpu:5.2f} s, target {TARGET_S:g} s {'met' if med_wall <= TARGET_S else 'missed'}, "
                        f"load {load:.1f}; {f['status']} {f['lat']:.7f},{f['lon']:.7f} yaw {f['yaw_deg']} "
                        f"pitch {f['pitch_deg']} roll {f['roll_deg']}")
                print(line, flush=True)
                rows.append((name + tag, med_wall, min(walls[tag]), med_cpu, load,
                             commit if tag == "" else args.baseline_label or checkout_commit(args.baseline)))
            if args.baseline is not None:
                print(f"  against the baseline: {moved(firsts[' (baseline)'], first)}", flush=True)
            if name in reference:
                print(f"  against --compare: {moved(reference[name], first)}", flush=True)
            if args.phases:
                p = phases(cmd, env)
                print(f"  imports {p['imports_s']:.3f} s (CPU {p['imports_cpu_s']:.3f} s), command {p['run_s']:.3f} s "
                      f"(CPU {p['run_cpu_s']:.3f} s); main thread's CPU from the start {p['main_thread_cpu_s']:.3f} s; "
                      "wall (CPU, all threads) per step:", flush=True)
                for _, _, label in PHASES:
                    if label in p["phases"]:
                        n, s, u = p["phases"][label]
                        print(f"    {label:36s} {s:6.3f} s ({u:6.3f} s)  {n} calls")
    finally:
        if busy is not None:
            busy.terminate()
            busy.wait()
    if args.save:
        write_text_atomic(args.save, json.dumps(answers, indent=1) + "\n")
    if args.record and rows:
        condition = "beside a busy process" if args.busy else "no spinner added"
        text = "".join(f"| {date.today()} | {which} | {name} | {wall:.2f} | {best:.2f} | {cpu:.2f} | "
                       f"{'met' if wall <= TARGET_S else 'missed'} | {condition}, load {load:.1f}, "
                       f"{os.cpu_count()} cores {platform.machine()} | {args.note} |\n"
                       for name, wall, best, cpu, load, which in rows)
        append_result(RESULTS, HEADER, text)
    return 0


HEADER = """# `viper locate` on a cached database, end to end (bench/locate_speed.py, issue 31)

Target: at most 2 s of wall clock for the whole command (a fresh process, start to answer) for a 60 deg
photo over a 10 km^2 search area. jacksboro-seedN: bench/photo_locate.py's synthetic photo of seed N over its
10 km^2 circle (the database of the circle cached); finse-YYYY: bench/photo_finse.py's command (the real
photo, a 600 m circle on the 4 m DSM, cached). Median of the repeats after one unmeasured run; CPU = user +
system time of the process.

| date | commit | case | wall median (s) | wall best (s) | CPU median (s) | 2 s target | conditions | note |
|---|---|---|---|---|---|---|---|---|
"""


if __name__ == "__main__":
    sys.exit(main())
