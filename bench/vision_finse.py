"""Real photographs through the command line: the two Finse photos and the Puy de Sancy panorama.

Run: .venv/bin/python bench/vision_finse.py [--work DIR] [--no-position]   (needs ../shared/data)

Everything under test runs as `.venv/bin/viper` subprocesses, as a user would type it:

1. `viper calibrate pose` on the 2019 frame with the data set's ground-control points (stated
   intrinsics as the start; focal length, k1 and k2 fitted), then on the 2022 photo with the same
   points' pixels in that photo (tests/data/finse_2022_gcp_pixels.csv) and the fitted camera.
2. `viper skyline PHOTO --camera --orientation --step-deg 0.1` on both photos; the CSV is compared
   with the traced skyline (tests/data/finse_skyline_trace.csv) carried to true azimuth and
   elevation through the same camera: detected share of the traced columns inside the DSM (target
   >= 90 %), RMS (target <= 0.1 deg) and largest error (target <= 1 deg).
3. `viper skyline` on the Puy de Sancy panorama: share of 1-degree azimuths detected (target >= 85 %),
   overlay written for the eye.
4. Positioning, with the options a field user gives: `viper precompute` on the DSM over a box of
   +-200 m around the camera, nodes every 5 m (the DSM's own 4 m would be finer still; a 10 m grid
   samples the roof and the ground around the camera too coarsely), then per photo
   `viper estimate --heading-tolerance 2 --height H --sigma 0.05,0.2 --json`: H is the camera's
   height above the DSM's surface (the roof it stands on) from the pose fit of step 1, the sigma
   interval the photo's angular precision (the detector's 0.005-0.03 deg against the traced skyline
   at the low end, the pose fit's 3.7 px RMS, 0.15 deg at 1443 px per radian, at the high end).
   The error is measured to the surveyed camera (MANIFEST section 6), and whether it lies inside the
   region (target within 10 m, inside).  The same estimate with the default sigma interval
   (0.3-0.8 deg, sized for the appliance's own panoramas on 30-90 m maps) is recorded beside it.

Figures are appended to bench/results/vision_finse.md.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from pyproj import Transformer

REPO = Path(__file__).resolve().parents[1]
VIPER = REPO / ".venv" / "bin" / "viper"
DATA = REPO.parent / "shared" / "data"
FINSE = DATA / "photo_pose_dem" / "finse"
DSM = FINSE / "time_lapse_finse_DSM_midfilled.tif"
GCPS = FINSE / "GCPs_pointagev4.csv"
SANCY = DATA / "panorama" / "puydesancy_equirect_4096x2048.jpg"
TRACE = REPO / "tests" / "data" / "finse_skyline_trace.csv"
GCP_2022 = REPO / "tests" / "data" / "finse_2022_gcp_pixels.csv"
RESULTS = REPO / "bench" / "results" / "vision_finse.md"
sys.path.insert(0, str(REPO))
from appliance.atomic import write_text_atomic  # noqa: E402
from bench.results_file import append_result  # noqa: E402

SURVEYED = (419169.2, 6718421.3)  # camera_pos, EPSG:32632 (MANIFEST section 6)
PHOTOS = ("2019-05-24_12-00_ori.jpg", "2022-07-08.jpg")
BOX_M = 200  # half-width of the search box around the camera
SPACING_M = 5  # database node spacing
STATED_CAMERA = "[camera]\nwidth = 1920\nheight = 1080\nfx = 1484.0\nfy = 1484.0\ncx = 960.0\ncy = 540.0\n"


def viper(*args: str | Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    cmd = [str(VIPER), *(str(a) for a in args)]
    print("$", " ".join(cmd), flush=True)
    out = subprocess.run(cmd, capture_output=True, text=True)
    if check and out.returncode != 0:
        raise SystemExit(f"failed ({out.returncode}): {out.stderr.strip()}")
    return out


def gcps_for_2022(work: Path) -> Path:
    """The data set's GCP file with the pixels replaced by their positions in the 2022 photo."""
    pixels = {r["name"]: r for r in csv.DictReader(GCP_2022.open())}
    out = work / "gcp_2022.csv"
    dst = io.StringIO(newline="")
    with GCPS.open() as src:
        reader = csv.DictReader(src)
        writer = csv.DictWriter(dst, fieldnames=["name", "x_world", "y_world", "z_world", "x_img", "y_img"])
        writer.writeheader()
        for r in reader:
            if r["name"] in pixels:
                p = pixels[r["name"]]
                writer.writerow(
                    {
                        "name": r["name"],
                        "x_world": r["x_world"],
                        "y_world": r["y_world"],
                        "z_world": r["z_world"],
                        "x_img": p["u_px"],
                        "y_img": p["v_px"],
                    }
                )
    write_text_atomic(out, dst.getvalue())
    return out


def compare(photo: str, skyline_csv: Path, camera: Path, orientation: Path) -> dict[str, float]:
    """Detected share, RMS and largest error (deg) against the traced skyline inside the DSM."""
    from appliance.skyline import read_skyline_csv
    from appliance.vision.camera import pixels_to_directions
    from appliance.vision.intrinsics import load_intrinsics
    from appliance.vision.photo import read_orientation_file

    rows = [r for r in csv.DictReader(TRACE.open()) if r["photo"] == photo]
    u = np.array([float(r["u_px"]) for r in rows])
    v = np.array([float(r["v_px"]) for r in rows])
    in_dsm = np.array([r["in_dsm"] == "1" for r in rows])
    pose, _ = read_orientation_file(orientation)
    assert pose is not None
    az, el = pixels_to_directions(load_intrinsics(camera), pose, u, v)
    sky = read_skyline_csv(skyline_csv)
    order = np.argsort(sky.azimuth_deg)
    saz, sel = sky.azimuth_deg[order], sky.elevation_deg[order]
    step = float(np.median(np.diff(saz)))
    i = np.clip(np.floor(az / step).astype(int), 0, saz.size - 2)
    t = (az - saz[i]) / step
    det = sel[i] * (1 - t) + sel[i + 1] * t
    ok = np.isfinite(det) & in_dsm
    err = det[ok] - el[ok]
    return {
        "columns": int(in_dsm.sum()),
        "detected": float(ok.sum() / in_dsm.sum()),
        "rms_deg": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "max_deg": float(np.max(np.abs(err))) if err.size else float("nan"),
        "beyond_dsm_detected": float(np.isfinite(det[~in_dsm]).mean()) if (~in_dsm).any() else float("nan"),
    }


def calibrate(work: Path) -> tuple[Path, dict[str, dict]]:
    """Step 1: `viper calibrate pose` on the 2019 frame (focal length, k1, k2 fitted from the stated
    intrinsics), then on the 2022 photo with the fitted camera.  Returns the fitted camera file and
    each photo's fit (the JSON `viper calibrate pose --out` writes: yaw_deg, pitch_deg, roll_deg,
    camera_lat_deg, camera_lon_deg, camera_height_m, ...), keyed by the photo's file name."""
    write_text_atomic(work / "stated.toml", STATED_CAMERA)
    camera = work / "camera.toml"
    camera.unlink(missing_ok=True)
    viper(
        "calibrate",
        "pose",
        FINSE / PHOTOS[0],
        "--camera",
        work / "stated.toml",
        "--points",
        GCPS,
        "--crs",
        "EPSG:32632",
        "--refine",
        "f,k1,k2",
        "--camera-out",
        camera,
        "--out",
        work / "2019.json",
        "--force",
    )
    viper(
        "calibrate",
        "pose",
        FINSE / PHOTOS[1],
        "--camera",
        camera,
        "--points",
        gcps_for_2022(work),
        "--crs",
        "EPSG:32632",
        "--out",
        work / "2022.json",
        "--force",
    )
    return camera, {p: json.loads((work / f"{p[:4]}.json").read_text()) for p in PHOTOS}


SIGMA = "0.05,0.2"  # deg: the photo's angular precision, see the docstring


def position(
    work: Path, photo: str, skyline_csv: Path, fit: dict[str, float], db: Path, sigma: str | None = SIGMA
) -> dict[str, object]:
    to_utm = Transformer.from_crs(4326, 32632, always_xy=True)
    x, y = to_utm.transform(fit["camera_lon_deg"], fit["camera_lat_deg"])
    with rasterio.open(DSM) as ds:
        ground = float(next(ds.sample([(x, y)]))[0])
    height = fit["camera_height_m"] - ground
    args: list[str | Path] = [
        db,
        skyline_csv,
        "--heading-tolerance",
        "2",
        "--json",
        "--height",
        f"{height:.2f}",
        "--truth",
        f"{fit['camera_lat_deg']},{fit['camera_lon_deg']}",
    ]
    if sigma is not None:
        args += ["--sigma", sigma]
    out = viper("estimate", *args, check=False)
    record: dict[str, object] = {"height_m": height, "exit": out.returncode, "sigma": sigma or "default"}
    if out.returncode != 0:
        record["stderr"] = out.stderr.strip().splitlines()[-1] if out.stderr.strip() else ""
        return record
    est = json.loads(out.stdout.strip().splitlines()[0])
    err = float(np.hypot(est["x"] - SURVEYED[0], est["y"] - SURVEYED[1]))
    record.update(
        {
            "error_m": err,
            "area_m2": est["region"]["area_m2"],
            "ambiguous": est.get("ambiguous"),
            "status": est.get("status"),  # with --truth: ambiguous also when the truth is outside the region
            "radius95_m": est.get("radius95_m"),
            "sigma_deg": est.get("sigma_deg"),
            "heading_correction_deg": est.get("heading_correction_deg"),
        }
    )
    # the region's cells are (lat, lon) centres of database nodes; the truth is inside when it lies
    # in one of those cells
    size = est["region"]["cell_size_m"]
    half = (max(size) if isinstance(size, list) else float(size)) / 2.0
    cells = np.asarray(est["region"].get("cells") or [], dtype=np.float64).reshape(-1, 2)
    sx, sy = SURVEYED
    if cells.size:
        cx, cy = to_utm.transform(cells[:, 1], cells[:, 0])
        inside: object = bool(np.any((np.abs(np.asarray(cx) - sx) <= half) & (np.abs(np.asarray(cy) - sy) <= half)))
    else:
        inside = None
    record["truth_in_region"] = inside
    return record


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="folder for outputs (default: a temporary one)")
    ap.add_argument("--no-position", action="store_true", help="skip the database and estimates")
    args = ap.parse_args()
    if not FINSE.is_dir():
        print(f"{FINSE} is absent; nothing to do")
        return 0
    work = args.work or Path(tempfile.mkdtemp(prefix="viper-finse-"))
    work.mkdir(parents=True, exist_ok=True)
    camera, fits = calibrate(work)
    rows = []
    skylines = {}
    for photo in PHOTOS:
        out = work / f"{photo[:4]}_skyline.csv"
        t0 = time.perf_counter()
        viper(
            "skyline",
            FINSE / photo,
            "--camera",
            camera,
            "--orientation",
            work / f"{photo[:4]}.json",
            "--step-deg",
            "0.1",
            "--out",
            out,
            "--overlay",
            work / f"{photo[:4]}_overlay.png",
            "--force",
        )
        dt = time.perf_counter() - t0
        m = compare(photo, out, camera, work / f"{photo[:4]}.json")
        m["seconds"] = dt
        skylines[photo] = out
        print(f"{photo}: {m}")
        rows.append((photo, m))
    t0 = time.perf_counter()
    sancy_csv = work / "sancy.csv"
    viper(
        "skyline",
        SANCY,
        "--out",
        sancy_csv,
        "--overlay",
        work / "sancy_overlay.png",
        "--min-elevation-deg",
        "-30",
        "--max-elevation-deg",
        "30",
        "--force",
    )
    sancy_s = time.perf_counter() - t0
    from appliance.skyline import read_skyline_csv

    sancy = read_skyline_csv(sancy_csv).valid_fraction
    print(f"Puy de Sancy: {sancy:.1%} of 1-degree azimuths; overlay {work / 'sancy_overlay.png'}")
    positions: dict[str, dict[str, object]] = {}
    defaults: dict[str, dict[str, object]] = {}
    if not args.no_position:
        f = fits[PHOTOS[0]]
        to_utm = Transformer.from_crs(4326, 32632, always_xy=True)
        x, y = to_utm.transform(f["camera_lon_deg"], f["camera_lat_deg"])
        with rasterio.open(DSM) as ds:
            ground = float(next(ds.sample([(x, y)]))[0])
        db = work / "finse.viperdb"
        to_geo = Transformer.from_crs(32632, 4326, always_xy=True)
        w_, s_ = to_geo.transform(x - BOX_M, y - BOX_M)
        e_, n_ = to_geo.transform(x + BOX_M, y + BOX_M)
        bounds = f"{w_:.6f},{s_:.6f},{e_:.6f},{n_:.6f}"
        viper(
            "precompute",
            DSM,
            "--crs",
            "EPSG:32632",
            "--out",
            db,
            "--spacing",
            str(SPACING_M),
            f"--search-bounds={bounds}",
            "--height",
            f"{f['camera_height_m'] - ground:.2f}",
            "--azimuths",
            "720",
            "--force",
        )
        for photo in PHOTOS:
            positions[photo] = position(work, photo, skylines[photo], fits[photo], db)
            print(f"{photo} position: {positions[photo]}")
            defaults[photo] = position(work, photo, skylines[photo], fits[photo], db, sigma=None)
            print(f"{photo} position, default sigma: {defaults[photo]}")
    text: list[str] = []
    today = datetime.date.today()
    for photo, m in rows:
        p = positions.get(photo, {})
        err = f"{p['error_m']:.1f}" if "error_m" in p else (f"refused: {p.get('stderr', '')}" if p else "not run")
        if "error_m" in p:
            err += f" (region {float(p['area_m2']) / 1e4:.2f} ha"  # type: ignore[arg-type]
            d = defaults.get(photo, {})
            if "error_m" in d:
                err += f"; default sigma: {d['error_m']:.1f}, {float(d['area_m2']) / 1e4:.1f} ha"  # type: ignore[arg-type]
            err += ")"
        text.append(
            f"| {today} | Finse {photo} | {m['detected']:.1%} | {m['rms_deg']:.3f} | {m['max_deg']:.2f} |"
            f" {err} | {p.get('truth_in_region', '')} | {m['seconds']:.1f} |\n"
        )
    text.append(f"| {today} | Puy de Sancy | {sancy:.1%} of 1-deg azimuths | | | | | {sancy_s:.1f} |\n")
    append_result(
        RESULTS,
        "# Real photographs through the command line (Finse, Puy de Sancy)\n\n"
        "bench/vision_finse.py; targets: Finse detected >= 90 % of the traced columns inside the DSM,"
        " RMS <= 0.1 deg, max <= 1 deg; positioning within 10 m, truth inside the region;"
        " Puy de Sancy >= 85 % of 1-degree azimuths.\n\n"
        "| date | photo | detected | RMS (deg) | max (deg) | position error (m) | truth in region |"
        " detection (s) |\n|---|---|---|---|---|---|---|---|\n",
        "".join(text),
    )
    print(f"appended to {RESULTS}; outputs in {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
