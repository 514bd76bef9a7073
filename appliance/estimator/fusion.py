"""Fusion of panoramas taken along a path (paper section 6.4).

The posterior after one panorama, moved by the dead-reckoned displacement between the two
stations and blurred by its uncertainty, is the prior of the next: p'(x) = (p * N(0, s^2))(x - d).
"""

from __future__ import annotations

import numpy as np

#: Probability floor of a transported prior, relative to its peak: only there to keep the logarithm
#: finite where the blurred posterior underflowed; it does not weaken the prior where it has mass.
PRIOR_FLOOR = 1e-250


def transport_prior(
    posterior: np.ndarray,
    n_rows: int,
    n_cols: int,
    dx_m: float,
    dy_m: float,
    east_m: float,
    north_m: float,
    sigma_m: float,
) -> np.ndarray:
    """Log prior per node after moving ``(east_m, north_m)`` with uncertainty ``sigma_m`` (1-sigma, m).

    ``posterior`` is per node (row-major, rows running south).  Probability that moves off the grid
    is lost; the result is normalised over the grid.
    """
    from scipy import ndimage  # here, not at import: most estimates fuse nothing

    p = np.nan_to_num(np.asarray(posterior, float).reshape(n_rows, n_cols), nan=0.0)
    moved = ndimage.shift(p, (-north_m / dy_m, east_m / dx_m), order=1, mode="constant", cval=0.0)
    if sigma_m > 0:
        moved = ndimage.gaussian_filter(moved, (sigma_m / dy_m, sigma_m / dx_m), mode="constant", truncate=4.0)
    peak = float(moved.max())
    if not peak > 0:
        return np.zeros(n_rows * n_cols)
    moved = np.maximum(moved, peak * PRIOR_FLOOR)
    moved /= moved.sum()
    return np.log(moved).ravel()
