"""The skyline seen from one viewpoint: elevation of the highest terrain along each azimuth.

Rays leave the viewpoint as straight lines of an azimuthal equidistant projection centred on it,
which are geodesics with exact distances, so azimuths are true-north azimuths whatever the DEM's
CRS (grid convergence and metres-per-degree are handled by the projection).  Terrain is sampled
bilinearly on the schedule of :func:`appliance.estimator.raycast.ray_distances`: a fiftieth of a cell
near the eye, growing with distance to a quarter cell.  The apparent drop of a target at distance d
is d^2 / (2 R_eff), with R_eff = R / (1 - k) folding the body's curvature and atmospheric
refraction k into one radius.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import CRS, Transformer

from appliance.errors import DemError
from appliance.estimator.raycast import ray_distances
from appliance.skyline import Skyline
from appliance.terrain.dem import Dem

DEFAULT_HEIGHT_M = 1.5
DEFAULT_MAX_RANGE_M = 60_000.0


@dataclass(frozen=True)
class Horizon(Skyline):
    """A rendered skyline, with the range (m) of the terrain point that forms it per azimuth."""

    distance_m: np.ndarray = field(default_factory=lambda: np.empty(0))
    ground_m: float = float("nan")


def local_aeqd(dem: Dem, lat: float, lon: float) -> CRS:
    """Azimuthal equidistant CRS centred on (lat, lon) on the DEM's ellipsoid."""
    ell = dem.crs.ellipsoid
    a = ell.semi_major_metre if ell is not None else dem.body.semi_major_m
    b = ell.semi_minor_metre if ell is not None else dem.body.semi_major_m
    return CRS.from_proj4(f"+proj=aeqd +lat_0={float(lat)!r} +lon_0={float(lon)!r} +a={a!r} +b={b!r} +units=m +no_defs")


def render_skyline(
    dem: Dem,
    lat: float,
    lon: float,
    height_m: float = DEFAULT_HEIGHT_M,
    azimuths_deg: np.ndarray | None = None,
    max_range_m: float | None = None,
    refraction: float | None = None,
    step_m: float | None = None,
) -> Horizon:
    """Render the skyline from (lat, lon) at ``height_m`` above the ground.

    Returns elevation angles (degrees above the local horizontal) at ``azimuths_deg`` (degrees
    clockwise from true north; default 0..359).  Azimuths along which no terrain lies within the
    map and the range are NaN.
    """
    az = np.arange(360.0) if azimuths_deg is None else np.asarray(azimuths_deg, dtype=float)
    max_range = DEFAULT_MAX_RANGE_M if max_range_m is None else float(max_range_m)
    if not np.isfinite(lat) or not -90.0 <= lat <= 90.0:
        raise DemError(f"latitude {lat} outside [-90, 90]")
    ground = float(dem.sample_lonlat(np.array([lon]), np.array([lat]))[0])
    if not np.isfinite(ground):
        raise DemError(f"{dem.source}: viewpoint {lat:.6f}, {lon:.6f} is off the map or on nodata")
    reach = min(max_range, _farthest_corner_m(dem, lat, lon))
    dist = ray_distances(min(dem.resolution_m()), reach, step_m)
    if dist.size == 0:
        raise DemError(f"{dem.source}: a reach of {reach:.3g} m holds no sample of the map (its cells are "
                       f"{min(dem.resolution_m()):.3g} m)")
    r_eff = dem.body.effective_radius_m(refraction)
    z_eye = ground + height_m
    to_dem = Transformer.from_crs(local_aeqd(dem, lat, lon), dem.crs, always_xy=True)

    elev = np.full(az.shape, np.nan)
    far = np.full(az.shape, np.nan)
    chunk = max(1, 2_000_000 // max(dist.size, 1))
    for start in range(0, az.size, chunk):
        a = np.radians(az[start : start + chunk])[:, None]
        ex = dist[None, :] * np.sin(a)
        ny = dist[None, :] * np.cos(a)
        x, y = to_dem.transform(ex, ny)
        z = dem.sample(np.asarray(x), np.asarray(y))
        tan = (z - z_eye - dist**2 / (2.0 * r_eff)) / dist
        valid = np.isfinite(tan)
        any_valid = valid.any(axis=1)
        best = np.argmax(np.where(valid, tan, -np.inf), axis=1)
        rows = np.arange(best.size)
        e = np.degrees(np.arctan(tan[rows, best]))
        elev[start : start + chunk] = np.where(any_valid, e, np.nan)
        far[start : start + chunk] = np.where(any_valid, dist[best], np.nan)
    return Horizon(az, elev, distance_m=far, ground_m=ground)


def _farthest_corner_m(dem: Dem, lat: float, lon: float) -> float:
    """Geodesic distance (m) from the viewpoint to the farthest corner of the map (no bound on a
    map of the whole body)."""
    if dem.whole_body:
        return float("inf")
    left, bottom, right, top = dem.bounds_xy()
    cx = np.array([left, right, left, right, (left + right) / 2])
    cy = np.array([bottom, bottom, top, top, (bottom + top) / 2])
    clon, clat = dem.xy_to_lonlat(cx, cy)
    _, _, d = dem.geod.inv(np.full(cx.size, lon), np.full(cx.size, lat), clon, clat)
    return float(np.max(d)) if np.all(np.isfinite(d)) else DEFAULT_MAX_RANGE_M
