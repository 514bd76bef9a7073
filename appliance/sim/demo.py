"""The demo map (matplotlib's embedded jacksboro DEM) and its skyline database, and the
skyline-only demo: a skyline seen from a random point between grid nodes, read by a noisy, partly
occluded sensor with a compass error, then located."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.bodies import geodesic_distance_m
from appliance.config import EstimatorConfig
from appliance.estimator import estimate
from appliance.locating.position import Position, place, skyline_grid
from appliance.outputs.files import write_map_layers, write_png
from appliance.skyline import Skyline, write_skyline_csv
from appliance.terrain.database import SkylineDatabase, build_database, load_database
from appliance.terrain.dem import Dem, load_dem
from appliance.terrain.horizon import render_skyline

#: the DEM of ``viper demo`` and of the simulated platform by default
DEMO_DEM = "jacksboro"


@dataclass(frozen=True)
class DemoResult:
    position: Position
    truth_lat: float
    truth_lon: float
    error_m: float
    compass_error_deg: float
    skyline_path: Path
    picture_path: Path
    db: SkylineDatabase
    #: the map's layers beside the picture (:func:`appliance.outputs.files.write_map_layers`)
    layer_paths: tuple[Path, ...] = ()


def demo_database(dem: Dem, out_dir: Path) -> SkylineDatabase:
    """The demo map's database, built once and kept beside the demo's outputs."""
    path = out_dir / f"{DEMO_DEM}.viperdb"
    if path.exists():
        try:
            return load_database(path, dem)
        except Exception:  # a stale or foreign file: rebuild it
            path.unlink()
    build_database(dem, path)
    return load_database(path, dem)


def sensor_reading(true_el: np.ndarray, rng: np.random.Generator, noise_deg: float = 0.2,
                   compass_error_deg: float = 0.0, occluded_deg: int = 25, dropouts: int = 11) -> Skyline:
    """What the platform reports: azimuth a (its heading sensor's) where the truth is at a + error."""
    az = np.arange(true_el.size, dtype=float)
    el = np.interp((az + compass_error_deg) % 360.0, az, true_el, period=360.0) + rng.normal(0, noise_deg, az.size)
    start = int(rng.integers(0, az.size))
    el[(start + np.arange(occluded_deg)) % az.size] = np.nan
    el[rng.choice(az.size, dropouts, replace=False)] = np.nan
    return Skyline(az, el)


def run_demo(out_dir: str | Path = "viper-demo", seed: int | None = None,
             estimator: EstimatorConfig | None = None) -> DemoResult:
    """A synthetic noisy skyline at a random point of the demo map, located with ``estimator``
    (default: the configuration's defaults); the skyline, a picture and the map's layers (``estimate-*``:
    posteriors as GeoTIFF, region and points as GeoJSON with their QGIS styles) in ``out_dir``."""
    cfg = EstimatorConfig() if estimator is None else estimator
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    dem = load_dem(DEMO_DEM)
    db = demo_database(dem, out)
    g = db.grid
    while True:
        r, c = rng.uniform(20, g.n_rows - 20), rng.uniform(20, g.n_cols - 20)
        lon, lat = g.xy_to_lonlat(*g.rc_to_xy(r, c))
        if np.isfinite(dem.sample_lonlat(np.atleast_1d(lon), np.atleast_1d(lat))[0]):
            break
    truth = render_skyline(dem, float(lat), float(lon), height_m=1.5)
    compass = float(rng.uniform(-4.0, 4.0))
    sky = sensor_reading(truth.elevation_deg, rng, compass_error_deg=compass)
    sky_path = out / "skyline.csv"
    write_skyline_csv(sky, sky_path)
    res = estimate(skyline_grid(db), sky.azimuth_deg, sky.elevation_deg, cfg.sigma_deg, cfg.heading_tolerance_deg)
    res_pos = place(db, res, str(sky_path))
    err = geodesic_distance_m(res_pos.lat, res_pos.lon, float(lat), float(lon), dem.body)
    pic = out / "estimate.png"
    write_png(db, res_pos, sky, pic, truth=(float(lat), float(lon)))
    layers = write_map_layers(db, res_pos, out, "estimate", truth=(float(lat), float(lon)))
    return DemoResult(res_pos, float(lat), float(lon), float(err), compass, sky_path, pic, db, layers)
