"""Same results before and after a refactor: a fixed set of outputs to capture on each checkout and compare.

Only stable entry points are used, so that modules can move inside ``appliance/``: the CLI as
``python -m appliance.cli.main`` and the package's top-level public names (``from appliance import ...``).
Run it with the checkout as the working folder and on PYTHONPATH::

    cd CHECKOUT && PYTHONPATH=CHECKOUT python bench/same_results.py --out DIR
    python bench/same_results.py --compare DIR_A DIR_B      # exit 1 if any file differs

It writes into DIR:

- ``demo_<seed>.txt``: stdout and exit status of ``viper demo --skyline-only --seed SEED`` (seeds 11, 12,
  13; its files go to DIR/work/demo).  Masked, not dropped: the work folder's path becomes ``<work>`` and
  the estimate's wall time ``in N ms`` becomes ``in <ms> ms``.  (The full simulated session, plain
  ``viper demo``, is not used: it runs in real time on threads, and its GPS fix count, log name and
  timings change from run to run.)
- ``database.sha256``: sha256 of two builds of the same ``viper precompute`` (SainteHelens.dem, the USGS
  ASCII quadrangle from ../shared/data, 159,264 nodes, ~7 s): equal hashes show the build is
  deterministic.
- ``accuracy.txt``: 30 trials at fixed random points between the nodes of that database (seed 5): the
  skyline rendered exactly there (``render_skyline``), seeded noise added (Gaussian 0.1 deg, a compass
  error up to +-2 deg, a 20-degree missing block), ``locate`` with the configuration's estimator
  defaults; per trial the truth, the estimate to 1e-7 deg, the error in m, the status and the region.

DIR/work is removed at the end unless ``--keep-work``.
"""

from __future__ import annotations

import argparse
import difflib
import hashlib
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEMO_SEEDS = (11, 12, 13)
DEM_NAME = "dem_usgs_ascii/SainteHelens.dem"
TRIALS = 30
TRIAL_SEED = 5
NOISE_DEG = 0.1
COMPASS_DEG = 2.0
MISSING_BLOCK_DEG = 20
CHI2_95_2D = 5.991
DIFF_LINES = 12


def viper(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the CLI from the checkout in the working folder, as the console script ``viper`` would."""
    return subprocess.run([sys.executable, "-m", "appliance.cli.main", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": os.getcwd()}, check=False)


def checked(p: subprocess.CompletedProcess[str], what: str) -> None:
    if p.returncode != 0:
        sys.exit(f"{what}: exit status {p.returncode}\n{p.stdout}{p.stderr}")


def demo_outputs(out: Path, work: Path) -> None:
    folder = work / "demo"
    for seed in DEMO_SEEDS:
        p = viper("demo", "--skyline-only", "--seed", str(seed), "--out", str(folder))
        text = p.stdout.replace(str(folder), "<work>")
        text = re.sub(r"\bin \d+ ms\b", "in <ms> ms", text)
        text += f"exit status {p.returncode}\n"
        if p.returncode != 0:
            text += "stderr:\n" + p.stderr
        (out / f"demo_{seed}.txt").write_text(text)
        print(f"  demo seed {seed}: exit status {p.returncode}", file=sys.stderr)


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def database_outputs(out: Path, work: Path, dem_path: Path) -> Path:
    """Build the database twice; keep the first for the accuracy run."""
    lines = []
    paths = [work / "first.viperdb", work / "second.viperdb"]
    for path in paths:
        checked(viper("precompute", str(dem_path), "--out", str(path), "--force"), "viper precompute")
        lines.append(f"{sha256_of(path)}  {DEM_NAME} build {len(lines) + 1}")
    lines.append("deterministic" if lines[0].split()[0] == lines[1].split()[0] else "NOT deterministic")
    paths[1].unlink()
    (out / "database.sha256").write_text("\n".join(lines) + "\n")
    return paths[0]


def accuracy_outputs(out: Path, dem_path: Path, db_path: Path) -> None:
    from appliance import Config, Skyline, load_database, load_dem, locate, render_skyline

    est = Config().estimator
    dem = load_dem(dem_path)
    db = load_database(db_path, dem)
    g = db.grid
    rng = np.random.default_rng(TRIAL_SEED)
    lines = [f"# {DEM_NAME}: {g.n_rows} x {g.n_cols} nodes, {g.dx_m:g} x {g.dy_m:g} m; seed {TRIAL_SEED}; "
             f"noise {NOISE_DEG} deg, compass +-{COMPASS_DEG} deg, missing block {MISSING_BLOCK_DEG} deg; "
             f"locate: sigma {est.sigma_deg}, heading tolerance {est.heading_tolerance_deg}, "
             f"occlusion weight {est.occlusion_weight}, map sigma {est.map_vertical_sigma_m} m",
             "# i  true_x true_y  true_lat true_lon  est_lat est_lon  error_m  status ambiguous  region_m2 cells  "
             "heading_corr_deg  r95_m  valid  notes"]
    for i in range(TRIALS):
        while True:  # a point between nodes, three from the edges, all four neighbouring nodes with a skyline
            r = rng.uniform(3, g.n_rows - 4)
            c = rng.uniform(3, g.n_cols - 4)
            r0, c0 = int(r), int(c)
            nodes = [(r0 + a) * g.n_cols + c0 + b for a in (0, 1) for b in (0, 1)]
            if np.all(np.isfinite(db.offset_deg[nodes])):
                break
        x, y = (float(v) for v in g.rc_to_xy(r, c))
        lon, lat = (float(v) for v in g.xy_to_lonlat(x, y))
        truth = render_skyline(dem, lat, lon, height_m=db.height_m)
        az = np.asarray(truth.azimuth_deg, dtype=float)
        err = rng.uniform(-COMPASS_DEG, COMPASS_DEG)
        el = np.interp((az + err) % 360.0, az, truth.elevation_deg, period=360.0) + rng.normal(0.0, NOISE_DEG, az.size)
        el[(rng.integers(0, az.size) + np.arange(MISSING_BLOCK_DEG)) % az.size] = np.nan
        pos = locate(db, Skyline(az, el), est.sigma_deg, est.heading_tolerance_deg,
                     occlusion_weight=est.occlusion_weight, map_sigma_m=est.map_vertical_sigma_m)
        res = pos.result
        _, _, dist = dem.geod.inv(lon, lat, pos.lon, pos.lat)
        cov = res.covariance_m2
        r95 = "none" if cov is None else f"{math.sqrt(CHI2_95_2D * float(np.linalg.eigvalsh(cov)[-1])):.3f}"
        lines.append(
            f"{i:2d}  {x:.3f} {y:.3f}  {lat:.7f} {lon:.7f}  {pos.lat:.7f} {pos.lon:.7f}  {float(dist):.3f}  "
            f"{'ambiguous' if res.ambiguous else 'ok'} {res.ambiguous}  {res.region_area_m2:.1f} "
            f"{res.region_nodes.size}  {res.heading_correction_deg:+.3f}  {r95}  {res.n_valid}  "
            f"{' | '.join(res.notes) or '-'}")
    (out / "accuracy.txt").write_text("\n".join(lines) + "\n")


def capture(out: Path, keep_work: bool) -> int:
    import appliance

    here = Path.cwd().resolve()
    where = Path(appliance.__file__).resolve()
    if here not in where.parents:
        sys.exit(f"appliance is imported from {where}, not from the working folder {here}: "
                 "run from the checkout with PYTHONPATH set to it")
    print(f"appliance from {where}", file=sys.stderr)
    dem_path = here.parent / "shared" / "data" / DEM_NAME
    if not dem_path.exists():
        sys.exit(f"{dem_path}: not found (expected ../shared/data beside the checkout)")
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    t0 = time.monotonic()
    demo_outputs(out, work)
    print(f"  demos done at {time.monotonic() - t0:.0f} s", file=sys.stderr)
    db_path = database_outputs(out, work, dem_path)
    print(f"  databases done at {time.monotonic() - t0:.0f} s", file=sys.stderr)
    accuracy_outputs(out, dem_path, db_path)
    print(f"  accuracy done at {time.monotonic() - t0:.0f} s", file=sys.stderr)
    if not keep_work:
        shutil.rmtree(work)
    return 0


def compare(a: Path, b: Path) -> int:
    names = sorted({p.name for d in (a, b) for p in d.iterdir() if p.is_file()})
    if not names:
        print(f"no files in {a} or {b}")
        return 2
    bad = 0
    for name in names:
        pa, pb = a / name, b / name
        if not (pa.exists() and pb.exists()):
            print(f"{name}: missing in {b if pa.exists() else a}")
            bad += 1
            continue
        la, lb = pa.read_text().splitlines(), pb.read_text().splitlines()
        if la == lb:
            print(f"{name}: identical")
            continue
        bad += 1
        print(f"{name}: differs")
        diff = [d for d in difflib.unified_diff(la, lb, str(pa), str(pb), n=0, lineterm="")
                if not d.startswith("@@")]
        for line in diff[:DIFF_LINES]:
            print(f"    {line}")
        if len(diff) > DIFF_LINES:
            print(f"    ... ({len(diff) - DIFF_LINES} more diff lines)")
    print("all identical" if bad == 0 else f"{bad} of {len(names)} files differ")
    return 0 if bad == 0 else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", type=Path, help="folder to write the outputs into (cwd and PYTHONPATH: the checkout)")
    g.add_argument("--compare", type=Path, nargs=2, metavar=("DIR_A", "DIR_B"), help="compare two output folders")
    ap.add_argument("--keep-work", action="store_true", help="keep DIR/work (databases, demo files)")
    args = ap.parse_args()
    if args.compare:
        return compare(*args.compare)
    return capture(args.out.resolve(), args.keep_work)


if __name__ == "__main__":
    sys.exit(main())
