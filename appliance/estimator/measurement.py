"""Step 1 of a search: the measured skyline on the database's azimuth grid, checked.

The measurement is resampled onto the grid's azimuths (linear, circular; a gap stays missing),
with its per-azimuth weights (the detector's confidence, a mask), and carries what every later step
weighs it by: its sample count, sigma's interval and midpoint, the occlusion cap and the map's
vertical error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from appliance.errors import InputError
from appliance.estimator.likelihood import occlusion_cap_deg2, sigma_midpoint, valid_sigma_interval

if TYPE_CHECKING:
    from appliance.estimator.skyline_grid import SkylineGrid


@dataclass(frozen=True)
class Measurement:
    """The measured skyline on the database's azimuth grid, checked, and what every step weighs it by."""

    elevation_deg: np.ndarray  # (n_az,) NaN = missing
    weight: np.ndarray  # (n_az,) 0..1, 0 where missing
    valid: np.ndarray  # (n_az,) bool
    n_valid: int
    n_eff: float  # the measurements' total weight: the likelihood's sample count
    sigma_lo_deg: float
    sigma_hi_deg: float
    sigma_ref_deg: float  # sigma's midpoint, what the parallax model's variances are weighed against
    cap_deg2: float  # the occlusion cap at sigma's midpoint
    occlusion_weight: float
    map_sigma_m: float


def measured_on_grid(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, weights: np.ndarray | None,
                     n_az: int) -> tuple[np.ndarray, np.ndarray]:
    """The measured skyline (deg, NaN where missing) and its weights (0..1, 0 where missing) on the
    azimuth grid j * 360 / n_az (:func:`resample_to_grid`); an azimuth of weight 0 is missing."""
    m = resample_to_grid(azimuth_deg, elevation_deg, n_az)
    if weights is None:
        return m, np.isfinite(m).astype(float)
    wts = np.asarray(weights, dtype=float)
    w_grid = resample_to_grid(azimuth_deg, np.where(np.isfinite(elevation_deg), wts, np.nan), n_az)
    m = np.where(np.isfinite(w_grid) & (w_grid > 0), m, np.nan)
    return m, np.where(np.isfinite(m), w_grid, 0.0)


def measure(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, sigma_deg: tuple[float, float],
             weights: np.ndarray | None, occlusion_weight: float, map_sigma_m: float,
             min_field_of_view_deg: float) -> Measurement:
    """Step 1: the measured skyline (deg) and its weights (0..1) resampled onto the grid's azimuths,
    the arguments checked (InputError), and sigma's midpoint (deg) and the occlusion cap (deg^2)."""
    sig_lo, sig_hi = float(sigma_deg[0]), float(sigma_deg[1])
    if not valid_sigma_interval(sig_lo, sig_hi):
        raise InputError(f"sigma interval [{sig_lo}, {sig_hi}] must satisfy 0 < lo <= hi")
    n_az = grid.n_azimuths
    if weights is not None:
        wts = np.asarray(weights, dtype=float)
        if wts.shape != np.shape(elevation_deg) or not np.all((wts >= 0) & (wts <= 1) | np.isnan(wts)):
            raise InputError("weights: one value in [0, 1] per measured azimuth")
    m, w_grid = measured_on_grid(azimuth_deg, elevation_deg, weights, n_az)
    if not 0.0 <= occlusion_weight < 1.0:
        raise InputError(f"occlusion weight {occlusion_weight}: expected 0 <= w < 1")
    if not (math.isfinite(map_sigma_m) and map_sigma_m >= 0.0):
        raise InputError(f"map vertical sigma {map_sigma_m} m: expected >= 0")
    valid = np.isfinite(m)
    n = int(valid.sum())
    step = grid.az_step_deg
    if n * step < min_field_of_view_deg:
        raise InputError(
            f"skyline covers {n * step:.0f} deg of azimuth ({n} valid azimuths of {n_az}), "
            f"less than the {min_field_of_view_deg:.0f} deg needed to locate anything"
        )
    sig_ref = sigma_midpoint(sig_lo, sig_hi)
    return Measurement(m, w_grid, valid, n, float(w_grid.sum()), sig_lo, sig_hi, sig_ref,
                        occlusion_cap_deg2(occlusion_weight, sig_ref), occlusion_weight, map_sigma_m)



def resample_to_grid(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, n_az: int) -> np.ndarray:
    """Measured skyline on the azimuth grid j * 360 / n_az; NaN where missing.

    Samples already on the grid are placed as they are.  Others are interpolated linearly between
    the two nearest valid samples on the circle, provided they are at most two grid steps apart;
    otherwise missing (never guessed across a gap).
    """
    step = 360.0 / n_az
    az = np.mod(np.asarray(azimuth_deg, float), 360.0)
    el = np.asarray(elevation_deg, float)
    ok = np.isfinite(el)
    if not ok.any():
        return np.full(n_az, np.nan)
    a, e = az[ok], el[ok]
    order = np.argsort(a)
    a, e = a[order], e[order]
    grid = np.arange(n_az) * step
    k = np.round(a / step).astype(int) % n_az
    if np.allclose(np.mod(a - k * step + 180.0, 360.0) - 180.0, 0.0, atol=1e-6):
        # already on the grid: place the samples, leave the others missing
        out = np.full(n_az, np.nan)
        out[k] = e
        return out
    a_ext = np.concatenate([a[-1:] - 360.0, a, a[:1] + 360.0])
    e_ext = np.concatenate([e[-1:], e, e[:1]])
    hi = np.searchsorted(a_ext, grid, side="left")
    hi = np.clip(hi, 1, a_ext.size - 1)
    lo = hi - 1
    span = a_ext[hi] - a_ext[lo]
    t = np.where(span > 0, (grid - a_ext[lo]) / np.where(span > 0, span, 1.0), 0.0)
    out = e_ext[lo] * (1 - t) + e_ext[hi] * t
    exact = np.isclose(a_ext[hi], grid) | np.isclose(a_ext[lo], grid)
    out[(span > 2.0 * step + 1e-9) & ~exact] = np.nan
    return out
