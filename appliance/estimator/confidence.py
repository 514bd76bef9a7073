"""How sure an estimate is, from the skyline itself: the noise and the number of independent
azimuths learned from the best fit's residuals, the 95 % credible region, its modes, and the
answer's covariance.

Residuals along azimuth are correlated (the stitch, the lens, a residual tilt, the map's error all
vary smoothly), so n measured azimuths carry the information of fewer independent ones:

    n_ind = n / (1 + 2 sum_k rho_k),

rho_k the residuals' autocorrelation at lag k, summed over Geyer's initial positive sequence.  The
likelihood of a skyline is then tempered by n_ind / n (each azimuth counts for that share of an
independent one), and sigma's interval is the chi-square interval of the residuals' RMS with n_ind
degrees of freedom.  Both come from the data, not from a setting.

The credible region holds the most probable nodes up to LEVEL of the posterior.  Its connected
parts (cells at most MODE_GAP_CELLS apart) are its modes; the mode of the answer is described by an
ellipse (the exact fit's covariance), the others by their cells.  An answer is ambiguous only when
another mode, farther from it than its own spread, belongs to the region.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

#: The credible level of the region and of the ellipse.
LEVEL = 0.95


def chi2_2dof(level: float = LEVEL) -> float:
    """The chi-square quantile with 2 degrees of freedom at ``level``: an ellipse's squared
    Mahalanobis radius."""
    return -2.0 * math.log(1.0 - level)
#: Cells of the region at most this many cells apart (along each axis) belong to one mode.
MODE_GAP_CELLS = 2
#: The exact fit's curvature at the learned sigma, tempered, understates the scatter of its answers
#: against independent truth (the reference ray march, bench/levelled_head.py and
#: bench/estimator_accuracy.py's sensor): their squared Mahalanobis distances ran 2-3 times chi-square's.
#: The covariance's variances are multiplied by this; tuned on those benches' first seeds, checked on
#: others (bench/results/confidence.md).
COVARIANCE_SCALE = 2.0
#: The smallest noise (deg) the learned interval may reach: the database's quantisation.
SIGMA_FLOOR_DEG = 0.02
#: Two-sided confidence of sigma's interval (standard normal quantile), and the fewest independent
#: azimuths the tempering and the interval assume.
SIGMA_Z = 1.959964
MIN_INDEPENDENT = 4.0


#: Parameters a fit takes from its residuals before they tell the noise: position (2) and heading.
FITTED_PARAMETERS = 3


def few_azimuths_factor(independent: float, level: float = LEVEL) -> float:
    """How much wider (in variance) a position's ellipse at ``level`` must be when sigma was learned
    from ``independent`` azimuths, less the FITTED_PARAMETERS a fit takes: the position then follows
    Student's t with nu = independent - FITTED_PARAMETERS degrees of freedom, whose squared radius at
    ``level`` is nu ((1 - level)^(-2/nu) - 1) (2 F(2, nu)) against chi-square's -2 ln(1 - level).  One
    for many azimuths."""
    nu = max(independent - FITTED_PARAMETERS, 1.0)
    return nu * ((1.0 - level) ** (-2.0 / nu) - 1.0) / chi2_2dof(level)


def independent_azimuths(residual_deg: np.ndarray) -> float:
    """How many independent azimuths the residuals (deg on a full-circle azimuth grid, NaN where
    missing) are worth: n / (1 + 2 sum of the autocorrelation over its initial positive sequence).
    The autocorrelation is taken about zero, so a common offset counts as correlated."""
    x, valid, n, var = _about_zero(residual_deg)
    if n < 3 or not var > 0.0:
        return float(n)
    # the lags in pairs, each made only when the sum has come to it (the sequence ends at the first
    # pair not positive, at the first lag with fewer than 8 pairs of azimuths, or at a quarter turn)
    total = 0.0
    for lag in range(1, x.size // 4 - 1, 2):
        pair = _autocorrelation(x, valid, lag, var) + _autocorrelation(x, valid, lag + 1, var)
        if not pair > 0.0:
            break
        total += pair
    return float(min(n, max(MIN_INDEPENDENT, n / (1.0 + 2.0 * total))))


def lag_one_correlation(residual_deg: np.ndarray) -> float:
    """The residuals' (deg on a full-circle azimuth grid, NaN where missing) autocorrelation from one
    azimuth to the next, about zero as :func:`independent_azimuths` takes it: near 0 for a sensor's
    white noise, near 1 where the residuals vary smoothly along the skyline (a wrong place, a tilt,
    what the map lacks).  NaN with fewer than 8 pairs of neighbouring measured azimuths, or no residual."""
    x, valid, _, var = _about_zero(residual_deg)
    if not var > 0.0:
        return math.nan
    return _autocorrelation(x, valid, 1, var)


def _about_zero(residual_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The residuals (NaN where missing) as the autocorrelations take them: zero where missing, which
    azimuths hold one, how many, and their mean square about zero (0 with none)."""
    r = np.asarray(residual_deg, dtype=np.float64)
    valid = np.isfinite(r)
    n = int(valid.sum())
    x = np.where(valid, r, 0.0)
    return x, valid, n, float(np.sum(x * x)) / max(n, 1)


def _autocorrelation(x: np.ndarray, valid: np.ndarray, lag: int, var: float) -> float:
    """The autocorrelation of ``x`` (zero where not ``valid``) at ``lag`` around the circle, over the
    pairs of valid azimuths; NaN with fewer than 8 such pairs."""
    pairs = int(np.count_nonzero(valid[lag:] & valid[:-lag])) + int(np.count_nonzero(valid[:lag] & valid[-lag:]))
    if pairs < 8:
        return math.nan
    return float(np.sum(x * np.concatenate((x[lag:], x[:lag])))) / pairs / var


def _chi2_quantile(dof: float, z: float) -> float:
    """The chi-square quantile at standard normal quantile ``z`` (Wilson-Hilferty)."""
    c = 2.0 / (9.0 * dof)
    return dof * max(1.0 - c + z * math.sqrt(c), 1e-3) ** 3


def sigma_interval(rms_deg: float, independent: float, floor_deg: float = SIGMA_FLOOR_DEG) -> tuple[float, float]:
    """Sigma's interval (deg) from the best fit's RMS residual over ``independent`` azimuths: the
    two-sided chi-square interval at SIGMA_Z, each end at least ``floor_deg``."""
    nu = max(independent, MIN_INDEPENDENT)
    lo = rms_deg * math.sqrt(nu / _chi2_quantile(nu, SIGMA_Z))
    hi = rms_deg * math.sqrt(nu / _chi2_quantile(nu, -SIGMA_Z))
    return max(lo, floor_deg), max(hi, floor_deg)


def credible_nodes(posterior: np.ndarray, level: float = LEVEL) -> np.ndarray:
    """The fewest nodes holding ``level`` of ``posterior`` (sums to one), the most probable first;
    returned sorted by index."""
    p = np.asarray(posterior, dtype=np.float64)
    nz = np.nonzero(p > 0.0)[0]
    if nz.size == 0:
        return nz
    order = nz[np.argsort(-p[nz], kind="stable")]
    cum = np.cumsum(p[order])
    k = int(np.searchsorted(cum, level * cum[-1])) + 1
    return np.sort(order[: min(k, order.size)])


@numba.njit(cache=True, nogil=True)
def _label(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int, gap: int) -> np.ndarray:
    """Connected parts of a set of cells, cells within ``gap`` along both axes being neighbours."""
    n = rows.size
    index = np.full(n_rows * n_cols, -1, dtype=np.int64)
    for i in range(n):
        index[rows[i] * n_cols + cols[i]] = i
    label = np.full(n, -1, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    current = 0
    for start in range(n):
        if label[start] >= 0:
            continue
        label[start] = current
        top = 0
        stack[0] = start
        while top >= 0:
            i = stack[top]
            top -= 1
            for dr in range(-gap, gap + 1):
                r = rows[i] + dr
                if r < 0 or r >= n_rows:
                    continue
                for dc in range(-gap, gap + 1):
                    c = cols[i] + dc
                    if c < 0 or c >= n_cols:
                        continue
                    j = index[r * n_cols + c]
                    if j >= 0 and label[j] < 0:
                        label[j] = current
                        top += 1
                        stack[top] = j
        current += 1
    return label


def mode_labels(nodes: np.ndarray, n_rows: int, n_cols: int, gap: int = MODE_GAP_CELLS) -> np.ndarray:
    """One label per node of ``nodes`` (flat indices): its connected part of the set."""
    nodes = np.asarray(nodes, dtype=np.int64)
    if nodes.size == 0:
        return np.zeros(0, dtype=np.int64)
    rows, cols = np.divmod(nodes, n_cols)
    return _label(rows, cols, n_rows, n_cols, gap)


@dataclass(frozen=True)
class Modes:
    """The credible region split into the answer's mode and the rest."""

    region: np.ndarray  # flat node indices of the credible region, sorted
    main: np.ndarray  # those of the answer's mode
    rivals: np.ndarray  # those of other modes farther from the answer than its own spread
    main_mass: float  # posterior of the answer's mode
    rival_mass: float  # posterior of the rival modes
    main_covariance_cells: np.ndarray  # (2, 2) the answer's mode's spread over its nodes, (row, col) cells^2


def modes(posterior: np.ndarray, n_rows: int, n_cols: int, row: float, col: float,
          level: float = LEVEL, same_cells: float = 2.0, reach_cells: float = 0.0) -> Modes:
    """The credible region of ``posterior`` (per node, sums to one) at ``level`` and its modes, the
    answer (fractional ``row``, ``col``) belonging to the mode nearest it.  A mode is a rival when
    its nearest cell lies farther from the answer than ``same_cells``, than twice the answer's
    mode's spread (1 sigma along its major axis) and than ``reach_cells`` (the answer's own
    ellipse, where it is known), and the rivals together hold at least 1 - ``level`` of the
    posterior."""
    region = credible_nodes(posterior, level)
    labels = mode_labels(region, n_rows, n_cols)
    r, c = np.divmod(region, n_cols)
    dist = np.hypot(r - row, c - col)
    main_label = labels[int(np.argmin(dist))]
    main = region[labels == main_label]
    p = np.asarray(posterior, dtype=np.float64)
    w = p[main] / max(float(p[main].sum()), 1e-300)
    mr, mc = np.divmod(main, n_cols)
    mean = np.array([np.sum(w * mr), np.sum(w * mc)])
    d = np.stack([mr - mean[0], mc - mean[1]])
    cov = (d * w) @ d.T + np.eye(2) / 12.0
    spread = math.sqrt(float(np.linalg.eigvalsh(cov)[-1]))
    reach = max(same_cells, 2.0 * spread, reach_cells)
    rival_labels = [lab for lab in np.unique(labels) if lab != main_label
                    and float(np.min(dist[labels == lab])) > reach]
    rivals = region[np.isin(labels, rival_labels)]
    if float(p[rivals].sum()) < 1.0 - level:
        # places holding less than the level leaves out anyway: the answer's mode alone is a region
        # at the level, and they are no rivals
        rivals = rivals[:0]
    return Modes(region, main, rivals, float(p[main].sum()), float(p[rivals].sum()), cov)


def grid_to_east_north(covariance_cells: np.ndarray, dx_m: float, dy_m: float, convergence_deg: float) -> np.ndarray:
    """A (row, col) covariance (cells^2) as an (east, north) one (m^2): rows run south by ``dy_m``,
    columns east by ``dx_m`` along the grid's axes, which stand ``convergence_deg`` from true north
    (grid +x is (cos g, -sin g) in east and north)."""
    a = np.array([[0.0, dx_m], [-dy_m, 0.0]])  # (row, col) -> grid (x, y)
    g = math.radians(convergence_deg)
    rot = np.array([[math.cos(g), math.sin(g)], [-math.sin(g), math.cos(g)]])  # grid (x, y) -> (east, north)
    m = rot @ a
    out = m @ np.asarray(covariance_cells, dtype=np.float64) @ m.T
    return 0.5 * (out + out.T)


def radius_m(covariance_m2: np.ndarray, level: float = LEVEL) -> float:
    """The ellipse's semi-major axis (m) at ``level``: what "± R m" reports."""
    return math.sqrt(chi2_2dof(level) * max(float(np.linalg.eigvalsh(np.asarray(covariance_m2))[-1]), 0.0))


def ellipse_area_m2(covariance_m2: np.ndarray, level: float = LEVEL) -> float:
    """The area (m^2) of the ellipse at ``level``."""
    return math.pi * chi2_2dof(level) * math.sqrt(max(float(np.linalg.det(np.asarray(covariance_m2))), 0.0))


def inside_ellipse(offset: np.ndarray, covariance: np.ndarray, level: float = LEVEL) -> bool:
    """Whether ``offset`` from the centre lies inside the ellipse of ``covariance`` at ``level``
    (same units for both)."""
    try:
        d2 = float(offset @ np.linalg.solve(covariance, offset))
    except np.linalg.LinAlgError:
        return False
    return d2 <= chi2_2dof(level)


def envelope(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance that is at least ``a`` and at least ``b`` along every direction (2 x 2, both
    positive definite): ``b`` seen in the frame where ``a`` is the identity, its variances below one raised
    to one."""
    w, v = np.linalg.eigh(a)
    half = v * np.sqrt(w)
    inv_half = v / np.sqrt(w)
    m = inv_half.T @ b @ inv_half
    mw, mv = np.linalg.eigh(0.5 * (m + m.T))
    lifted = (mv * np.maximum(mw, 1.0)) @ mv.T
    out = half @ lifted @ half.T
    return 0.5 * (out + out.T)
