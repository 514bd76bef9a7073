"""Interval-valued Gaussian likelihood and the lower and upper posteriors (paper sections 4.2-4.4).

A measured skyline m (n valid azimuths) and the skyline s(theta) rendered at candidate theta give

    L(theta; sigma) = prod_i N(m_i; s_i(theta), sigma^2) = (2 pi sigma^2)^(-n/2) exp(-SSD / (2 sigma^2)),

the n-sample form.  The paper's Expression (1) normalises once, (2 pi sigma^2)^(-1/2); with one
sigma for every candidate the factor cancels in the posterior, but once sigma ranges over an
interval [sigma_l, sigma_u] it does not: the factor sigma^(-n) is what makes a small sigma pay for
large residuals, and without it the extremes over sigma would always sit at the interval's ends.

For each candidate, log L over sigma has one stationary point, sigma* = sqrt(SSD / n), a maximum;
so the upper likelihood is at sigma* clamped into the interval and the lower at whichever end is
worse.  With the likelihood of each candidate free within [L_l, L_u] and prior p, the posteriors
are (the closed form after the paper's Expression (2)):

    lower(theta) = L_l p / (L_l p + sum_{theta' != theta} L_u p)
    upper(theta) = L_u p / (L_u p + sum_{theta' != theta} L_l p)

All of it in log space: 360 samples make the plain exponentials underflow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

import appliance.numerics  # noqa: F401  (scipy's BLAS and LAPACK for numba without scipy.linalg)

LOG_2PI = math.log(2.0 * math.pi)


def log_likelihood(ssd: np.ndarray, n: float | np.ndarray, sigma_deg: float) -> np.ndarray:
    """log L for squared-residual sums ``ssd`` (deg^2) over ``n`` samples at one sigma (deg)."""
    s2 = sigma_deg * sigma_deg
    return -0.5 * n * (LOG_2PI + math.log(s2)) - ssd / (2.0 * s2)


def valid_sigma_interval(sigma_lo: float, sigma_hi: float) -> bool:
    """Whether [sigma_lo, sigma_hi] (deg) is an interval the bounds can be made over: 0 < lo <= hi."""
    return 0 < sigma_lo <= sigma_hi


def sigma_midpoint(sigma_lo: float, sigma_hi: float) -> float:
    """Sigma's midpoint (deg): the one sigma of what needs one (the parallax model's weights, the
    occlusion cap, the midpoint posterior)."""
    return 0.5 * (sigma_lo + sigma_hi)


def log_likelihood_bounds(ssd: np.ndarray, n: float | np.ndarray, sigma_lo: float,
                          sigma_hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper log-likelihood over sigma in [sigma_lo, sigma_hi] (deg)."""
    if not valid_sigma_interval(sigma_lo, sigma_hi):
        raise ValueError(f"sigma interval [{sigma_lo}, {sigma_hi}] must satisfy 0 < lo <= hi")
    star = np.sqrt(np.maximum(ssd, 0.0) / np.maximum(n, 1))
    s_best = np.clip(star, sigma_lo, sigma_hi)
    upper = -0.5 * n * (LOG_2PI + 2.0 * np.log(s_best)) - ssd / (2.0 * s_best**2)
    lower = np.minimum(log_likelihood(ssd, n, sigma_lo), log_likelihood(ssd, n, sigma_hi))
    return lower, upper


def _logsumexp(a: np.ndarray) -> float:
    m = float(np.max(a))
    if not math.isfinite(m):
        return m
    return m + math.log(float(np.sum(np.exp(a - m))))


def _log_rest(log_w: np.ndarray) -> np.ndarray:
    """log(sum_{j != i} w_j) for every i, without cancellation at the largest term."""
    total = _logsumexp(log_w)
    with np.errstate(divide="ignore", invalid="ignore"):
        rest = total + np.log1p(-np.exp(np.minimum(log_w - total, 0.0)))
    top = int(np.argmax(log_w))
    others = np.delete(log_w, top)
    rest[top] = _logsumexp(others) if others.size else -np.inf
    return rest


@dataclass(frozen=True)
class PosteriorBounds:
    """Log lower and upper posteriors of every candidate (same shape as the likelihoods)."""

    log_lower: np.ndarray
    log_upper: np.ndarray

    @property
    def lower(self) -> np.ndarray:
        return np.exp(self.log_lower)

    @property
    def upper(self) -> np.ndarray:
        return np.exp(self.log_upper)


def posterior_bounds(log_lo: np.ndarray, log_up: np.ndarray, log_prior: np.ndarray | None = None) -> PosteriorBounds:
    """Lower and upper posteriors from lower and upper log-likelihoods (and a log prior)."""
    lo = log_lo.astype(np.float64).ravel()
    up = log_up.astype(np.float64).ravel()
    if log_prior is not None:
        lp = np.broadcast_to(log_prior, log_lo.shape).astype(np.float64).ravel()
        lo = lo + lp
        up = up + lp
    rest_up = _log_rest(up)
    rest_lo = _log_rest(lo)
    log_lower = lo - np.logaddexp(lo, rest_up)
    log_upper = up - np.logaddexp(up, rest_lo)
    return PosteriorBounds(log_lower.reshape(log_lo.shape), log_upper.reshape(log_lo.shape))


def log_upper_with_others(log_upper: np.ndarray, log_upper_unnormalised: np.ndarray,
                          log_others_lower: float) -> np.ndarray:
    """An upper bound on candidates' upper posterior (nats) once others join the ones it was
    normalised over (the candidates of other grids), from the upper posterior among its own and the
    unnormalised one (nats, on the scale of ``log_others_lower``, the others' summed unnormalised
    lower posterior O).

    Among its own a candidate's upper posterior is u = b / (b + S - a), with b and a its unnormalised
    upper and lower posterior and S the summed lower ones; with the others O joins the denominator,
    so 1 / g = 1 / u + O / b exactly.  For no others (O = 0) g is u."""
    lu = np.minimum(np.asarray(log_upper, dtype=np.float64), 0.0)
    if log_others_lower == -math.inf:
        return lu
    lb = np.asarray(log_upper_unnormalised, dtype=np.float64)
    return -np.logaddexp(-lu, log_others_lower - lb)


#: The span (deg) above the terrain over which an occluder's top may lie, for the occlusion component.
OCCLUDER_SPAN_DEG = 20.0


def occlusion_cap_deg2(weight: float, sigma_deg: float) -> float:
    """The most a measurement *above* the predicted skyline may cost, as a squared residual (deg^2).

    An occluder in front of the terrain (a tree, a building, the rover's mast) can only raise the
    measured skyline, never lower it.  Each azimuth's likelihood is the mixture

        p(m | s) = (1 - w) N(m; s, sigma^2) + w U(m; s, s + H)          (U: uniform above s),

    with w the occlusion weight and H = OCCLUDER_SPAN_DEG.  Below the prediction only the Gaussian
    speaks, so a measured skyline well below the rendered one stays strong evidence against the
    place; above it, -2 sigma^2 log p levels off at

        C = 2 sigma^2 log(1 / kappa),   kappa = w sqrt(2 pi) sigma / ((1 - w) H),

    which is where the occlusion component takes over.  Residuals enter the n-sample Gaussian of
    the interval posterior as min(r^2, C) above the prediction, so the region keeps its closed form.
    ``weight`` = 0 gives the plain Gaussian (C infinite).
    """
    if not weight > 0.0:
        return math.inf
    if weight >= 1.0:
        return 0.0
    kappa = weight * math.sqrt(2.0 * math.pi) * sigma_deg / ((1.0 - weight) * OCCLUDER_SPAN_DEG)
    if kappa >= 1.0:
        return 0.0
    return 2.0 * sigma_deg * sigma_deg * math.log(1.0 / kappa)


def kernel_cap(cap_deg2: float) -> float:
    """The cap as the compiled kernels take it: a finite float (1e30 where there is none)."""
    return float(min(cap_deg2, 1e30))


@numba.njit(cache=True, inline="always")
def is_occluded(residual: float | np.floating, weighted_square: float | np.floating,
                cap: float | np.floating) -> bool | np.bool_:
    """Whether one measurement is taken for an occluder: above the model (``residual``, measured
    minus model, > 0) with its weighted square past the cap (the kernels' form, any float type).
    Both tests are made, not one after the other (``&``, not ``and``): with no branch in it, a loop
    over shifts compiles to plain vector loads and stores (with ``and`` the every-heading first pass
    stored its sums by scatter, at 2.5 times the cost; the same numbers)."""
    return (residual > 0) & (weighted_square > cap)


def occluded_mask(residual: np.ndarray, weighted_square: np.ndarray, cap_deg2: float) -> np.ndarray:
    """:func:`is_occluded` over arrays."""
    return (residual > 0) & (weighted_square > cap_deg2)


def capped_cost(ssd: np.ndarray, occluded: np.ndarray, cap_deg2: float) -> np.ndarray:
    """Residual sums (deg^2) with each occluded measurement (by weight) counting the cap: the cost
    at sigma's reference that ranks headings and places.  ``ssd`` itself when the cap is infinite."""
    return ssd if not math.isfinite(cap_deg2) else ssd + occluded * cap_deg2


# The model's own variance tau^2 at an azimuth (parallax, the map's height error; ``parallax.py``)
# widens its Gaussian to sigma^2 + tau^2: the squared residual counts sigma^2 / (sigma^2 + tau^2) of
# itself against sigma, and the wider Gaussian pays its log-normaliser log(1 + tau^2 / sigma^2).

@numba.njit(cache=True, inline="always")
def variance_weight(sig2: float, tau2: float) -> float:
    """sigma^2 / (sigma^2 + tau^2): the weight of a squared residual under the model's variance."""
    return sig2 / (sig2 + tau2)


@numba.njit(cache=True, inline="always")
def variance_log_normaliser(sig2: float, tau2: float) -> float:
    """log(1 + tau^2 / sigma^2): what the Gaussian widened by tau^2 pays (nats, times 2)."""
    return math.log1p(tau2 / sig2)


def variance_tables(tau2_deg2: np.ndarray, sigma_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`variance_weight` and :func:`variance_log_normaliser` of every tau^2 of a table at one
    sigma (deg), as float32 (from the ratio r = tau^2 / sigma^2: 1 / (1 + r) and log1p(r))."""
    r = tau2_deg2 / (sigma_deg * sigma_deg)
    return (1.0 / (1.0 + r)).astype(np.float32), np.log1p(r).astype(np.float32)


def variance_weighted(u: np.ndarray, sigma_deg: float, var_deg2: np.ndarray) -> np.ndarray:
    """Measurement weights ``u`` times sigma^2 / (sigma^2 + var) (the exact fit's form)."""
    return u * sigma_deg**2 / (sigma_deg**2 + var_deg2)


def _occlusion_split(n: float, occluded: np.ndarray, weight: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian's sample count and the sigma-free part of the mixture's log-likelihood:
    log(w / H) per occluded measurement, log(1 - w) per other one."""
    occ = np.asarray(occluded, dtype=np.float64)
    n_g = np.maximum(n - occ, 1.0)
    return n_g, occ * math.log(weight / OCCLUDER_SPAN_DEG) + n_g * math.log1p(-weight)


def mixture_log_likelihood(ssd: np.ndarray, n: float, occluded: np.ndarray, sigma: float,
                           weight: float) -> np.ndarray:
    """The occlusion mixture's log-likelihood at one sigma (see :func:`mixture_log_likelihood_bounds`)."""
    if not weight > 0.0:
        return log_likelihood(ssd, n, sigma)
    n_g, const = _occlusion_split(n, occluded, weight)
    return log_likelihood(ssd, n_g, sigma) + const


def mixture_log_likelihood_bounds(ssd: np.ndarray, n: float, occluded: np.ndarray, sigma_lo: float,
                                  sigma_hi: float, weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper log-likelihood over sigma of the occlusion mixture (:func:`occlusion_cap_deg2`).

    ``occluded`` measurements (by weight) are those the occluder explains: each contributes
    log(w / H), whatever sigma; the other n - occluded contribute the n-sample Gaussian of their
    residual sum ``ssd`` and log(1 - w) each.  With ``weight`` = 0 this is :func:`log_likelihood_bounds`.
    """
    if not weight > 0.0:
        return log_likelihood_bounds(ssd, n, sigma_lo, sigma_hi)
    n_g, const = _occlusion_split(n, occluded, weight)
    lo, up = log_likelihood_bounds(ssd, n_g, sigma_lo, sigma_hi)
    return lo + const, up + const


@numba.njit(cache=True, parallel=True, nogil=True)
def _best_column_bounds(ssd: np.ndarray, occluded: np.ndarray, penalty: np.ndarray, log_prior: np.ndarray,
                        cap32: np.float32, rank_cap: bool, n: float, sigma_lo: float, sigma_hi: float,
                        log_occ: float, log_clear: float, mixture: bool, lower: np.ndarray,
                        upper: np.ndarray) -> int:
    """The loop behind :func:`best_column_bounds`, written to round as its numpy form does (no
    fast-math: the same operations in the same order)."""
    n_rows, n_cols = ssd.shape
    s2_lo = sigma_lo * sigma_lo
    s2_hi = sigma_hi * sigma_hi
    log_lo = math.log(sigma_lo)
    log_hi = math.log(sigma_hi)
    log_s2_lo = math.log(s2_lo)
    log_s2_hi = math.log(s2_hi)
    den_lo = 2.0 * s2_lo
    den_hi = 2.0 * s2_hi
    # with no mixture every row has the same n: its terms in sigma alone are made once
    k_lo = -0.5 * n * (LOG_2PI + log_s2_lo)
    k_hi = -0.5 * n * (LOG_2PI + log_s2_hi)
    u_lo = -0.5 * n * (LOG_2PI + 2.0 * log_lo)
    u_hi = -0.5 * n * (LOG_2PI + 2.0 * log_hi)
    scored = 0
    for i in numba.prange(n_rows):
        k = 0
        best = ssd[i, 0] + occluded[i, 0] * cap32 if rank_cap else ssd[i, 0]
        for j in range(1, n_cols):
            v = ssd[i, j] + occluded[i, j] * cap32 if rank_cap else ssd[i, j]
            if v < best:
                best = v
                k = j
        c = np.float64(ssd[i, k])
        o = np.float64(occluded[i, k])
        if mixture:
            n_i = max(n - o, 1.0)
            const = o * log_occ + n_i * log_clear
            h = -0.5 * n_i
            a_lo = h * (LOG_2PI + log_s2_lo)
            a_hi = h * (LOG_2PI + log_s2_hi)
            b_lo = h * (LOG_2PI + 2.0 * log_lo)
            b_hi = h * (LOG_2PI + 2.0 * log_hi)
        else:
            n_i = n
            const = 0.0
            a_lo, a_hi, b_lo, b_hi = k_lo, k_hi, u_lo, u_hi
        star = math.sqrt(max(c, 0.0) / max(n_i, 1.0))
        q_lo = c / den_lo
        q_hi = c / den_hi
        # sigma* clamped into the interval: at either end (most nodes lie far off) the upper bound
        # shares the lower one's division, and its logarithm is known
        if star >= sigma_hi:
            up = b_hi - q_hi
        elif star <= sigma_lo:
            up = b_lo - q_lo
        else:
            up = -0.5 * n_i * (LOG_2PI + 2.0 * math.log(star)) - c / (2.0 * (star * star))
        ll_lo = a_lo - q_lo
        ll_hi = a_hi - q_hi
        lo = min(ll_lo, ll_hi)
        if math.isnan(ll_lo) or math.isnan(ll_hi):
            lo = np.nan
        if mixture:
            lo = lo + const
            up = up + const
        half = 0.5 * penalty[i]
        lower[i] = (lo - half) + log_prior[i]
        upper[i] = (up - half) + log_prior[i]
        if math.isfinite(c):
            scored += 1
    return scored


def best_column_bounds(ssd: np.ndarray, occluded: np.ndarray, penalty: np.ndarray, log_prior: np.ndarray,
                       cap_deg2: float, n: float, sigma_lo: float, sigma_hi: float,
                       weight: float, serial: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """For each row of residual sums ``ssd`` (deg^2, float32, one column per heading) and occluded
    weights: the column of least ``ssd + cap_deg2 * occluded`` (the first of equal ones; the sum
    alone when the cap is infinite), and that column's lower and upper log-likelihood over sigma in
    [sigma_lo, sigma_hi] deg (:func:`mixture_log_likelihood_bounds`, ``n`` samples, occlusion
    ``weight``), less half the row's log-normaliser ``penalty``, plus its ``log_prior`` (nats).
    Also the count of rows whose chosen sum is finite.  Rounds as the numpy form does: one pass
    over the rows, no temporaries of their size.  ``serial`` runs the loop on the caller's thread
    alone (the same operations row by row: the same numbers): between the parallel steps of two
    searches a parallel loop costs more CPU than it saves, as its idle threads spin-wait (OpenMP's
    active wait) through the serial work that follows it."""
    if not valid_sigma_interval(sigma_lo, sigma_hi):
        raise ValueError(f"sigma interval [{sigma_lo}, {sigma_hi}] must satisfy 0 < lo <= hi")
    rows = ssd.shape[0]
    lower = np.empty(rows)
    upper = np.empty(rows)
    mixture = weight > 0.0
    log_occ = math.log(weight / OCCLUDER_SPAN_DEG) if mixture else 0.0
    log_clear = math.log1p(-weight) if mixture else 0.0
    threads = numba.get_num_threads()
    if serial:
        numba.set_num_threads(1)
    try:
        scored = _best_column_bounds(ssd, occluded, np.asarray(penalty, dtype=np.float64),
                                     np.asarray(log_prior, dtype=np.float64), np.float32(cap_deg2),
                                     math.isfinite(cap_deg2), float(n), float(sigma_lo), float(sigma_hi), log_occ,
                                     log_clear, mixture, lower, upper)
    finally:
        numba.set_num_threads(threads)
    return lower, upper, int(scored)
