"""The real Finse photos located by `viper locate`, their orientation unknown (issue 31).

Run: .venv/bin/python bench/photo_finse.py [--work DIR] [--viper PATH] [--offset-bearing 60] [--dry-run]
     (needs ../shared/data)

1. `viper calibrate pose` exactly as bench/vision_finse.py runs it (its function, imported): the 2019
   frame with the data set's ground-control points gives the lens (f, k1, k2 fitted) and the surveyed
   orientation; the 2022 photo gets its own orientation from the same points' pixels in it
   (tests/data/finse_2022_gcp_pixels.csv).
2. Per photo, as a user who knows the lens but not where the camera points:
   `viper locate PHOTO --map DSM --crs EPSG:32632 --camera <fitted camera.toml> --near LAT,LON,600
   --json --truth <surveyed camera> --cache DIR`, the circle's centre 250 m from the surveyed camera
   (MANIFEST section 6: E 419169.2, N 6718421.3) towards --offset-bearing (default 60 deg, true), so
   the camera is not at its middle.  The first run has a fresh, empty --cache (the DSM's database is
   built: timing.build_s); the second run, the same command again, finds it cached.

Figures per photo: error (m) to the surveyed camera (target <= 15 m) and status (target ok); the
solved yaw, pitch and roll beside those `viper calibrate pose` gave (target within 0.3 deg), and the
focal length beside the fitted one; build time and total time of the first run, total time of the
second.  Rows are appended to bench/results/photo_finse.md; the answers go to WORK/answers.jsonl.

--dry-run runs the calibration and prints the locate commands without running them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
from pyproj import Geod, Transformer

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

from appliance.atomic import write_text_atomic  # noqa: E402
from bench import vision_finse  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402

RESULTS = HERE / "results" / "photo_finse.md"
SURVEYED = vision_finse.SURVEYED  # camera_pos, EPSG:32632
NEAR_RADIUS_M = 600.0
NEAR_OFFSET_M = 250.0
TARGET_ERROR_M = 15.0
TARGET_ANGLE_DEG = 0.3


def surveyed_lat_lon() -> tuple[float, float]:
    lon, lat = Transformer.from_crs(32632, 4326, always_xy=True).transform(*SURVEYED)
    return float(lat), float(lon)


def near_centre(bearing_deg: float, offset_m: float = NEAR_OFFSET_M) -> tuple[float, float]:
    """(lat, lon) ``offset_m`` from the surveyed camera towards ``bearing_deg`` (true, clockwise from north)."""
    lat, lon = surveyed_lat_lon()
    lon2, lat2, _ = Geod(ellps="WGS84").fwd(lon, lat, bearing_deg, offset_m)
    return float(lat2), float(lon2)


def locate_command(viper: Path, photo: str, camera: Path, centre: tuple[float, float], cache: Path,
                   pitch_tolerance_deg: float = 10.0) -> list[str]:
    """The webcam looks 7 degrees down: beyond the default 5-degree pitch tolerance, so it is given."""
    lat, lon = surveyed_lat_lon()
    return [str(viper), "locate", str(vision_finse.FINSE / photo), "--map", str(vision_finse.DSM),
            "--crs", "EPSG:32632", "--camera", str(camera),
            "--near", f"{centre[0]:.7f},{centre[1]:.7f},{NEAR_RADIUS_M:.0f}",
            "--pitch-tolerance", f"{pitch_tolerance_deg:g}",
            "--json", "--truth", f"{lat:.7f},{lon:.7f}", "--cache", str(cache)]


def run_locate(cmd: list[str], timeout_s: float) -> tuple[dict | None, dict]:
    """The locator's JSON answer (None when it failed) and the run's exit code, wall time and error line."""
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        code, stdout, stderr = out.returncode, out.stdout, out.stderr
    except subprocess.TimeoutExpired:
        code, stdout, stderr = -1, "", f"timed out after {timeout_s:.0f} s"
    run: dict = {"exit": code, "wall_s": round(time.perf_counter() - t0, 2)}
    answer = None
    if code == 0:
        try:
            answer = json.loads(stdout)
        except ValueError:
            lines = [ln for ln in stdout.splitlines() if ln.startswith("{")]
            try:
                answer = json.loads(lines[-1]) if lines else None
            except ValueError:
                answer = None
    if not isinstance(answer, dict) or "lat" not in answer:
        run["failed"] = stderr.strip().splitlines()[-1] if stderr.strip() else f"exit {code}, no JSON answer"
        return None, run
    return answer, run


def angle_diff_deg(a: float, b: float) -> float:
    return float((a - b + 180.0) % 360.0 - 180.0)


def score(answer: dict | None, run: dict, fit: dict) -> dict:
    """The answer against the surveyed camera and against the orientation `viper calibrate pose` gave."""
    row: dict = dict(run)
    if answer is None:
        return row
    x, y = Transformer.from_crs(4326, 32632, always_xy=True).transform(float(answer["lon"]), float(answer["lat"]))
    timing = answer.get("timing") or {}
    truth = answer.get("truth") or {}
    row.update({
        "lat": answer["lat"], "lon": answer["lon"], "error_m": round(float(np.hypot(x - SURVEYED[0],
                                                                                       y - SURVEYED[1])), 2),
        "truth_error_m": truth.get("error_m"), "in_region": truth.get("in_region"),
        "in_ellipse": truth.get("in_ellipse"), "status": answer.get("status"), "ambiguous": answer.get("ambiguous"),
        "radius95_m": answer.get("radius95_m"), "build_s": timing.get("build_s"), "total_s": timing.get("total_s"),
    })
    o = answer.get("orientation") or {}
    if o:
        row.update({
            "yaw_deg": o.get("yaw_deg"), "pitch_deg": o.get("pitch_deg"), "roll_deg": o.get("roll_deg"),
            "focal_px": o.get("focal_px"),
            "yaw_diff_deg": round(angle_diff_deg(float(o["yaw_deg"]), float(fit["yaw_deg"])), 3),
            "pitch_diff_deg": round(float(o["pitch_deg"]) - float(fit["pitch_deg"]), 3),
            "roll_diff_deg": round(float(o["roll_deg"]) - float(fit["roll_deg"]), 3),
        })
    return row


def _num(v: object, fmt: str) -> str:
    return format(float(v), fmt) if isinstance(v, (int, float)) else "-"


def table_row(photo: str, fit: dict, first: dict, second: dict, commit: str, load: str, bearing: float) -> str:
    if "error_m" not in first:
        result = f"failed: {first.get('failed', '')}"
        cells = [result, "-", "-", "-", "-"]
    else:
        ok_err = "yes" if first["error_m"] <= TARGET_ERROR_M else "no"
        cells = [f"{first['error_m']:.1f} ({ok_err}; radius95 {_num(first.get('radius95_m'), '.1f')} m, "
                 f"in region {first.get('in_region')}, in ellipse {first.get('in_ellipse')})",
                 str(first.get("status"))]
        angles = []
        for k in ("yaw", "pitch", "roll"):
            angles.append(f"{_num(first.get(f'{k}_deg'), '.2f')} / {float(fit[f'{k}_deg']):.2f} "
                          f"({_num(first.get(f'{k}_diff_deg'), '+.2f')})")
        cells.append("; ".join(angles))
        cells.append(f"{_num(first.get('focal_px'), '.1f')} / {float(fit['fx']):.1f}")
        cells.append(f"{_num(first.get('build_s'), '.1f')}, {_num(first.get('total_s'), '.1f')}")
    second_s = _num(second.get("total_s"), ".1f") if "error_m" in second else f"failed: {second.get('failed', '')}"
    if "error_m" in second and "error_m" in first and abs(second["error_m"] - first["error_m"]) > 0.01:
        second_s += f" (error {second['error_m']:.1f} m)"
    return ("| " + " | ".join([str(date.today()), commit, photo, f"{bearing:g}", *cells, second_s, load,
                               platform.machine()]) + " |\n")


HEADER = """# The real Finse photos located by `viper locate` (bench/photo_finse.py, issue 31)

Lens from `viper calibrate pose` on the 2019 frame (f, k1, k2 fitted to the ground-control points);
orientation unknown to the locator. `viper locate PHOTO --map DSM (4 m, EPSG:32632) --camera <fitted>
--near <250 m from the surveyed camera towards the bearing>,600 --truth <surveyed camera>`. Targets:
error <= 15 m to the surveyed camera, status ok, yaw / pitch / roll within 0.3 deg of the pose fit's.
First run with an empty --cache (the DSM's database built), second run the same command, cached.
Commit: the checkout of the viper that ran.

"""

COLUMNS = ["date", "commit", "photo", "bearing (deg)", "error (m) (target <= 15)", "status (target ok)",
           "yaw / pitch / roll: solved / pose fit (diff, target 0.3)", "focal (px): solved / fitted",
           "first run: build, total (s)", "second run: total (s)", "load", "machine"]
TABLE_HEADER = HEADER + "| " + " | ".join(COLUMNS) + " |\n" + "|---" * len(COLUMNS) + "|\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="folder for outputs (default: a temporary one)")
    ap.add_argument("--viper", type=Path, default=vision_finse.VIPER, help="the viper executable to measure")
    ap.add_argument("--offset-bearing", type=float, default=60.0,
                    help="direction (deg, true) from the camera to the search circle's centre")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed per locate")
    ap.add_argument("--dry-run", action="store_true", help="calibrate, then print the locate commands only")
    ap.add_argument("--no-record", action="store_true", help="do not append to bench/results/photo_finse.md")
    args = ap.parse_args()
    if not vision_finse.FINSE.is_dir():
        print(f"{vision_finse.FINSE} is absent; nothing to do")
        return 0
    if not args.viper.exists():
        raise SystemExit(f"--viper {args.viper}: not found")
    vision_finse.VIPER = args.viper  # the calibration runs with the viper under test
    work = args.work or Path(tempfile.mkdtemp(prefix="viper-photo-finse-"))
    work.mkdir(parents=True, exist_ok=True)
    commit = checkout_commit(args.viper)
    load_start = os.getloadavg()[0]
    camera, fits = vision_finse.calibrate(work)
    centre = near_centre(args.offset_bearing)
    print(f"surveyed camera {surveyed_lat_lon()}, search circle centre {centre} "
          f"({NEAR_OFFSET_M:.0f} m towards {args.offset_bearing:g} deg), radius {NEAR_RADIUS_M:.0f} m")
    answers: list[dict] = []
    pairs: list[tuple[str, dict, dict, dict]] = []
    for photo in vision_finse.PHOTOS:
        fit = fits[photo]
        print(f"{photo}: pose fit yaw {fit['yaw_deg']:.3f} pitch {fit['pitch_deg']:.3f} roll {fit['roll_deg']:.3f}")
        if args.dry_run:
            cmd = locate_command(args.viper, photo, camera, centre, work / f"cache-{photo[:4]}-NEW")
            print("$", " ".join(cmd), "   (twice, with a new empty cache folder: the second run finds it filled)")
            continue
        cache = Path(tempfile.mkdtemp(prefix=f"cache-{photo[:4]}-", dir=work))  # new and empty
        cmd = locate_command(args.viper, photo, camera, centre, cache)
        runs = []
        for attempt in ("first", "second"):
            answer, run = run_locate(cmd, args.timeout)
            row = {"photo": photo, "run": attempt, **score(answer, run, fit)}
            print(json.dumps(row), flush=True)
            runs.append(row)
            answers.append({**row, "answer": answer})
            write_text_atomic(work / "answers.jsonl", "".join(json.dumps(a) + "\n" for a in answers))
        pairs.append((photo, fit, runs[0], runs[1]))
    if args.dry_run:
        return 0
    load = f"{load_start:.1f}-{os.getloadavg()[0]:.1f}"
    text = "".join(table_row(photo, fit, first, second, commit, load, args.offset_bearing)
                   for photo, fit, first, second in pairs)
    if not args.no_record:
        append_result(RESULTS, TABLE_HEADER, text)
        print(f"appended to {RESULTS}; outputs in {work}")
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
