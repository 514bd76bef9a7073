"""The appliance's estimate as the autopilot reads a position: the fields of ``GPS_INPUT`` or of
``VISION_POSITION_ESTIMATE``.  Pure: a :class:`PositionFix` in, the message's fields out (pymavlink
encodes them, :mod:`appliance.drivers.mavlink_reader` sends them).

``GPS_INPUT``:

- ``horiz_accuracy``: the RMS radial error of the estimate, ``sqrt(trace(covariance_m2))`` (DRMS:
  ``sqrt(sigma_east^2 + sigma_north^2)``), in metres.  A receiver's hAcc is of this kind; it is the
  1-sigma major axis times between 1 and sqrt(2).
- ``fix_type``: 3 (3D) for an estimate that says ok; 0 (no GPS) for one that does not (ambiguous, or
  without a covariance), sent only when ``output_ambiguous`` is set.
- ``ignore_flags``: altitude, HDOP, VDOP, velocities, speed accuracy and vertical accuracy are not
  measured and flagged ignored; ``horiz_accuracy`` is flagged ignored only when the estimate has no
  covariance.  ``satellites_visible`` is 0 and ``yaw`` 0 (none): nothing here is a satellite count
  or a GPS heading.
- time: ``time_usec`` the estimate's UTC time (Unix epoch), ``time_week``/``time_week_ms`` the same
  instant as GPS time (UTC + :data:`GPS_LEAP_SECONDS`).

``VISION_POSITION_ESTIMATE``: x north and y east (m) of the estimate from an origin in the autopilot's
local frame, its north/east covariance in the upper-triangular 6x6 pose covariance (row-major: [0]
x-x, [1] x-y, [6] y-y); z and the angles are not measured: z = 0 and angles 0 with variances of
:data:`UNMEASURED_VAR_M2` and :data:`UNMEASURED_VAR_RAD2`.
"""

from __future__ import annotations

import datetime as dt
import math

import numpy as np

from appliance.drivers.autopilot import PositionFix

#: GPS time runs ahead of UTC by the leap seconds since 1980 (18 since 2017-01-01)
GPS_LEAP_SECONDS = 18
GPS_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.timezone.utc)
SECONDS_PER_WEEK = 7 * 86400
#: GPS_FIX_TYPE values
FIX_NONE = 0
FIX_3D = 3
#: GPS_INPUT_IGNORE_FLAGS bits (common.xml)
IGNORE_ALT, IGNORE_HDOP, IGNORE_VDOP = 1, 2, 4
IGNORE_VEL_HORIZ, IGNORE_VEL_VERT, IGNORE_SPEED_ACCURACY = 8, 16, 32
IGNORE_HORIZONTAL_ACCURACY, IGNORE_VERTICAL_ACCURACY = 64, 128
#: what the appliance never measures
IGNORED_ALWAYS = (IGNORE_ALT | IGNORE_HDOP | IGNORE_VDOP | IGNORE_VEL_HORIZ | IGNORE_VEL_VERT
                  | IGNORE_SPEED_ACCURACY | IGNORE_VERTICAL_ACCURACY)
UNMEASURED_VAR_M2 = 1.0e4
UNMEASURED_VAR_RAD2 = math.pi ** 2
EARTH_RADIUS_M = 6_371_008.8


def horizontal_accuracy_m(covariance_m2: np.ndarray | None) -> float | None:
    """The RMS radial error sqrt(trace) of an (east, north) covariance (m); None without a finite one."""
    if covariance_m2 is None:
        return None
    cov = np.asarray(covariance_m2, dtype=np.float64)
    if cov.shape != (2, 2) or not np.all(np.isfinite(cov)) or np.trace(cov) < 0:
        return None
    return float(math.sqrt(np.trace(cov)))


def gps_time(time_ns: int) -> tuple[int, int]:
    """(GPS week, milliseconds into the week) of a UTC time (ns since the Unix epoch)."""
    since_ms = (time_ns // 1_000_000) - int(GPS_EPOCH.timestamp() * 1000) + GPS_LEAP_SECONDS * 1000
    week, ms = divmod(since_ms, SECONDS_PER_WEEK * 1000)
    return int(week), int(ms)


def gps_input_fields(fix: PositionFix, gps_id: int = 0) -> dict[str, float | int]:
    """The keyword arguments of pymavlink's ``gps_input_encode`` for ``fix``."""
    accuracy = horizontal_accuracy_m(fix.covariance_m2)
    good = fix.ok and accuracy is not None
    flags = IGNORED_ALWAYS | (0 if accuracy is not None else IGNORE_HORIZONTAL_ACCURACY)
    week, week_ms = gps_time(fix.time_ns)
    return {
        "time_usec": fix.time_ns // 1000, "gps_id": gps_id, "ignore_flags": flags,
        "time_week_ms": week_ms, "time_week": week, "fix_type": FIX_3D if good else FIX_NONE,
        "lat": int(round(fix.lat_deg * 1e7)), "lon": int(round(fix.lon_deg * 1e7)), "alt": 0.0,
        "hdop": 0.0, "vdop": 0.0, "vn": 0.0, "ve": 0.0, "vd": 0.0, "speed_accuracy": 0.0,
        "horiz_accuracy": 0.0 if accuracy is None else accuracy, "vert_accuracy": 0.0,
        "satellites_visible": 0, "yaw": 0,
    }


def north_east_m(lat_deg: float, lon_deg: float, origin_lat_deg: float, origin_lon_deg: float) -> tuple[float, float]:
    """(north, east) metres of a point from an origin on a local tangent plane (a sphere of the Earth's
    mean radius: under 0.5 % of the distance in error within tens of kilometres)."""
    north = math.radians(lat_deg - origin_lat_deg) * EARTH_RADIUS_M
    dlon = (lon_deg - origin_lon_deg + 180.0) % 360.0 - 180.0
    east = math.radians(dlon) * EARTH_RADIUS_M * math.cos(math.radians(0.5 * (lat_deg + origin_lat_deg)))
    return north, east


def origin_of(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """The (lat, lon) of the local frame's origin, given a place and its local (north, east) position."""
    lat0 = lat_deg - math.degrees(north_m / EARTH_RADIUS_M)
    lon0 = lon_deg - math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(0.5 * (lat_deg + lat0)))))
    return lat0, lon0


def vision_position_fields(fix: PositionFix, origin: tuple[float, float], reset_counter: int) -> dict[str, object]:
    """The keyword arguments of ``vision_position_estimate_encode`` for ``fix`` (requires a covariance)."""
    if fix.covariance_m2 is None:
        raise ValueError("VISION_POSITION_ESTIMATE needs the estimate's covariance")
    north, east = north_east_m(fix.lat_deg, fix.lon_deg, *origin)
    c = np.asarray(fix.covariance_m2, dtype=np.float64)  # (east, north)
    cov = [0.0] * 21
    cov[0], cov[1], cov[6] = float(c[1, 1]), float(c[0, 1]), float(c[0, 0])
    cov[11] = UNMEASURED_VAR_M2
    cov[15] = cov[18] = cov[20] = UNMEASURED_VAR_RAD2
    return {"usec": fix.time_ns // 1000, "x": north, "y": east, "z": 0.0, "roll": 0.0, "pitch": 0.0, "yaw": 0.0,
            "covariance": cov, "reset_counter": reset_counter % 256}
