"""Steps 3 and 4 of a search: posterior bounds, the best candidate and the region of nodes.

Each rescored candidate's likelihood is bounded over sigma's interval (the n-sample Gaussian with
the occlusion mixture, ``likelihood.py``), counting a ``temper`` share of itself once the noise is
learned, and the lower and upper posteriors follow under the prior.  The best candidate is the one
of highest lower posterior; the region, the nodes whose upper posterior reaches it.  The exact fits
of the refinement are ranked the same way (:func:`fit_bounds`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.estimator.exact import Fit, PositionPrior
from appliance.estimator.likelihood import (
    mixture_log_likelihood,
    mixture_log_likelihood_bounds,
    posterior_bounds,
    sigma_midpoint,
)
from appliance.estimator.measurement import Measurement
from appliance.estimator.rescore import Plausible, Rescored
from appliance.estimator.skyline_grid import SkylineGrid, nearest_node

#: Refined fits closer than this (cells) to the best are the same answer.
SAME_ANSWER_CELLS = 2.0


@dataclass(frozen=True)
class Posteriors:
    """The best candidate, every node's posterior bounds and the region (log posteriors in nats)."""

    best_r: int  # the best candidate's row in :class:`Rescored`
    best_k: int  # and its shift's column
    best_node: int
    best_log_lower: float
    best_log_upper: float
    node_lower: np.ndarray  # (n_nodes,) log lower posterior of each node's best heading
    node_upper: np.ndarray  # (n_nodes,)
    region: np.ndarray  # nodes whose upper posterior reaches the best's lower one
    posterior_mid: np.ndarray  # (n_nodes,) posterior at sigma's midpoint, marginal over heading
    log_sum_lo: float  # log of the sum of every rescored candidate's unnormalised lower posterior
    log_sum_up: float  # and of its upper one
    log_sum_mid: float  # log of the sum of the unnormalised midpoint posterior over the rescored nodes
    best_lo_unnormalised: float  # the best candidate's unnormalised log lower posterior
    best_up_unnormalised: float
    node_upper_unnormalised: np.ndarray  # (n_nodes,) unnormalised log upper posterior of each node's best heading


def posteriors(meas: Measurement, lp: np.ndarray, plausible: Plausible, rescored: Rescored,
               temper: float = 1.0) -> Posteriors:
    """Steps 3 and 4: exact posterior bounds over the rescored candidates, the best candidate and the
    region.  The other nodes lie hundreds of nats below the best: their share of the sums is nil, and
    their own posteriors are their first-pass likelihood over the (unchanged) sum of the rest.  The
    log-likelihood counts ``temper`` of itself (each azimuth that share of an independent one)."""
    sig_lo, sig_hi, n_eff, occlusion_weight = meas.sigma_lo_deg, meas.sigma_hi_deg, meas.n_eff, meas.occlusion_weight
    rescore, ssd_r, occ_r = rescored.nodes, rescored.ssd, rescored.occluded
    lp_r = lp[rescore, None] - temper * rescored.half_penalty
    lo_r, up_r = mixture_log_likelihood_bounds(ssd_r, n_eff, occ_r, sig_lo, sig_hi, occlusion_weight)
    lo_r, up_r = temper * lo_r, temper * up_r
    post = posterior_bounds(lo_r + lp_r, up_r + lp_r)
    best_flat = int(np.argmax(post.log_lower))
    best_r, best_k = divmod(best_flat, ssd_r.shape[1])
    best_lower_log = float(post.log_lower.ravel()[best_flat])
    log_sum_up = float(np.logaddexp.reduce((up_r + lp_r).ravel()))
    log_sum_lo = float(np.logaddexp.reduce((lo_r + lp_r).ravel()))
    # the first-pass lower bounds become the normalised map in place
    node_lower = plausible.log_lower
    node_lower -= log_sum_up
    node_upper = plausible.log_upper - log_sum_lo
    node_lower[rescore] = np.max(post.log_lower, axis=1)
    node_upper[rescore] = np.max(post.log_upper, axis=1)
    region = np.nonzero(node_upper >= best_lower_log)[0]
    # the first-pass upper bounds are not needed past this point: their array takes the rescored values
    node_up_unnormalised = plausible.log_upper
    node_up_unnormalised[rescore] = np.max(up_r + lp_r, axis=1)

    # a precise posterior at sigma's midpoint, marginal over heading: what fusion carries forward
    # (nil at the nodes not rescored)
    mid = sigma_midpoint(sig_lo, sig_hi)
    ll_mid = temper * mixture_log_likelihood(ssd_r, n_eff, occ_r, mid, occlusion_weight) + lp_r
    node_mid_r = np.logaddexp.reduce(np.where(np.isfinite(ll_mid), ll_mid, -np.inf), axis=1)
    log_sum_mid = float(np.logaddexp.reduce(node_mid_r))
    posterior_mid = np.zeros(node_lower.size)
    posterior_mid[rescore] = np.exp(node_mid_r - log_sum_mid)
    return Posteriors(best_r, best_k, int(rescore[best_r]), best_lower_log,
                       float(post.log_upper.ravel()[best_flat]), node_lower, node_upper, region, posterior_mid,
                       log_sum_lo, log_sum_up, log_sum_mid, float((lo_r + lp_r)[best_r, best_k]),
                       float((up_r + lp_r)[best_r, best_k]), node_up_unnormalised)


@dataclass(frozen=True)
class Answer:
    """A position in fractional grid (row, col), the heading correction (deg), the RMS residual (deg)
    and, for an exact fit, the covariance of (row, col) (cells^2)."""

    row: float
    col: float
    heading_deg: float
    rms_deg: float
    covariance_cells: np.ndarray | None = None


def grid_answer(grid: SkylineGrid, meas: Measurement, rescored: Rescored, post: Posteriors) -> Answer:
    """Step 4's answer: the best candidate's node, its heading correction in (-180, 180] deg and its
    RMS residual (deg)."""
    n_az = grid.n_azimuths
    shift_steps = float(rescored.shifts[post.best_r, post.best_k])
    if shift_steps > n_az / 2:
        shift_steps -= n_az
    row, col = divmod(post.best_node, grid.n_cols)
    rms = math.sqrt(float(rescored.ssd[post.best_r, post.best_k]) / meas.n_valid)
    return Answer(float(row), float(col), shift_steps * grid.az_step_deg, rms)



def fit_bounds(fits: list[Fit], grid: SkylineGrid, log_prior: np.ndarray, meas: Measurement,
                position_prior: PositionPrior | None = None, temper: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Each fit's lower and upper log-posterior (nats): the exact likelihood over the measurement's
    sigma interval, counting ``temper`` of itself, plus the prior of its nearest node, or the
    ``position_prior`` where there is one (the same belief, held between nodes)."""
    n = meas.n_eff
    ssd = np.array([f.ssd * n / max(f.n, 1) for f in fits])
    occ = np.array([f.occluded * n / max(f.n, 1) for f in fits])
    lo, up = mixture_log_likelihood_bounds(ssd, n, occ, meas.sigma_lo_deg, meas.sigma_hi_deg, meas.occlusion_weight)
    if position_prior is not None:
        lp = np.array([-0.5 * position_prior.cost(np.array([f.row, f.col])) for f in fits])
    else:
        lp = np.array([log_prior[nearest_node(grid, f.row, f.col)] for f in fits])
    return temper * lo + lp, temper * up + lp


def most_likely_fit(fits: list[Fit], grid: SkylineGrid, log_prior: np.ndarray, meas: Measurement,
              position_prior: PositionPrior | None = None) -> Fit:
    """The fit of highest lower log-posterior (:func:`fit_bounds`)."""
    lo, _ = fit_bounds(fits, grid, log_prior, meas, position_prior)
    return fits[int(np.argmax(lo))]
