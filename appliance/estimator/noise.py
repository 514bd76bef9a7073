"""The noise a skyline has, learned from its best exact fit, and what follows from it.

A search starts from a wide sigma interval (the configuration's).  Once the best place is fitted
exactly, its residuals tell the noise the skyline has: sigma's interval and the share of its
azimuths that are independent (``confidence.py``), which tempers the likelihood.  The best fit is
then fitted again at that sigma, its rivals ranked under it, and the answer's covariance made from
its curvature.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from appliance.estimator import confidence
from appliance.estimator.exact import Fit, Model, PositionPrior, marginal_position_covariance
from appliance.estimator.exact import refine as refine_exact
from appliance.estimator.likelihood import occlusion_cap_deg2, sigma_midpoint
from appliance.estimator.measurement import Measurement
from appliance.estimator.posteriors import SAME_ANSWER_CELLS, fit_bounds
from appliance.estimator.skyline_grid import SkylineGrid, nearest_node

#: The prior on a levelled head's residual tilt (deg, 1 sigma per axis), fitted with the learned sigma.
TILT_SIGMA_DEG = 0.3
#: The position's spread (cells) when the best fit is fitted again at the learned sigma.
POLISH_SPREAD_CELLS = 0.05
#: The fewest sectors of the skyline whose disagreement widens a covariance (a 360 deg panorama has 12).
MIN_SECTORS = 6


def learned_noise(residual_deg: np.ndarray, floor_deg: float, default_deg: float) -> tuple[float, float, float]:
    """Sigma's interval (deg, each end at least ``floor_deg``) and the likelihood's tempering
    (independent azimuths over measured ones) that a best fit's residuals (deg on the azimuth grid,
    NaN where missing) give; ``default_deg`` is the RMS taken when no residual is finite."""
    r = np.asarray(residual_deg, dtype=np.float64)
    finite = np.isfinite(r)
    rms = math.sqrt(float(np.nanmean(r * r))) if finite.any() else default_deg
    independent = confidence.independent_azimuths(r)
    lo, hi = confidence.sigma_interval(rms, independent, floor_deg)
    # a fit left with fewer than MIN_INDEPENDENT residuals (every azimuth taken for an occluder)
    # counts as that many: a tempering of 0 would turn every bound into 0 * -inf
    independent = max(independent, confidence.MIN_INDEPENDENT)
    return lo, hi, min(1.0, independent / max(float(finite.sum()), 1.0))


def sector_jackknife(fit: Fit, sigma_deg: float) -> np.ndarray | None:
    """The (row, col) covariance (cells^2) of the fit's position from a jackknife over its sectors of
    azimuth: each sector left out in turn, the fit's Gauss-Newton step from the optimum without it
    (at ``sigma_deg``, with the priors), and the spread of those steps, (k - 1) / k times the sum of their
    squares about their mean.  It shows how far the sectors disagree about the position, whatever made
    them (the map's error under near horizons, correlated noise and tilt that the fit's position
    absorbs).  None without sectors, or where a step cannot be solved."""
    if (fit.sector_pulls is None or fit.sector_curvatures is None or fit.curvature is None
            or fit.prior_information is None or fit.sector_pulls.shape[0] < 2):
        return None
    s2 = sigma_deg**2
    information = fit.curvature / s2 + fit.prior_information
    moves = []
    for g, h in zip(fit.sector_pulls, fit.sector_curvatures):
        try:
            moves.append(np.linalg.solve(information - h / s2, -g / s2)[:2])
        except np.linalg.LinAlgError:
            return None
    d = np.asarray(moves)
    d -= d.mean(axis=0)
    k = d.shape[0]
    return (k - 1.0) / k * (d.T @ d)


def tempered_covariance(fit: Fit, sigma_deg: float, temper: float) -> np.ndarray | None:
    """The exact fit's (row, col) covariance (cells^2) from its curvature at ``sigma_deg``, its
    likelihood counting ``temper`` of itself, with its priors (None: no curvature, or singular),
    widened for the few independent azimuths sigma was learned from
    (:func:`confidence.few_azimuths_factor`); then, without a position prior, widened along any
    direction in which the sectors of the skyline disagree about the position more than that
    (:func:`sector_jackknife`, with MIN_SECTORS sectors at least).  Where the noise is as the
    curvature assumes, the sectors' spread is about half that covariance (COVARIANCE_SCALE), so its
    sampling noise seldom widens it."""
    if fit.curvature is None or fit.prior_information is None:
        return None
    # the likelihood's information alone is widened: a prior's (a traverse's, the eye's) is not
    sig2 = sigma_deg**2 * confidence.COVARIANCE_SCALE * confidence.few_azimuths_factor(temper * fit.n)
    model = marginal_position_covariance(temper * fit.curvature / sig2 + fit.prior_information)
    # the sectors' spread is the skyline's alone: a position prior (a traverse's) pulls the fit off the
    # skyline's own optimum, and every sector's pull then carries that
    if (model is None or fit.sector_pulls is None or fit.sector_pulls.shape[0] < MIN_SECTORS
            or np.any(fit.prior_information[:2, :2] != 0.0)):
        return model
    spread = sector_jackknife(fit, sigma_deg)
    if spread is None:
        return model
    return confidence.envelope(model, spread)


def learned_measurement(meas: Measurement, fit: Fit, floor_deg: float) -> tuple[Measurement, float]:
    """The measurement with sigma's interval learned from ``fit``'s residuals (each end at least
    ``floor_deg``), and the tempering of its likelihood: independent azimuths over measured ones
    (``confidence.py``)."""
    r = fit.residual_deg
    assert r is not None
    lo, hi, temper = learned_noise(r, floor_deg, meas.sigma_ref_deg)
    learned = Measurement(meas.elevation_deg, meas.weight, meas.valid, meas.n_valid, meas.n_eff, lo, hi,
                          sigma_midpoint(lo, hi), meas.cap_deg2, meas.occlusion_weight, meas.map_sigma_m)
    return learned, temper


def polished_fit(grid: SkylineGrid, meas: Measurement, fit: Fit, heading_tolerance_deg: float | None,
                 height_m: float | None, position_prior: PositionPrior | None) -> Fit | None:
    """``fit`` fitted again from where it stands at the measurement's (learned) sigma: the weights,
    the occlusion cap and the point where the fit is at the noise follow the noise the skyline has,
    not the search's.  None when the new fit fails."""
    assert grid.terrain is not None
    sigma, step = meas.sigma_ref_deg, grid.az_step_deg
    tol = heading_tolerance_deg
    bounds = (-180.0, 180.0) if tol is None else (-tol - step, tol + step)
    node = nearest_node(grid, fit.row, fit.col)
    n_row, n_col = divmod(node, grid.n_cols)
    model = Model(meas.weight, occlusion_cap_deg2(meas.occlusion_weight, sigma), meas.map_sigma_m)
    return refine_exact(grid.terrain, grid.dx_m, grid.dy_m, meas.elevation_deg, n_row, n_col, grid.n_cols,
                        fit.heading_deg, height_m, (fit.row, fit.col), sigma, bounds, model, position_prior,
                        start_spread_cells=POLISH_SPREAD_CELLS, tilt_sigma_deg=TILT_SIGMA_DEG)


def rival_fits(fits: list[Fit], best: Fit, grid: SkylineGrid, lp: np.ndarray, meas: Measurement, temper: float,
               position_prior: PositionPrior | None, unpolished: Fit | None = None,
               polish: Callable[[Fit], Fit | None] | None = None) -> list[Fit]:
    """The exact fits at other places (more than SAME_ANSWER_CELLS from ``best``) whose upper
    log-posterior, at the measurement's sigma interval and tempering, reaches ``best``'s lower one.

    ``best`` may be ``unpolished`` fitted again (:func:`polished_fit`, with the head's tilt), which
    the other fits were not: a place whose fit reaches ``unpolished``'s is then fitted again the same
    way (``polish``) and weighed so against ``best``.  Like is compared with like: a tilt can take more
    from another place's residuals than from the answer's (a levelled head's residual tilt at the true
    place, fitted only at the wrong one, made it look the better place)."""
    def away(f: Fit) -> bool:
        return math.hypot(f.row - best.row, f.col - best.col) > SAME_ANSWER_CELLS

    others = [f for f in fits if away(f)]
    if not others:
        return []
    lo, up = fit_bounds([best] + others, grid, lp, meas, position_prior, temper)
    rivals = [f for i, f in enumerate(others, start=1) if up[i] >= lo[0]]
    if unpolished is None or polish is None:
        return rivals
    lo_u, up_u = fit_bounds([unpolished] + others, grid, lp, meas, position_prior, temper)
    for i, f in enumerate(others, start=1):
        if up[i] >= lo[0] or up_u[i] < lo_u[0]:
            continue
        again = polish(f)
        if again is None or not away(again):
            continue
        lo_p, up_p = fit_bounds([best, again], grid, lp, meas, position_prior, temper)
        if up_p[1] >= lo_p[0]:
            rivals.append(again)
    return rivals


def answer_covariance(fit: Fit | None, meas: Measurement, temper: float,
                      conf: confidence.Modes) -> np.ndarray:
    """The answer's (row, col) covariance (cells^2): the exact fit's curvature at the learned sigma,
    tempered, with its priors; without one, the spread of the answer's mode over its nodes."""
    if fit is not None:
        cov = tempered_covariance(fit, meas.sigma_ref_deg, temper)
        if cov is not None:
            return cov
    return conf.main_covariance_cells
