"""An independent, dense and exact skyline renderer: the oracle for the production renderer.

Geodesic rays (pyproj's Geod.fwd on the DEM's ellipsoid), samples every fiftieth of a cell out to
NEAR_M (where a horizon a cell away moves by degrees within the cell) and every quarter cell beyond,
bilinear terrain on the DEM's own grid, and the exact elevation angle on a sphere of effective
radius R / (1 - k) (no parabolic approximation).
"""

from __future__ import annotations

import numpy as np

from appliance.terrain.dem import Dem

#: Out to here (or four cells, if further) the march steps a fiftieth of a cell.
NEAR_M = 3000.0


def reference_skyline(
    dem: Dem,
    lat: float,
    lon: float,
    height_m: float = 1.5,
    azimuths_deg: np.ndarray | None = None,
    max_range_m: float = 60_000.0,
    refraction: float | None = None,
) -> np.ndarray:
    az = np.arange(360.0) if azimuths_deg is None else np.asarray(azimuths_deg, float)
    cell = min(dem.resolution_m())
    near_m = min(max(NEAR_M, 4.0 * cell), max_range_m)
    fine = np.arange(1, int(near_m / (cell / 50.0)) + 1) * (cell / 50.0)
    coarse = np.arange(int(near_m / (cell / 4.0)) + 1, int(max_range_m / (cell / 4.0)) + 1) * (cell / 4.0)
    dist = np.concatenate([fine, coarse])
    r_eff = dem.body.effective_radius_m(refraction)
    z0 = float(dem.sample_lonlat(np.array([lon]), np.array([lat]))[0])
    z_eye = r_eff + z0 + height_m
    out = np.full(az.size, np.nan)
    for i, a in enumerate(az):
        lons, lats, _ = dem.geod.fwd(np.full(dist.size, lon), np.full(dist.size, lat), np.full(dist.size, a), dist)
        z = dem.sample_lonlat(np.asarray(lons), np.asarray(lats))
        ok = np.isfinite(z)
        if not ok.any():
            continue
        last = np.nonzero(ok)[0][-1]
        zt, d = z[: last + 1], dist[: last + 1]
        theta = d / r_eff
        rt = r_eff + zt
        elev = np.degrees(np.arctan2(rt * np.cos(theta) - z_eye, rt * np.sin(theta)))
        out[i] = np.nanmax(elev)
    return out
