"""Step 5 of a search: the answer refined between nodes.

On a map's terrain (``exact.py``), every distinct mode of the region gets one exact render (a
look, heading scanned along it), the best few looks are fitted in full (position, heading, eye
height) and the fit of highest lower posterior is the answer.  A fit whose look promised as much as
the best's but which ends far worse stopped in a poor optimum, and is made again from its node's
neighbours.  The looks run on threads of their
own (their ray march releases the GIL).  Without terrain, the answer is refined between the
database's skylines (``subcell.py``).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba
import numpy as np

from appliance.estimator.exact import Fit, Model, PositionPrior
from appliance.estimator.exact import refine as refine_exact
from appliance.estimator.exact import screen as screen_exact
from appliance.estimator.likelihood import occlusion_cap_deg2, sigma_midpoint
from appliance.estimator.measurement import Measurement
from appliance.estimator.posteriors import Answer, Posteriors, most_likely_fit
from appliance.estimator.rescore import Rescored
from appliance.estimator.skyline_grid import SkylineGrid
from appliance.estimator.subcell import refine_subcell

_T = TypeVar("_T")

#: How many of the region's most likely nodes (at least two cells apart) get one exact render, and
#: how many of those the refinement fits in full.
SCREEN_NODES = 40
REFINE_NODES = 3

#: A fit down to CONVERGED_RMS times CONVERGED_SIGMA_DEG (what a skyline read to the map's own
#: precision leaves) has found the place; RIVAL_LOOKS more modes are then looked at, and fitted only
#: if their look comes within LOOK_MARGIN times its residual sum.  A fit above it may stand at the
#: wrong place however well it does against the search's sigma (the sigma learned from it would
#: then vouch for it), so every mode is looked at.
CONVERGED_RMS = 1.5
CONVERGED_SIGMA_DEG = 0.05
RIVAL_LOOKS = 4
LOOK_MARGIN = 2.0
#: A fit whose look came within LOOK_MARGIN of the best look but whose residual sum ends above this many
#: times the best fit's is made again from the node's neighbours (:meth:`_RefineContext._fit_again`).
FAILED_FIT_RATIO = 2.0
#: Modes whose upper log-posterior lies further than this below the best's get no look.
SCREEN_MARGIN_NATS = 30.0
#: A look stands for the neighbourhood of its point, this spread (1 sigma, cells) around it.
SCREEN_SPREAD_CELLS = 0.3


class _RefineContext:
    """What the exact refinement of one estimate shares: looks (one render per start, heading
    scanned) and full fits of the best-looking ones."""

    def __init__(self, grid: SkylineGrid, m: np.ndarray, rescore: np.ndarray, shifts_r: np.ndarray,
                 ssd_r: np.ndarray, moves_r: np.ndarray, bounds: tuple[float, float], height_m: float | None,
                 sigma: float, model: Model, position_prior: PositionPrior | None) -> None:
        self.grid, self.m, self.rescore, self.shifts_r, self.ssd_r, self.moves_r = grid, m, rescore, shifts_r, ssd_r, \
            moves_r
        self.bounds, self.height_m, self.sigma, self.model = bounds, height_m, sigma, model
        self.position_prior = position_prior

    def _start(self, cand: int) -> tuple[tuple[float, float], tuple[float, float], float, float]:
        """The node, where its linearised fit moved it, and the headings of both (deg)."""
        g, n_az = self.grid, self.m.size
        step = 360.0 / n_az
        ir = int(np.searchsorted(self.rescore, cand))
        sh = float(self.shifts_r[ir, int(np.argmin(self.ssd_r[ir]))])
        if sh > n_az / 2:
            sh -= n_az
        c_row, c_col = divmod(cand, g.n_cols)
        de, dn, dphi, _ = self.moves_r[ir]
        return (float(c_row), float(c_col)), (c_row - dn / g.dy_m, c_col + de / g.dx_m), sh * step, sh * step + dphi

    def fit_from_linear(self, cand: int) -> Fit | None:
        _, moved, _, phi = self._start(cand)
        return self._fit(cand, moved, phi)

    def _fit(self, cand: int, start: tuple[float, float], phi: float) -> Fit | None:
        """The exact fit from ``start`` (fractional row, col) and heading ``phi`` (deg) near node ``cand``.

        With a position prior the fit minimises the skyline's cost plus the prior's.  The prior pulls
        from the first step, while the annealing still lets the skyline steer only loosely, and can
        lead the fit into another basin than the skyline's own between two nodes: the fit is also
        made without the prior, then polished under it from there, and the one of lower total cost
        kept."""
        g = self.grid
        assert g.terrain is not None
        c_row, c_col = divmod(cand, g.n_cols)

        def fit(at: tuple[float, float], heading: float, prior: PositionPrior | None) -> Fit | None:
            assert g.terrain is not None
            return refine_exact(g.terrain, g.dx_m, g.dy_m, self.m, c_row, c_col, g.n_cols, heading, self.height_m,
                                at, self.sigma, self.bounds, self.model, prior)

        pulled = fit(start, phi, self.position_prior)
        if self.position_prior is None:
            return pulled
        free = fit(start, phi, None)
        if free is None:
            return pulled
        polished = fit((free.row, free.col), free.heading_deg, self.position_prior)
        fits = [f for f in (pulled, polished) if f is not None]
        return min(fits, key=self._posterior_cost, default=None)

    def _posterior_cost(self, fit: Fit) -> float:
        """What a fit under the position prior minimises (chi-square units): the skyline's cost at
        sigma plus the prior's Mahalanobis term."""
        assert self.position_prior is not None
        return fit.ssd / (self.sigma * self.sigma) + self.position_prior.cost(np.array([fit.row, fit.col]))

    def look_at(self, fit: Fit) -> float:
        """The cost of a look from where a fit ended (what other looks must come near to rival it)."""
        g = self.grid
        assert g.terrain is not None
        node = min(max(int(round(fit.row)), 0), g.n_rows - 1) * g.n_cols + min(max(int(round(fit.col)), 0),
                                                                                g.n_cols - 1)
        cost, _ = screen_exact(g.terrain, g.dx_m, g.dy_m, self.m, fit.row, fit.col, float(g.convergence_deg[node]),
                               fit.heading_deg, self.bounds, self.height_m, self.sigma, self.model,
                               SCREEN_SPREAD_CELLS)
        return cost

    def looks(self, nodes: list[int]) -> Callable[[], list[_Look]]:
        """One look at each node (from the node and from its linearised move), started on the look
        threads (:func:`start_on_threads`): what waits for them, (cost, node, start, heading) in the
        nodes' order."""
        g = self.grid
        assert g.terrain is not None
        starts = []
        for cand in nodes:
            node, moved, phi_node, phi_moved = self._start(cand)
            starts += [(cand, node, phi_node), (cand, moved, phi_moved)]

        def look(item: tuple[int, tuple[float, float], float]) -> tuple[float, float]:
            cand, start, phi0 = item
            assert g.terrain is not None
            return screen_exact(g.terrain, g.dx_m, g.dy_m, self.m, start[0], start[1], float(g.convergence_deg[cand]),
                                phi0, self.bounds, self.height_m, self.sigma, self.model, SCREEN_SPREAD_CELLS)

        pending = start_on_threads(look, starts)
        return lambda: [(cost, cand, start, phi) for (cand, start, _), (cost, phi) in zip(starts, pending())]

    def fit_looked(self, looks: list[_Look], beat: float = math.inf) -> list[Fit]:
        """Full fits of the best-looking REFINE_NODES nodes of ``looks`` (:meth:`looks`), of those
        only whose look comes within LOOK_MARGIN of ``beat`` (the look from a fit already made) when
        one is given."""
        fits: list[Fit] = []
        refined: list[int] = []
        made: list[tuple[float, int, float, Fit]] = []  # each fit with its look's cost, node and heading
        for cost, cand, start, phi in sorted(looks, key=lambda v: v[0]):
            if not math.isfinite(cost) or len(refined) >= REFINE_NODES or cost > LOOK_MARGIN * beat:
                break
            if cand in refined:
                continue
            refined.append(cand)
            fit = self._fit(cand, start, phi)
            if fit is not None:
                fits.append(fit)
                made.append((cost, cand, phi, fit))
        if len(made) < 2:
            return fits
        best_look, best_ssd = min(m[0] for m in made), min(m[3].ssd for m in made)
        for i, (cost, cand, phi, fit) in enumerate(made):
            if cost <= LOOK_MARGIN * best_look and fit.ssd > FAILED_FIT_RATIO * best_ssd:
                fits[i] = self._fit_again(cand, phi, fit)
        return fits

    def _fit_again(self, cand: int, phi: float, failed: Fit) -> Fit:
        """The best of ``failed`` (the fit from node ``cand``) and fits from the node's four neighbours
        (heading ``phi``): a place whose look promised as much as the best's but whose fit ended far
        worse stopped in a poor optimum, and a start a node over may find the place's own."""
        g = self.grid
        row, col = divmod(cand, g.n_cols)
        best = failed
        for r, c in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            node = r * g.n_cols + c
            if not (0 <= r < g.n_rows and 0 <= c < g.n_cols) or not math.isfinite(float(g.offset_deg[node])):
                continue
            again = self._fit(node, (float(r), float(c)), phi)
            if again is not None and again.ssd < best.ssd:
                best = again
        return best


#: One look of the refinement: its cost, the node, the start (fractional row, col) and the heading (deg).
_Look = tuple[float, int, tuple[float, float], float]
_look_pools: dict[int, ThreadPoolExecutor] = {}
_look_pool_lock = threading.Lock()
_R = TypeVar("_R")


def start_on_threads(work: Callable[[_T], _R], items: list[_T]) -> Callable[[], list[_R]]:
    """``work`` on every item started on as many threads as the compiled kernels may use (numba's
    thread count; with one, as on a tiled search's own threads, done here in turn): what waits for
    the results, in the items' order.  For work whose time is mostly ray marches, which release the
    GIL: each item's result is what it would be on the caller's thread."""
    threads = min(numba.get_num_threads(), len(items))
    if threads <= 1:
        made = [work(v) for v in items]
        return lambda: made
    with _look_pool_lock:
        pool = _look_pools.get(threads)
        if pool is None:
            pool = _look_pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="viper-look",
                                                             initializer=numba.set_num_threads, initargs=(1,))
    futures = [pool.submit(work, v) for v in items]
    return lambda: [f.result() for f in futures]



def _distinct_nodes(nodes: np.ndarray, score: np.ndarray, n_cols: int, count: int, first: int) -> list[int]:
    """The best node, then the highest-scoring ``nodes`` at least two cells from those chosen."""
    chosen = [int(first)]
    for v in nodes[np.argsort(-score[nodes])]:
        if len(chosen) >= count:
            break
        r, c = divmod(int(v), n_cols)
        if all(max(abs(r - cr), abs(c - cc)) >= 2 for cr, cc in (divmod(u, n_cols) for u in chosen)):
            chosen.append(int(v))
    return chosen



def refined(grid: SkylineGrid, meas: Measurement, lp: np.ndarray, rescored: Rescored, post: Posteriors,
            answer: Answer, heading_tolerance_deg: float | None, height_m: float | None,
             position_prior: PositionPrior | None) -> tuple[Answer, list[Fit], Fit | None, list[str]]:
    """Step 5: the answer refined between nodes, the exact fits made (the best's rivals among them),
    the best fit (None without terrain or fit) and the notes."""
    in_rescore = np.zeros(post.node_lower.size, dtype=bool)
    in_rescore[rescored.nodes] = True
    scored = post.region[in_rescore[post.region]]
    if grid.terrain is None:
        return _subcell_answer(grid, meas, lp, rescored, post, scored, answer), [], None, []
    fits = _exact_fits(grid, meas, rescored, post, scored, heading_tolerance_deg, height_m, position_prior)
    if not fits:
        return answer, [], None, []
    best_fit = most_likely_fit(fits, grid, lp, meas, position_prior)
    notes: list[str] = []
    if best_fit.occluded > 0.05 * best_fit.n:
        notes.append(f"occluded: {best_fit.occluded:.0f} of {best_fit.n} azimuths stand above the map's "
                     "terrain (trees, buildings, masts?) and were left out")
    rms = math.sqrt(best_fit.ssd / max(best_fit.n - best_fit.occluded, 1.0))
    return (Answer(best_fit.row, best_fit.col, best_fit.heading_deg, rms, best_fit.covariance_cells),
            fits, best_fit, notes)


def _exact_fits(grid: SkylineGrid, meas: Measurement, rescored: Rescored, post: Posteriors, scored: np.ndarray,
                heading_tolerance_deg: float | None, height_m: float | None,
                position_prior: PositionPrior | None) -> list[Fit]:
    """Step 5 on a map's terrain: every distinct mode of the region (``scored``: its rescored nodes)
    gets one exact render, heading scanned along it; the best few of those are fitted in full
    (position in grid cells, heading in deg, eye height in m)."""
    sig_lo, step, tol = meas.sigma_lo_deg, grid.az_step_deg, heading_tolerance_deg
    bounds = (-180.0, 180.0) if tol is None else (-tol - step, tol + step)
    exact_model = Model(meas.weight, occlusion_cap_deg2(meas.occlusion_weight, sig_lo), meas.map_sigma_m)
    ctx = _RefineContext(grid, meas.elevation_deg, rescored.nodes, rescored.shifts, rescored.ssd, rescored.moves,
                         bounds, height_m, sig_lo, exact_model, position_prior)
    # the modes worth a look: those whose upper posterior comes within SCREEN_MARGIN_NATS of the
    # best's (the region itself is wider by the whole of sigma's interval)
    top_up = float(np.max(post.node_upper[scored]))
    worth = scored[post.node_upper[scored] >= top_up - SCREEN_MARGIN_NATS]
    modes = _distinct_nodes(worth, post.node_lower, grid.n_cols, SCREEN_NODES, post.best_node)
    # the best mode first, fitted straight from where its linearised fit moved it; when that comes
    # down to the sensor's noise, a few more looks check for a rival, else all of them
    # (the looks at those few are made on the look threads while the best mode is fitted)
    rival_looks = ctx.looks(modes[1 : 1 + RIVAL_LOOKS])
    first = ctx.fit_from_linear(modes[0])
    if first is not None and first.rms_deg <= CONVERGED_RMS * CONVERGED_SIGMA_DEG:
        return [first] + ctx.fit_looked(rival_looks(), ctx.look_at(first))
    head, tail = ctx.looks(modes[:1]), ctx.looks(modes[1 + RIVAL_LOOKS :])
    return ([] if first is None else [first]) + ctx.fit_looked(head() + rival_looks() + tail())


def _subcell_answer(grid: SkylineGrid, meas: Measurement, lp: np.ndarray, rescored: Rescored, post: Posteriors,
                    scored: np.ndarray, answer: Answer) -> Answer:
    """Step 5 with no terrain: the most likely nodes of the region (the best first) refined between
    the database's skylines (``subcell.py``); the fit of the best likelihood at sigma's midpoint plus
    the prior of its nearest node is kept, else the grid's ``answer``."""
    n_az, step, n, rescore = grid.n_azimuths, grid.az_step_deg, meas.n_valid, rescored.nodes
    mid = sigma_midpoint(meas.sigma_lo_deg, meas.sigma_hi_deg)
    order = np.argsort(-post.node_lower[scored])[:REFINE_NODES]
    tries = [post.best_node] + [int(v) for v in scored[order] if int(v) != post.best_node]
    best_blend = (-math.inf, answer.rms_deg, answer.row, answer.col, answer.heading_deg)
    for cand in tries:
        k_c = int(np.argmin(rescored.ssd[np.searchsorted(rescore, cand)]))
        sh = float(rescored.shifts[np.searchsorted(rescore, cand), k_c])
        if sh > n_az / 2:
            sh -= n_az
        r_c, c_c, h_c, rms_c = refine_subcell(grid, meas.elevation_deg, cand, sh * step, math.inf)
        near = int(round(r_c)) * grid.n_cols + int(round(c_c))
        score = -n * rms_c * rms_c / (2.0 * mid * mid) + lp[near]
        if score > best_blend[0]:
            best_blend = (score, rms_c, r_c, c_c, h_c)
    if not math.isfinite(best_blend[0]):
        return answer
    _, rms, frow, fcol, heading = best_blend
    return Answer(frow, fcol, heading, rms)
