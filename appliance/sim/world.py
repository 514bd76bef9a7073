"""The one simulated world every twin reads: true position, attitude, magnetic field and a clock.

Frames as :mod:`appliance.drivers.attitude`: world NWU (x north, y west, z up), head/body FLU
(x forward along the camera's optical axis, y left, z up).  The compass, the inclinometer and the
camera ride on the pan head: the head's true heading is ``heading_deg + stage_deg``.  The tripod's
tilt is a slope of the head plane (``tilt_north_deg`` up towards north, ``tilt_east_deg`` up
towards east); the head's pitch and roll follow from it at each heading.

The magnetic field is the World Magnetic Model's at the true position and date (pygeomag), seen by
the magnetometer through soft iron ``S`` and hard iron ``b``: ``raw = S @ field_body + b`` (tesla).
The clock is real time scaled by ``time_rate`` from ``start_utc``: the twins run in real threads.
"""

from __future__ import annotations

import datetime as dt
import math
import threading
import time
from dataclasses import dataclass, field

from appliance.drivers.attitude import Mat3, Vec3, body_to_world, matvec, transpose
from appliance.drivers.heading import _geomag

IDENTITY: Mat3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
EARTH_RADIUS_M = 6_371_008.8
STANDARD_GRAVITY_M_S2 = 9.80665


class SimClock:
    """UTC = ``start_utc`` + real elapsed time x ``time_rate``.

    ``monotonic_s`` and ``sleep`` are in simulated seconds too, so procedures that wait and time out
    run ``time_rate`` times faster than real time, at the pace of the twins.
    """

    def __init__(self, start_utc: dt.datetime, time_rate: float = 1.0) -> None:
        self.start_utc = start_utc
        self.time_rate = time_rate
        self._t0 = time.monotonic()

    def now(self) -> dt.datetime:
        return self.start_utc + dt.timedelta(seconds=(time.monotonic() - self._t0) * self.time_rate)

    def now_ns(self) -> int:
        return int(self.now().timestamp() * 1e9)

    def monotonic_s(self) -> float:
        return (time.monotonic() - self._t0) * self.time_rate

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of simulated time."""
        time.sleep(max(seconds, 0.0) / self.time_rate)


@dataclass
class SimWorld:
    lat_deg: float
    lon_deg: float
    ground_elevation_m: float
    mast_height_m: float = 1.5
    geoid_separation_m: float = -30.0
    heading_deg: float = 0.0  # true heading of the head at stage angle 0
    tilt_north_deg: float = 0.0
    tilt_east_deg: float = 0.0
    hard_iron_t: Vec3 = (0.0, 0.0, 0.0)
    soft_iron: Mat3 = IDENTITY
    clock: SimClock = field(default_factory=lambda: SimClock(dt.datetime(2026, 6, 1, 12, tzinfo=dt.timezone.utc)))
    stage_deg: float = 0.0

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        when = self.clock.start_utc
        gm = _geomag(when.year)
        from pygeomag import decimal_year_from_date

        r = gm.calculate(glat=self.lat_deg, glon=self.lon_deg, alt=self.alt_msl_m / 1000.0,
                         time=decimal_year_from_date(when))
        self.field_model = str(gm.model)
        self.declination_deg = float(r.d)
        # WMM gives north, east, down in nT: NWU tesla
        self.field_world_t: Vec3 = (r.x * 1e-9, -r.y * 1e-9, -r.z * 1e-9)

    @property
    def alt_msl_m(self) -> float:
        return self.ground_elevation_m + self.mast_height_m

    @property
    def head_heading_deg(self) -> float:
        return (self.heading_deg + self.stage_deg) % 360.0

    def head_tilt(self) -> tuple[float, float]:
        """(pitch_deg, roll_deg) of the head at its current heading (exact for the plane's slope)."""
        h = math.radians(self.head_heading_deg)
        gn, ge = math.tan(math.radians(self.tilt_north_deg)), math.tan(math.radians(self.tilt_east_deg))
        # slope along the forward direction and along the right-hand direction (heading + 90)
        fwd = gn * math.cos(h) + ge * math.sin(h)
        right = -gn * math.sin(h) + ge * math.cos(h)
        pitch = math.degrees(math.atan(fwd))
        roll = -math.degrees(math.atan(right * math.cos(math.radians(pitch))))
        return pitch, roll

    def body_to_world(self) -> Mat3:
        pitch, roll = self.head_tilt()
        return body_to_world(self.head_heading_deg, pitch, roll)

    def accel_body_g(self) -> Vec3:
        """What a resting accelerometer on the head reads (g)."""
        return matvec(transpose(self.body_to_world()), (0.0, 0.0, 1.0))

    def field_body_raw_t(self) -> Vec3:
        """What the head's magnetometer reads (tesla), hard and soft iron included."""
        b = matvec(transpose(self.body_to_world()), self.field_world_t)
        s = matvec(self.soft_iron, b)
        return (s[0] + self.hard_iron_t[0], s[1] + self.hard_iron_t[1], s[2] + self.hard_iron_t[2])

    def move_to(self, lat_deg: float, lon_deg: float, ground_elevation_m: float, heading_deg: float,
                tilt_north_deg: float, tilt_east_deg: float) -> None:
        """The platform driven to a new place (a rover's stop): position, ground, heading and the slope
        it stands on.  The magnetic field keeps the start's (a few hundred metres change it by less
        than the magnetometer resolves)."""
        with self.lock:
            self.lat_deg, self.lon_deg, self.ground_elevation_m = lat_deg, lon_deg, ground_elevation_m
            self.heading_deg, self.tilt_north_deg, self.tilt_east_deg = heading_deg, tilt_north_deg, tilt_east_deg

    def offset_position(self, north_m: float, east_m: float) -> tuple[float, float]:
        """(lat, lon) of a point ``north_m``, ``east_m`` from the true position."""
        lat = self.lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon
