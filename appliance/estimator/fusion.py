"""Fusion of panoramas taken along a path (paper section 6.4).

The posterior after one panorama, moved by the dead-reckoned displacement between the two
stations and blurred by its uncertainty, is the prior of the next: p'(x) = (p * N(0, s^2))(x - d).
Per node for the grid search; and, for the exact fit between nodes, the last fix with its
covariance moved the same way (a Gaussian: the grid's cells are too coarse to carry it).
"""

from __future__ import annotations

import numpy as np

from appliance.estimator.exact import PositionPrior

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


def transport_fix(
    row: float,
    col: float,
    covariance_cells: np.ndarray,
    dx_m: float,
    dy_m: float,
    east_m: float,
    north_m: float,
    sigma_m: float,
) -> PositionPrior:
    """The continuous twin of :func:`transport_prior`: a fix at fractional grid (row, col) with its
    (row, col) covariance (cells^2), moved by ``(east_m, north_m)`` along the grid's axes and widened
    by the move's ``sigma_m`` per axis.  The exact fit between nodes weighs it."""
    cov = np.asarray(covariance_cells, dtype=float) + np.diag([(sigma_m / dy_m) ** 2, (sigma_m / dx_m) ** 2])
    return PositionPrior(row - north_m / dy_m, col + east_m / dx_m, np.linalg.inv(cov))
