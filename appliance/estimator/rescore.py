"""Step 2's second pass: the plausible nodes scored on every azimuth.

The first pass (``coarse.py``) bounds every node's likelihood; the nodes whose upper bound comes
within RESCORE_MARGIN_NATS of the best lower one are scored again on every azimuth and every shift
of their band of headings.  With parallax, each node's best shift is then moved by its own
first-order parallax within its cell (``parallax.linearised_fit``), so the grid's spacing no longer
decides the score.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.errors import EstimationError
from appliance.estimator import parallax
from appliance.estimator.likelihood import capped_cost, kernel_cap
from appliance.estimator.measurement import Measurement
from appliance.estimator.search import TauModel, ssd_for_shifts
from appliance.estimator.skyline_grid import SkylineGrid

#: Nodes whose first-pass upper log-likelihood lies within this many nats of the best first-pass
#: lower log-likelihood are rescored on every azimuth.
RESCORE_MARGIN_NATS = 200.0
MIN_RESCORE = 64


@dataclass(frozen=True)
class Plausible:
    """The nodes worth rescoring, and every node's first-pass bounds (nats)."""

    nodes: np.ndarray  # sorted node indices
    log_lower: np.ndarray  # (n_nodes,) lower log-likelihood plus log prior
    log_upper: np.ndarray  # (n_nodes,) upper log-likelihood plus log prior
    scored_nodes: int  # nodes with a finite first-pass score


def plausible_nodes(bounds: tuple[np.ndarray, np.ndarray, int], floor: float | None,
                    temper: float = 1.0) -> Plausible:
    """Step 2, the nodes worth every azimuth: those whose first-pass upper log-posterior (nats,
    ``bounds``: :func:`first_pass_bounds`, which the result takes over) comes within
    RESCORE_MARGIN_NATS of the best lower one (or of ``floor``, when higher: a lower bound reached
    elsewhere on the lattice), at least MIN_RESCORE of them.  Bounds tempered by ``temper`` are
    held to the margin tempered alike: the nodes a search at the given noise would rescore, as a
    single grid's search weighs its learned noise over the nodes it rescored at the given one."""
    node_lo, node_up, scored = bounds
    n_nodes = node_lo.size
    best_lo = float(np.max(node_lo)) if floor is None else max(float(np.max(node_lo)), floor)
    rescore = np.nonzero(node_up >= best_lo - RESCORE_MARGIN_NATS * temper)[0]
    if rescore.size < MIN_RESCORE:
        rescore = np.sort(np.argpartition(-node_up, min(MIN_RESCORE, n_nodes) - 1)[:MIN_RESCORE])
    return Plausible(rescore, node_lo, node_up, scored)


@dataclass(frozen=True)
class Rescored:
    """The plausible nodes scored on every azimuth (float64)."""

    nodes: np.ndarray  # (n_r,) sorted node indices
    shifts: np.ndarray  # (n_r, n_k) azimuth steps
    ssd: np.ndarray  # (n_r, n_k) weighted residual sums, deg^2
    occluded: np.ndarray  # (n_r, n_k) weight of the occluded measurements
    half_penalty: np.ndarray  # (n_r, 1) half the log-normaliser, nats
    moves: np.ndarray  # (n_r, 4) linearised moves: east m, north m, heading deg, eye m (0 with no parallax)


def rescore_nodes(grid: SkylineGrid, meas: Measurement, rescore: np.ndarray, shifts: np.ndarray) -> Rescored:
    """Step 2, the second pass: the plausible nodes at every azimuth and every shift of their band;
    with parallax, each node's best shift then moved by its own first-order parallax within its cell
    (east, north in m, heading in deg, eye in m)."""
    m, w_grid, cap = meas.elevation_deg, meas.weight, meas.cap_deg2
    tau = None
    gradient = None
    if grid.distance_codes is not None:
        # the ground's gradient at the plausible nodes, made once for both kernels; the sums pick
        # each node's shift, its normaliser is the linearised fit's, below
        gradient = grid.ground_gradient_at(rescore)
        tau = TauModel(grid.distance_codes, grid.ground_gradient2_at(rescore, gradient), grid.rho2_m2,
                       grid.inverse_range2, meas.sigma_ref_deg, meas.map_sigma_m, with_penalty=False)
    occ_r32 = np.empty((rescore.size, shifts.shape[1]), dtype=np.float32)
    ssd_r = ssd_for_shifts(grid.codes, grid.offset_deg, grid.step_deg, m, shifts, rows=rescore,
                           tau=tau, weights=w_grid, cap_deg2=cap, occluded=occ_r32)
    ssd_r = ssd_r.astype(np.float64)
    occ_r = occ_r32.astype(np.float64)
    pen_r = np.zeros((rescore.size, 1))
    if not np.isfinite(ssd_r).any():
        raise EstimationError("no candidate node has terrain along the measured azimuths")
    shifts_r = np.asarray(shifts)
    moves_r = np.zeros((rescore.size, 4))
    if grid.has_parallax:
        # each node's skyline moved by its own first-order parallax within its cell: the grid's
        # spacing no longer decides, what the linear model cannot say does (LINEARISED_SCALE)
        k_best = np.argmin(capped_cost(ssd_r, occ_r, cap), axis=1)
        shifts_r = shifts_r[np.arange(rescore.size), k_best][:, None]
        ssd_lin, pen_lin, moves_r, occ_lin = _linearised(grid, m, w_grid, rescore, shifts_r[:, 0],
                                                         meas.sigma_ref_deg, cap, meas.map_sigma_m, gradient)
        ssd_r, occ_r = ssd_lin[:, None], occ_lin[:, None]
        pen_r = 0.5 * pen_lin[:, None]
    return Rescored(rescore, shifts_r, ssd_r, occ_r, pen_r, moves_r)



def _linearised(grid: SkylineGrid, m: np.ndarray, w: np.ndarray, rows: np.ndarray, shifts: np.ndarray,
                sig_ref: float, cap: float, map_sigma_m: float,
                gradient: tuple[np.ndarray, np.ndarray] | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted residual sums (deg^2), log-normalisers, moves (east m, north m, heading deg, eye m)
    and occluded weights of ``rows`` at whole ``shifts`` under the linearised parallax model
    (``parallax.py``); ``gradient`` is the ground's gradient at those rows when already made
    (:meth:`SkylineGrid.ground_gradient_at`)."""
    assert grid.distance_codes is not None
    valid = np.isfinite(m)
    jj = np.nonzero(valid)[0].astype(np.int64)
    mj = m[jj].astype(np.float64)
    # the kernel reads the rows' nodes only
    ge, gn = grid.ground_gradient_at(rows) if gradient is None else gradient
    gamma = grid.convergence_deg
    out = np.empty(rows.size)
    pen = np.empty(rows.size)
    occ = np.empty(rows.size)
    moves = np.empty((rows.size, 4))
    half = 0.5 * max(grid.dx_m, grid.dy_m)
    parallax.linearised_fit(grid.codes, grid.distance_codes, grid.offset_deg, grid.step_deg, ge, gn, gamma, jj, mj,
                            np.asarray(rows, dtype=np.int64), np.asarray(shifts, dtype=np.int64), grid.rho2_m2,
                            grid.inverse_range2, sig_ref * sig_ref, parallax.LINEARISED_SCALE**2, half * half,
                            grid.az_step_deg**2, w[jj].astype(np.float64), kernel_cap(cap),
                            map_sigma_m * map_sigma_m, out, pen, moves, occ)
    return out, pen, moves, occ
