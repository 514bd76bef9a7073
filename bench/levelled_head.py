"""A levelled head's real errors: the estimator's defaults against every error such a head has at once.

Truth, as bench/estimator_accuracy.py draws it: a random point between grid nodes (on a node with a
skyline), its skyline from the dense reference renderer (tests/reference_render.py) at 1-degree
true azimuths, camera 1.5 m above the ground.  The measured skyline, per trial, in this order:

- occluders the map lacks: 0-3 blocks (trees, a mast, a building), each 2-12 deg of azimuth wide at
  a random azimuth, with a flat top 0.5-5 deg above the block's mean true elevation; the skyline
  there becomes max(truth, top): an occluder only ever raises it;
- residual tilt after levelling: pitch and roll each uniform in [-0.3, +0.3] deg; with h the
  platform's true heading (uniform in 0-360 deg) the elevation at true azimuth a changes by
  pitch * cos(a - h) + roll * sin(a - h);
- compass error uniform in +-3 deg: the sensor reads azimuth a where the true azimuth is a + err
  (as estimator_accuracy.measured_skyline), on 1-degree sensor azimuths;
- correlated noise: white Gaussian noise smoothed along azimuth by a circular Gaussian filter of
  sigma 6/sqrt(2) deg (the noise's autocorrelation is then a Gaussian of sigma 6 deg), rescaled to
  0.12 deg RMS, plus white noise of 0.03 deg RMS;
- missing: one contiguous block of 15-40 deg, then 3 % of all azimuths scattered over the rest (NaN).

Estimate: appliance.locating.position.locate with the defaults of EstimatorConfig(), as the session's
onboard estimate calls it (bench/session_chain.py).  Error: geodesic metres on the DEM's ellipsoid,
and cells (the geometric mean node spacing).  "ok" means the answer does not say ambiguous.  Each
trial has its own seed (np.random.default_rng(seed)), so any one can be rerun alone with
``--first SEED --trials 1``.

Targets: >= 97 % within two cells; of those, >= 90 % say ok; no answer beyond two cells says ok;
truth inside the region >= 95 %.  Truth inside the 95 % ellipse (appliance.locating.position.truth_in_ellipse)
and the stated radius (R95 = sqrt(5.991 * largest eigenvalue of result.covariance_m2)) are reported
where the estimator provides them, n/a otherwise.

    python bench/levelled_head.py [--map jacksboro|white-mountains] [--trials 60] [--first 1] [--no-append]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.config import EstimatorConfig  # noqa: E402
from appliance.estimator import SkylineGrid  # noqa: E402
from appliance.locating import position  # noqa: E402
from appliance.locating.position import Position, locate, skyline_grid, truth_in_region  # noqa: E402
from appliance.skyline import Skyline  # noqa: E402
from appliance.terrain.database import SkylineDatabase  # noqa: E402
from appliance.terrain.dem import Dem  # noqa: E402
from bench.estimator_accuracy import MAPS, between_nodes, map_database  # noqa: E402
from bench.results_file import append_result  # noqa: E402
from tests.reference_render import reference_skyline  # noqa: E402

CAMERA_HEIGHT_M = 1.5
TILT_DEG = 0.3
COMPASS_DEG = 3.0
NOISE_CORRELATION_DEG = 6.0
CORRELATED_RMS_DEG = 0.12
WHITE_RMS_DEG = 0.03
MISSING_BLOCK_DEG = (15, 40)
DROPOUT_FRACTION = 0.03
MAX_OCCLUDERS = 3
OCCLUDER_WIDTH_DEG = (2.0, 12.0)
OCCLUDER_RISE_DEG = (0.5, 5.0)
#: chi-square with two degrees of freedom at 95 %
CHI2_95_2D = 5.991

#: appliance.locating.position.truth_in_ellipse, where the estimator has it
TruthInEllipse = Callable[[SkylineDatabase, Position, tuple[float, float]], bool]
truth_in_ellipse: TruthInEllipse | None = getattr(position, "truth_in_ellipse", None)


@dataclass(frozen=True)
class Trial:
    seed: int
    error_m: float
    error_cells: float
    ambiguous: bool
    in_region: bool
    in_ellipse: bool | None  # None: no truth_in_ellipse
    r95_m: float | None  # None: no covariance stated
    region_cells: int
    estimate_s: float


def levelled_head_skyline(truth: np.ndarray, rng: np.random.Generator) -> Skyline:
    """The skyline a levelled head measures of ``truth`` (1-degree true azimuths): the module's model."""
    n = truth.size
    az = np.arange(n, dtype=float)
    scene = truth.copy()
    for _ in range(rng.integers(0, MAX_OCCLUDERS + 1)):
        start = rng.uniform(0.0, 360.0)
        covered = (az - start) % 360.0 < rng.uniform(*OCCLUDER_WIDTH_DEG)
        top = float(truth[covered].mean()) + rng.uniform(*OCCLUDER_RISE_DEG)
        scene[covered] = np.maximum(scene[covered], top)
    heading = rng.uniform(0.0, 360.0)
    pitch, roll = rng.uniform(-TILT_DEG, TILT_DEG, 2)
    rel = np.radians(az - heading)
    scene = scene + pitch * np.cos(rel) + roll * np.sin(rel)
    err = rng.uniform(-COMPASS_DEG, COMPASS_DEG)
    el = np.interp((az + err) % 360.0, az, scene, period=360.0)
    smooth = gaussian_filter1d(rng.normal(0.0, 1.0, n), NOISE_CORRELATION_DEG / math.sqrt(2.0), mode="wrap")
    el = el + smooth * (CORRELATED_RMS_DEG / np.sqrt(np.mean(smooth**2))) + rng.normal(0.0, WHITE_RMS_DEG, n)
    block = int(rng.integers(MISSING_BLOCK_DEG[0], MISSING_BLOCK_DEG[1] + 1))
    el[(rng.integers(0, n) + np.arange(block)) % n] = np.nan
    el[rng.choice(np.nonzero(np.isfinite(el))[0], int(round(DROPOUT_FRACTION * n)), replace=False)] = np.nan
    return Skyline(az, el)


def one_trial(seed: int, dem: Dem, db: SkylineDatabase, grid: SkylineGrid, cell_m: float,
              est: EstimatorConfig) -> Trial:
    rng = np.random.default_rng(seed)
    lat, lon = between_nodes(db, grid, rng)[2:]
    truth = reference_skyline(dem, lat, lon, CAMERA_HEIGHT_M)
    sky = levelled_head_skyline(truth, rng)
    pos = locate(db, sky, est.sigma_deg, est.heading_tolerance_deg, grid=grid, occlusion_weight=est.occlusion_weight,
                 map_sigma_m=est.map_vertical_sigma_m)
    _, _, err = dem.geod.inv(lon, lat, pos.lon, pos.lat)
    r = pos.result
    cov = getattr(r, "covariance_m2", None)
    return Trial(
        seed=seed, error_m=float(err), error_cells=float(err) / cell_m, ambiguous=r.ambiguous,
        in_region=truth_in_region(db, pos, (lat, lon)),
        in_ellipse=None if truth_in_ellipse is None else bool(truth_in_ellipse(db, pos, (lat, lon))),
        r95_m=None if cov is None else math.sqrt(CHI2_95_2D * float(np.linalg.eigvalsh(cov)[-1])),
        region_cells=int(r.region_nodes.size), estimate_s=r.elapsed_s,
    )


def trial_line(t: Trial) -> str:
    ellipse = "n/a" if t.in_ellipse is None else ("inside" if t.in_ellipse else "OUTSIDE")
    r95 = "n/a" if t.r95_m is None else f"{t.r95_m:.0f} m"
    return (f"seed {t.seed}: {t.error_m:7.1f} m ({t.error_cells:5.2f} cells), "
            f"{'ambiguous' if t.ambiguous else 'ok'}, truth {'inside' if t.in_region else 'OUTSIDE'} region, "
            f"ellipse {ellipse}, ± {r95} (95 %), region {t.region_cells} cells, "
            f"estimate {t.estimate_s * 1e3:.0f} ms")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--map", default="jacksboro", choices=sorted(MAPS))
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--first", type=int, default=1, help="seed of the first trial")
    ap.add_argument("--no-append", action="store_true", help="do not add the summary to the results file")
    args = ap.parse_args()
    dem, db = map_database(args.map)
    grid = skyline_grid(db)
    cell_m = float(np.sqrt(grid.dx_m * grid.dy_m))
    est = EstimatorConfig()
    t0 = time.monotonic()
    trials = []
    for seed in range(args.first, args.first + args.trials):
        trials.append(one_trial(seed, dem, db, grid, cell_m, est))
        print(trial_line(trials[-1]), flush=True)
    wall = time.monotonic() - t0
    cells = np.array([t.error_cells for t in trials])
    ok = ~np.array([t.ambiguous for t in trials])
    right = cells <= 2.0
    ellipse = ("n/a" if truth_in_ellipse is None else
               f"{100 * np.mean([bool(t.in_ellipse) for t in trials]):.1f} %")
    ok_if_right = f"{100 * ok[right].mean():.1f} %" if right.any() else "n/a"
    row = (
        f"| {date.today()} | {args.map} | {len(trials)} (from {args.first}) | {cell_m:.0f} m | "
        f"{100 * right.mean():.1f} % (>= 97) | {ok_if_right} (>= 90) | {int(np.sum(~right & ok))} (0) | "
        f"{100 * np.mean([t.in_region for t in trials]):.1f} % (>= 95) | {ellipse} | "
        f"{np.median([t.error_m for t in trials]):.1f} m | {np.median([t.region_cells for t in trials]):.0f} | "
        f"{1e3 * np.median([t.estimate_s for t in trials]):.0f} ms | {wall / 60:.1f} min, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f}, {platform.machine()} |\n"
    )
    print(row, end="")
    if args.no_append:
        return 0
    append_result(
        HERE / "results" / "levelled_head.md",
        "# A levelled head's real errors (bench/levelled_head.py)\n\n"
        "Truth from the dense reference ray march at random points between nodes, camera 1.5 m.  Measured "
        "skyline: 0-3 occluders the map lacks (2-12 deg wide, flat top 0.5-5 deg above the mean true skyline "
        "there, only raising it), residual tilt (pitch and roll each up to +-0.3 deg), compass error up to "
        "+-3 deg, noise correlated along azimuth (autocorrelation a Gaussian of sigma 6 deg, 0.12 deg RMS) plus "
        "white noise (0.03 deg RMS), one missing block of 15-40 deg and 3 % scattered dropouts.  Estimator: "
        "EstimatorConfig() defaults.  Cells: error over the geometric mean node spacing; ok: not ambiguous; "
        "ellipse: truth inside the stated 95 % ellipse (n/a where the estimator has none).  Medians over all "
        "trials.  Targets in brackets.\n\n"
        "| date | map | seeds | cell | within 2 cells | ok of those | wrong and ok | truth in region | "
        "truth in 95 % ellipse | median error | median region (cells) | estimate time | run |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        row,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
