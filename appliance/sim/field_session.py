"""A whole simulated field session: a random place on the ``[sim] dem`` map, the twins started
there, the real drivers on them, and the session of :mod:`appliance.acquisition.session`.

The simulated truth comes back beside the session's result as a :class:`SimTruth`, so that the
demo and the tests measure the estimate against where the platform really stood.
:func:`run_field_traverse` is a rover's traverse: the same platform driven by the rover twin from
stop to stop, with the true place of every stop.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from appliance.acquisition.onboard import load_session_database
from appliance.acquisition.platform import platform_of
from appliance.acquisition.session import SessionResult, run_platform_session
from appliance.acquisition.traverse import run_traverse
from appliance.config import Config, PlatformConfig, PlatformKind, SimFaultsConfig
from appliance.errors import InputError
from appliance.sim.demo import DEMO_DEM, demo_database
from appliance.sim.platform import open_sim_platform
from appliance.terrain.dem import load_dem

if TYPE_CHECKING:
    from appliance.acquisition.traverse import TraverseResult
    from appliance.drivers.factory import Devices
    from appliance.logbook.live import Publisher
    from appliance.terrain.database import SkylineDatabase
    from appliance.terrain.dem import Dem


@dataclass(frozen=True)
class SimTruth:
    """Where and how the simulated platform stood (degrees; heading clockwise from true north)."""

    lat_deg: float
    lon_deg: float
    heading_deg: float
    tilt_north_deg: float
    tilt_east_deg: float
    mast_height_m: float


def random_position(dem: Dem, db: SkylineDatabase | None, rng: np.random.Generator,
                    margin_nodes: float = 20.0) -> tuple[float, float]:
    """(lat, lon) drawn uniformly inside the database's grid (or the DEM) away from its edges, on terrain."""
    for _ in range(1000):
        if db is not None:
            g = db.grid
            margin_nodes = min(margin_nodes, g.n_rows / 4, g.n_cols / 4)
            r = rng.uniform(margin_nodes, g.n_rows - margin_nodes)
            c = rng.uniform(margin_nodes, g.n_cols - margin_nodes)
            lon, lat = (float(v) for v in g.xy_to_lonlat(*g.rc_to_xy(r, c)))
        else:
            lon0, lat0, lon1, lat1 = dem.bounds_lonlat()
            lat = float(lat0 + (lat1 - lat0) * rng.uniform(0.25, 0.75))
            lon = float(lon0 + (lon1 - lon0) * rng.uniform(0.25, 0.75))
        if math.isfinite(float(dem.sample_lonlat(np.atleast_1d(lon), np.atleast_1d(lat))[0])):
            return lat, lon
    raise InputError("no position on terrain found in the map after 1000 draws")


def simulated_config(config: Config, dem: Dem, db: SkylineDatabase | None, rng: np.random.Generator,
                     faults: SimFaultsConfig | None = None) -> Config:
    """``config`` with ``[sim]`` at a random position of the map, heading, tripod tilt and seed."""
    lat, lon = random_position(dem, db, rng)
    sim = dataclasses.replace(
        config.sim,
        lat_deg=lat,
        lon_deg=lon,
        ground_elevation_m=None,
        heading_deg=float(rng.uniform(0.0, 360.0)),
        tilt_north_deg=float(rng.uniform(-2.0, 2.0)),
        tilt_east_deg=float(rng.uniform(-2.0, 2.0)),
        seed=int(rng.integers(1 << 30)),
        faults=config.sim.faults if faults is None else faults,
    )
    return dataclasses.replace(config, platform=PlatformConfig(PlatformKind.SIM), sim=sim)


def truth_of(config: Config) -> SimTruth:
    """The simulated truth of a ``[sim]`` configuration."""
    s = config.sim
    return SimTruth(s.lat_deg, s.lon_deg, s.heading_deg, s.tilt_north_deg, s.tilt_east_deg, s.mast_height_m)


def sim_database(config: Config, dem: Dem, cache_dir: Path) -> SkylineDatabase | None:
    """The skyline database of ``[session] database``; on the demo map without one, the demo's
    database built once in ``cache_dir``; otherwise None (the estimate is then skipped)."""
    db = load_session_database(config.session, dem)
    if db is None and config.sim.dem == DEMO_DEM:
        cache_dir.mkdir(parents=True, exist_ok=True)
        db = demo_database(dem, cache_dir)
    return db


def _sim_map(config: Config, out: Path, dem: Dem | None, db: SkylineDatabase | None,
             on_status: Callable[[str], None]) -> tuple[Dem, SkylineDatabase | None]:
    """The ``[sim] dem`` map and its database, unless the caller gave them."""
    dem = dem if dem is not None else load_dem(config.sim.dem)
    if db is None:
        on_status("loading the skyline database")
        db = sim_database(config, dem, out)
    return dem, db


def run_field_session(
    config: Config,
    out_dir: str | Path,
    seed: int | None = None,
    dem: Dem | None = None,
    faults: SimFaultsConfig | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    db: SkylineDatabase | None = None,
    publisher: Publisher | None = None,
) -> tuple[SessionResult, SimTruth]:
    """A whole simulated session at a random position of the ``[sim] dem`` map; the log goes to
    ``out_dir``.  Returns the session's result and the simulated truth.

    The platform is :func:`appliance.sim.platform.open_sim_platform`: the real drivers over the twins'
    wire protocols (ptys, fake I2C, a simulated V4L2 capture), faults from ``faults`` (else
    ``[sim.faults]``).  The skyline database is ``db``, else :func:`sim_database`.  Every logged
    message also goes to ``publisher`` (the live view), when given.
    """
    rng = np.random.default_rng(seed)
    out = Path(out_dir)
    dem, db = _sim_map(config, out, dem, db, on_status)
    sim_config = simulated_config(config, dem, db, rng, faults)
    result = run_platform_session(open_sim_platform, sim_config, out, db, should_stop, on_status,
                                  publisher)
    return result, truth_of(sim_config)


def on_map_fn(dem: Dem, db: SkylineDatabase | None, margin_nodes: float = 10.0) -> Callable[[float, float], bool]:
    """Whether (lat, lon) is on the DEM's terrain and inside the database's grid, ``margin_nodes`` from its
    edges (a rover's stop should not leave the map it is located on)."""

    def on_map(lat: float, lon: float) -> bool:
        if not math.isfinite(float(dem.sample_lonlat(np.atleast_1d(lon), np.atleast_1d(lat))[0])):
            return False
        if db is None:
            return True
        g = db.grid
        r, c = (float(v) for v in g.xy_to_rc(*g.lonlat_to_xy(lon, lat)))
        margin = min(margin_nodes, g.n_rows / 4, g.n_cols / 4)
        return margin <= r <= g.n_rows - 1 - margin and margin <= c <= g.n_cols - 1 - margin

    return on_map


def run_field_traverse(
    config: Config,
    out_dir: str | Path,
    n_stops: int,
    seed: int | None = None,
    dem: Dem | None = None,
    db: SkylineDatabase | None = None,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
    publisher: Publisher | None = None,
    on_open: Callable[[Devices], None] = lambda devices: None,
) -> tuple[TraverseResult, list[SimTruth]]:
    """A simulated traverse of ``n_stops`` stops from a random start on the ``[sim] dem`` map: the rover
    twin drives legs of ``[sim] leg_length_m`` in random directions between stops and reports them with
    ``[sim] odometry_sigma_m`` of noise.  Returns the traverse and the true place of every stop;
    ``on_open(devices)`` sees the simulated devices (and twins) once they are open."""
    if n_stops < 1:
        raise InputError(f"a traverse needs at least one stop, got {n_stops}")
    rng = np.random.default_rng(seed)
    out = Path(out_dir)
    dem, db = _sim_map(config, out, dem, db, on_status)
    sim_config = simulated_config(config, dem, db, rng)
    sim_config = dataclasses.replace(sim_config, traverse=dataclasses.replace(sim_config.traverse, stops=n_stops))
    truths: list[SimTruth] = []
    on_status("opening the devices")
    with open_sim_platform(sim_config, on_map=on_map_fn(dem, db)) as devices:
        on_open(devices)
        world, rover = devices.world, devices.rover  # type: ignore[attr-defined]

        def record_truth() -> None:
            truths.append(SimTruth(world.lat_deg, world.lon_deg, world.heading_deg, world.tilt_north_deg,
                                   world.tilt_east_deg, world.mast_height_m))

        def drive_on(stop: int) -> None:
            on_status(f"stop {stop} done: the rover drives on")
            rover.drive()
            record_truth()

        record_truth()
        result = run_traverse(platform_of(devices), sim_config, out, db, n_stops, should_stop, on_status, publisher,
                              on_stop_done=drive_on)
    return result, truths[: len(result.stops)]
