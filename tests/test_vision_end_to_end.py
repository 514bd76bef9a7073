"""End to end: a synthetic panorama from a position on jacksboro -> viper skyline -> the estimator."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from appliance.cli.main import main
from appliance.skyline import read_skyline_csv
from appliance.vision.panorama import save_panorama
from appliance.vision.synth import dem_skyline_fn, render_panorama

LAT, LON = 36.62, -84.22


def test_synthetic_jacksboro_panorama_to_skyline_csv(tmp_path: Path) -> None:
    from appliance.terrain.dem import load_dem
    from appliance.terrain.horizon import render_skyline

    dem = load_dem("jacksboro")
    fn = dem_skyline_fn(dem, LAT, LON, 1.5)
    sp = render_panorama(fn, np.random.default_rng(0), px_per_rad=557.0, height_px=300, weather="hazy")
    pano = tmp_path / "pano.png"
    save_panorama(sp.panorama, pano)
    csv = tmp_path / "sky.csv"
    assert main(["skyline", str(pano), "--out", str(csv)]) == 0
    sky = read_skyline_csv(csv)
    ref = render_skyline(dem, LAT, LON, height_m=1.5)
    ok = sky.valid & np.isfinite(ref.elevation_deg)
    assert ok.mean() >= 0.8
    assert math.sqrt(float(np.mean((sky.elevation_deg[ok] - ref.elevation_deg[ok]) ** 2))) <= 0.3

    # the detected skyline locates the camera on a database of the map around it
    from appliance.config import EstimatorConfig
    from appliance.locating.position import locate, truth_error_m
    from appliance.terrain.database import build_database, load_database

    db_path = tmp_path / "around.viperdb"
    build_database(dem, db_path, search_bounds=(LON - 0.03, LAT - 0.025, LON + 0.03, LAT + 0.025), progress=None)
    db = load_database(db_path, dem)
    cfg = EstimatorConfig()
    pos = locate(db, sky, cfg.sigma_deg, cfg.heading_tolerance_deg, occlusion_weight=cfg.occlusion_weight)
    cell_m = math.hypot(db.grid.dx_m, db.grid.dy_m)
    assert truth_error_m(db, pos, (LAT, LON)) < 2.0 * cell_m
    assert abs(pos.result.heading_correction_deg) < 1.0  # the synthetic panorama's north is true north
