"""The simulated rover: drives the simulated platform from stop to stop and reports each leg in the
odometry line protocol (:mod:`appliance.drivers.odometry`) over a :class:`PtyPort`.

A leg has a random length in ``[sim] leg_length_m`` and a random direction, redrawn until its end
stands on the map (``on_map``, e.g. inside the skyline database's grid away from its edges); the
world's position, ground height, heading (the direction driven) and the slope it stops on change
accordingly.  The line reports the leg with Gaussian noise of ``[sim] odometry_sigma_m`` per axis and
that sigma, as a wheel odometry or a visual odometry would.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from appliance.config import SimConfig
from appliance.drivers.odometry import OdometryReport, format_line
from appliance.errors import InputError
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimWorld

#: a leg whose end is off the map is drawn again, at most this many times
MAX_DRAWS = 500


@dataclass(frozen=True)
class Leg:
    """One leg driven: the true displacement (m, east and north), where it ended and what was reported."""

    east_m: float
    north_m: float
    lat_deg: float
    lon_deg: float
    report: OdometryReport


class RoverTwin:
    """Moves ``world`` along random legs and writes one odometry line per stop to ``port``."""

    def __init__(self, world: SimWorld, port: PtyPort, sim: SimConfig, ground_m: Callable[[float, float], float],
                 on_map: Callable[[float, float], bool], seed: int) -> None:
        self.world, self.port, self.sim = world, port, sim
        self.ground_m, self.on_map = ground_m, on_map
        self.rng = np.random.default_rng(seed)
        self.stop_id = 0
        self.legs: list[Leg] = []

    def plan_leg(self) -> tuple[float, float, float, float]:
        """(east_m, north_m, lat, lon) of a random leg from the world's position ending on the map."""
        lo, hi = self.sim.leg_length_m
        for _ in range(MAX_DRAWS):
            length = float(self.rng.uniform(lo, hi))
            bearing = float(self.rng.uniform(0.0, 2.0 * math.pi))
            east, north = length * math.sin(bearing), length * math.cos(bearing)
            lat, lon = self.world.offset_position(north, east)
            if self.on_map(lat, lon) and math.isfinite(self.ground_m(lat, lon)):
                return east, north, lat, lon
        raise InputError(f"the simulated rover found no leg of {lo:g}-{hi:g} m ending on the map in {MAX_DRAWS} draws")

    def drive(self) -> Leg:
        """Drive one leg, stop, and send its odometry line; returns the leg."""
        east, north, lat, lon = self.plan_leg()
        heading = math.degrees(math.atan2(east, north)) % 360.0 if (east or north) else self.world.heading_deg
        tilt_n, tilt_e = (float(v) for v in self.rng.uniform(-2.0, 2.0, 2))
        self.world.move_to(lat, lon, self.ground_m(lat, lon), heading, tilt_n, tilt_e)
        sigma = self.sim.odometry_sigma_m
        noise_e, noise_n = (float(v) for v in self.rng.normal(0.0, sigma, 2)) if sigma > 0 else (0.0, 0.0)
        self.stop_id += 1
        report = OdometryReport(self.stop_id, east + noise_e, north + noise_n, sigma)
        self.port.write(format_line(report))
        leg = Leg(east, north, lat, lon, report)
        self.legs.append(leg)
        return leg
