"""Position (and heading) from one measured skyline against a skyline database.

Candidates are theta = (node, heading correction phi).  The flow:

1. Resample the measured skyline onto the database's azimuth grid (linear, circular; a gap stays
   missing).
2. Score every node: with a compass, phi spans +-beta around zero in azimuth steps; with no compass,
   every phi (FFT cross-correlation), keeping each node's best band of headings.  A first pass on
   every fourth azimuth finds the plausible nodes; they, and only they, are scored on every azimuth.
   Nodes left on the first pass are far less likely than the best (hundreds of nats), so their
   first-pass score stands in for the full one in the posterior's sums.
3. Lower and upper likelihoods over sigma in [sigma_l, sigma_u], then the lower and upper
   posteriors (``likelihood.py``) under the prior (uniform, or the fused one).
4. Best estimate: the candidate with the highest lower posterior.  Region: the nodes holding a
   candidate whose upper posterior reaches the best's lower posterior.
5. Sub-cell refinement (``refine.py``): the skyline between nodes is interpolated from the four
   around it, and position and heading are searched continuously near the best node.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TypeVar

import numba
import numpy as np

from appliance.errors import EstimationError, InputError
from appliance.estimator import confidence, parallax
from appliance.estimator.exact import Fit, Model, PositionPrior, Terrain, marginal_position_covariance
from appliance.estimator.exact import refine as refine_exact
from appliance.estimator.exact import screen as screen_exact
from appliance.estimator.likelihood import (
    best_column_bounds,
    mixture_log_likelihood,
    mixture_log_likelihood_bounds,
    occlusion_cap_deg2,
    posterior_bounds,
)
from appliance.estimator.search import (
    TauModel,
    box_decimate,
    decimated,
    ssd_coarse,
    ssd_coarse_best,
    ssd_for_shifts,
)

_T = TypeVar("_T")

#: The defaults, the same as the configuration's ([estimator] in appliance/config.py, a test keeps
#: them equal): the interval the search starts from (the estimate's is learned from the skyline), the
#: compass's tolerance, and the prior share of azimuths hidden by what the map lacks.
SIGMA_DEG = (0.3, 0.8)
HEADING_TOLERANCE_DEG = 4.0
OCCLUSION_WEIGHT = 0.05

COARSE_STRIDE = 4
#: Nodes whose first-pass upper log-likelihood lies within this many nats of the best first-pass
#: lower log-likelihood are rescored on every azimuth.
RESCORE_MARGIN_NATS = 200.0
MIN_RESCORE = 64
#: How many of the region's most likely nodes (at least two cells apart) get one exact render, and
#: how many of those the refinement fits in full.
SCREEN_NODES = 40
REFINE_NODES = 3
#: A search is made again with the sigma learned when its upper end lies below this share of the
#: search's lower end.
SEARCH_AGAIN_RATIO = 0.5
#: ... and with the occluders' share learned when the best fit leaves more than this many times the
#: prior share to them.
OCCLUSION_AGAIN_RATIO = 2.0
#: A fit down to CONVERGED_RMS times CONVERGED_SIGMA_DEG (what a skyline read to the map's own
#: precision leaves) has found the place; RIVAL_LOOKS more modes are then looked at, and fitted only
#: if their look comes within LOOK_MARGIN times its residual sum.  A fit above it may stand at the
#: wrong place however well it does against the search's sigma (the sigma learned from it would
#: then vouch for it), so every mode is looked at.
CONVERGED_RMS = 1.5
CONVERGED_SIGMA_DEG = 0.05
RIVAL_LOOKS = 4
LOOK_MARGIN = 2.0
#: Modes whose upper log-posterior lies further than this below the best's get no look.
SCREEN_MARGIN_NATS = 30.0
#: A look stands for the neighbourhood of its point, this spread (1 sigma, cells) around it.
SCREEN_SPREAD_CELLS = 0.3
#: A region (sigma as given, not learned) wider than this many map cells is reported as ambiguous.
AMBIGUOUS_CELLS = 25
#: A heading correction within this much (deg) of the compass's tolerance is at its limit; the search
#: is then made again with a tolerance this much (deg) wider.
HEADING_LIMIT_MARGIN_DEG = 0.5
HEADING_WIDEN_DEG = 3.0
#: A best fit that leaves more than this share of the azimuths to occluders has not explained the skyline.
MAX_OCCLUDED_SHARE = 0.5
#: The prior on a levelled head's residual tilt (deg, 1 sigma per axis), fitted with the learned sigma.
TILT_SIGMA_DEG = 0.3
#: The position's spread (cells) when the best fit is fitted again at the learned sigma.
POLISH_SPREAD_CELLS = 0.05
#: Refined fits closer than this (cells) to the best are the same answer.
SAME_ANSWER_CELLS = 2.0
#: The smallest field of view (deg of valid azimuths) a skyline must cover.
MIN_FIELD_OF_VIEW_DEG = 20.0


@dataclass(frozen=True)
class SkylineGrid:
    """What the estimator needs of a skyline database: uint8 codes with per-node offset and step,
    and the node grid's shape and ground spacing.  Pure arrays: no files, no projections."""

    codes: np.ndarray  # (n_nodes, n_az) uint8, 255 = no terrain
    offset_deg: np.ndarray  # (n_nodes,) float32, NaN = node on nodata
    step_deg: np.ndarray  # (n_nodes,) float32
    n_rows: int
    n_cols: int
    dx_m: float
    dy_m: float
    #: (n_nodes, n_az) uint8 log-quantised range of each horizon point (255 = none); None = unknown
    distance_codes: np.ndarray | None = None
    ground_m: np.ndarray | None = None
    terrain: Terrain | None = None
    distance_min_m: float = 1.0
    distance_log_step: float = 0.05
    #: the first pass made ahead (at the database's build): :attr:`coarse`, and :meth:`coarse_tau2`
    #: with no map error; None = made on first use
    first_pass: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def n_azimuths(self) -> int:
        return int(self.codes.shape[1])

    @property
    def has_parallax(self) -> bool:
        return self.distance_codes is not None

    @cached_property
    def rho2_m2(self) -> float:
        return parallax.offset_variance_m2(self.dx_m, self.dy_m)

    @cached_property
    def ground_gradient2(self) -> np.ndarray:
        """|grad z|^2 of the ground at every node, float32 (0 where unknown)."""
        ge, gn = self.ground_gradient
        return (ge * ge + gn * gn).astype(np.float32)

    @cached_property
    def ground_gradient(self) -> tuple[np.ndarray, np.ndarray]:
        if self.ground_m is None:
            zero = np.zeros(self.codes.shape[0])
            return zero, zero
        return parallax.ground_gradient(self.ground_m, self.n_rows, self.n_cols, self.dx_m, self.dy_m)

    def ground_gradient_at(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`ground_gradient` where only ``nodes`` are filled (0 elsewhere), for the kernels that
        read those nodes alone: the same values without the gradient of the whole map."""
        if self.ground_m is None or "ground_gradient" in self.__dict__:
            return self.ground_gradient
        return parallax.ground_gradient_at(self.ground_m, self.n_rows, self.n_cols, self.dx_m, self.dy_m, nodes)

    def ground_gradient2_at(self, nodes: np.ndarray,
                            gradient: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """:attr:`ground_gradient2` where only ``nodes`` are filled (0 elsewhere); ``gradient`` is
        :meth:`ground_gradient_at` of the same nodes when already made (not made twice)."""
        if self.ground_m is None or "ground_gradient2" in self.__dict__:
            return self.ground_gradient2
        ge, gn = self.ground_gradient_at(nodes) if gradient is None else gradient
        idx = np.asarray(nodes, dtype=np.int64).ravel()
        g2 = np.zeros(ge.size, dtype=np.float32)
        g2[idx] = (ge[idx] * ge[idx] + gn[idx] * gn[idx]).astype(np.float32)
        return g2

    @cached_property
    def convergence_deg(self) -> np.ndarray:
        if self.terrain is None:
            return np.zeros(self.codes.shape[0])
        return np.asarray(self.terrain.convergence_deg, dtype=np.float64)

    @cached_property
    def inverse_range2(self) -> np.ndarray:
        return parallax.inverse_range2_table(self.distance_min_m, self.distance_log_step)

    @cached_property
    def _coarse_tau2_cache(self) -> dict[float, np.ndarray]:
        return {}

    def coarse_tau2(self, map_sigma_m: float = 0.0) -> np.ndarray:
        """The model's variance (parallax, the map's height error) over each first-pass run of
        azimuths (uint8 codes); made once per map error."""
        assert self.distance_codes is not None
        cache = self._coarse_tau2_cache
        if map_sigma_m == 0.0 and self.first_pass is not None:
            return self.first_pass[2]
        if map_sigma_m not in cache:
            cache[map_sigma_m] = parallax.coarse_tau2_codes(
                self.codes, self.distance_codes, self.offset_deg, self.step_deg, self.ground_gradient2, self.rho2_m2,
                self.inverse_range2, COARSE_STRIDE, map_sigma_m)
        return cache[map_sigma_m]

    @cached_property
    def coarse(self) -> tuple[np.ndarray, np.ndarray]:
        """Codes averaged over runs of COARSE_STRIDE azimuths, and the nodes lacking terrain
        somewhere: made once, at the database's build or on first use, for every estimate on this grid."""
        if self.first_pass is not None:
            return self.first_pass[0], self.first_pass[1]
        return decimated(self.codes, self.offset_deg, COARSE_STRIDE)

    @property
    def az_step_deg(self) -> float:
        return 360.0 / self.n_azimuths

    def skylines_deg(self, index: np.ndarray | int) -> np.ndarray:
        codes = np.asarray(self.codes[index])
        off = np.asarray(self.offset_deg[index], dtype=np.float64)
        st = np.asarray(self.step_deg[index], dtype=np.float64)
        el = off[..., None] + st[..., None] * codes
        return np.where(codes == 255, np.nan, el)


@dataclass(frozen=True)
class EstimateResult:
    """One position estimate.  Positions are fractional grid (row, col); the caller maps them to
    coordinates.  Posteriors are per node (best heading at each node)."""

    row: float
    col: float
    node: int
    heading_correction_deg: float
    lower: float
    upper: float
    log_lower: float
    region_nodes: np.ndarray
    region_area_m2: float
    log_lower_map: np.ndarray  # (n_nodes,) log lower posterior of each node's best heading
    log_upper_map: np.ndarray
    posterior_map: np.ndarray  # (n_nodes,) posterior at sigma's midpoint, marginal over heading
    rms_residual_deg: float
    n_valid: int
    sigma_deg: tuple[float, float]
    ambiguous: bool
    candidates: int
    elapsed_s: float
    notes: list[str] = field(default_factory=list)
    covariance_cells: np.ndarray | None = None  # (row, col) covariance of an exact fit (cells^2)
    #: The normalisers behind the maps above, in nats: log of the sum over every rescored candidate
    #: of its unnormalised lower and upper posterior (likelihood bound times prior), and of the
    #: midpoint posterior summed over heading.  The maps are normalised within this grid; searches
    #: over several grids (a tiled database) need these to normalise across them.
    log_evidence_lower: float = math.nan
    log_evidence_upper: float = math.nan
    log_evidence_mid: float = math.nan
    #: The best candidate's unnormalised log lower and upper posterior (nats), on the same scale.
    log_lower_unnormalised: float = math.nan
    log_upper_unnormalised: float = math.nan
    #: (n_nodes,) each node's unnormalised log upper posterior (its best heading), on the same scale;
    #: None when not made
    log_upper_unnormalised_map: np.ndarray | None = None
    #: how many nodes the first pass let through to be scored on every azimuth
    rescored: int = 0
    #: the answer's covariance (east, north; m^2) at sigma learned from the skyline; None without one
    covariance_m2: np.ndarray | None = None
    #: how many independent azimuths the skyline is worth (its residuals' autocorrelation)
    independent_azimuths: float = math.nan
    #: the credible region's nodes that belong to other modes than the answer's (rival places)
    rival_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: posterior share of the answer's mode and of the rival modes
    main_mass: float = math.nan
    rival_mass: float = 0.0
    #: the eye's height found by the exact fit above the map's surface under it (m), NaN without one
    eye_offset_m: float = math.nan
    #: whether sigma_deg was learned from the skyline (else it is the interval the search was given)
    sigma_learned: bool = False
    #: the share of the measured azimuths the best fit leaves to occluders (what the map lacks)
    occluded_share: float = 0.0
    #: whether the heading correction reached the compass's tolerance (then the answer is ambiguous)
    heading_at_limit: bool = False
    #: the sigma interval the search was made with (deg)
    sigma_deg_searched: tuple[float, float] = (math.nan, math.nan)


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
        threads (:func:`_start_looks`): what waits for them, (cost, node, start, heading) in the
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

        pending = _start_looks(look, starts)
        return lambda: [(cost, cand, start, phi) for (cand, start, _), (cost, phi) in zip(starts, pending())]

    def fit_looked(self, looks: list[_Look], beat: float = math.inf) -> list[Fit]:
        """Full fits of the best-looking REFINE_NODES nodes of ``looks`` (:meth:`looks`), of those
        only whose look comes within LOOK_MARGIN of ``beat`` (the look from a fit already made) when
        one is given."""
        fits: list[Fit] = []
        refined: list[int] = []
        for cost, cand, start, phi in sorted(looks, key=lambda v: v[0]):
            if not math.isfinite(cost) or len(refined) >= REFINE_NODES or cost > LOOK_MARGIN * beat:
                break
            if cand in refined:
                continue
            refined.append(cand)
            fit = self._fit(cand, start, phi)
            if fit is not None:
                fits.append(fit)
        return fits


#: One look of the refinement: its cost, the node, the start (fractional row, col) and the heading (deg).
_Look = tuple[float, int, tuple[float, float], float]
_look_pools: dict[int, ThreadPoolExecutor] = {}
_look_pool_lock = threading.Lock()


def _start_looks(look: Callable[[_T], tuple[float, float]],
                 items: list[_T]) -> Callable[[], list[tuple[float, float]]]:
    """``look`` of every item started on as many threads as the compiled kernels may use (numba's
    thread count; with one, as on a tiled search's own threads, made here in turn): what waits for
    them, in the items' order.  Each look is one render whose ray march releases the GIL, and the
    same on any thread: the same answers as one after the other."""
    threads = min(numba.get_num_threads(), len(items))
    if threads <= 1:
        made = [look(v) for v in items]
        return lambda: made
    with _look_pool_lock:
        pool = _look_pools.get(threads)
        if pool is None:
            pool = _look_pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="viper-look",
                                                             initializer=numba.set_num_threads, initargs=(1,))
    futures = [pool.submit(look, v) for v in items]
    return lambda: [f.result() for f in futures]


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
                            grid.az_step_deg**2, w[jj].astype(np.float64), float(min(cap, 1e30)),
                            map_sigma_m * map_sigma_m, out, pen, moves, occ)
    return out, pen, moves, occ


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


#: Nodes per call of the every-heading first pass (each call is one parallel region).
HEADING_BLOCK_NODES = 1 << 24


def _every_heading_first_pass(grid: SkylineGrid, m: np.ndarray, valid: np.ndarray, w_grid: np.ndarray,
                              n_eff: float, sig_ref: float, cap: float, map_sigma_m: float,
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """No compass: every node scored at every heading of the first pass (whole runs of
    COARSE_STRIDE azimuths), keeping its best; returns the first pass's (scores, occluded weights,
    log-normalisers), the band of fine shifts to rescore around each node's best heading, that
    heading (azimuth steps) and the count of azimuths."""
    n_nodes, n_az = grid.codes.shape
    m_dec = box_decimate(m, COARSE_STRIDE)
    w_dec = box_decimate(np.where(valid, w_grid, np.nan), COARSE_STRIDE)
    scale = n_az / max(float(np.nansum(w_dec)), 1e-9) * n_eff / max(n_az, 1)
    tau_c = (grid.coarse_tau2(map_sigma_m), *parallax.tau2_tables(sig_ref)) if grid.has_parallax else None
    codes_c, partial = grid.coarse
    best = np.empty(n_nodes, dtype=np.float32)
    best_occ = np.empty(n_nodes, dtype=np.float32)
    best_arg = np.empty(n_nodes, dtype=np.int64)
    pen = np.empty(n_nodes)
    w_dec0 = np.nan_to_num(w_dec)
    for lo in range(0, n_nodes, HEADING_BLOCK_NODES):
        hi = min(lo + HEADING_BLOCK_NODES, n_nodes)
        block_tau = None if tau_c is None else (tau_c[0][lo:hi], tau_c[1], tau_c[2])
        best[lo:hi], best_occ[lo:hi], best_arg[lo:hi], pen[lo:hi] = ssd_coarse_best(
            (codes_c[lo:hi], partial[lo:hi]), grid.offset_deg[lo:hi], grid.step_deg[lo:hi], m_dec, block_tau, w_dec0,
            cap)
    # the coarse heading is good to half a run: rescore a band of fine shifts around it
    half = COARSE_STRIDE // 2 + 1
    band = np.arange(-half, half + 1)
    best *= np.float32(scale)
    best_occ *= np.float32(scale)
    pen *= scale
    return best[:, None], best_occ[:, None], pen, band, best_arg * COARSE_STRIDE, n_az


def _capped(ssd: np.ndarray, occluded: np.ndarray, cap: float) -> np.ndarray:
    """Residual sums with each occluded measurement counting the cap: what ranks headings."""
    return ssd if not math.isfinite(cap) else ssd + occluded * cap


def _fit_bounds(fits: list[Fit], grid: SkylineGrid, log_prior: np.ndarray, meas: _Measurement,
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
        lp = np.array([log_prior[_nearest_node(grid, f.row, f.col)] for f in fits])
    return temper * lo + lp, temper * up + lp


def _best_fit(fits: list[Fit], grid: SkylineGrid, log_prior: np.ndarray, meas: _Measurement,
              position_prior: PositionPrior | None = None) -> Fit:
    """The fit of highest lower log-posterior (:func:`_fit_bounds`)."""
    lo, _ = _fit_bounds(fits, grid, log_prior, meas, position_prior)
    return fits[int(np.argmax(lo))]


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


def estimate(
    grid: SkylineGrid,
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    sigma_deg: tuple[float, float] = SIGMA_DEG,
    heading_tolerance_deg: float | None = HEADING_TOLERANCE_DEG,
    log_prior: np.ndarray | None = None,
    min_field_of_view_deg: float = MIN_FIELD_OF_VIEW_DEG,
    refine: bool = True,
    height_m: float | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    weights: np.ndarray | None = None,
    map_sigma_m: float = 0.0,
    position_prior: PositionPrior | None = None,
    rescore_floor: float | None = None,
    first: FirstPass | None = None,
    learn_noise: bool = True,
    sigma_floor_deg: float | None = None,
) -> EstimateResult:
    """Estimate the position from one skyline.

    ``heading_tolerance_deg`` = None means no compass: every heading is searched.  ``log_prior``
    is a per-node log prior (uniform in heading), e.g. from fusion; None is uniform.  ``height_m``
    is the camera's height above the map's surface for the exact refinement (default: the
    database's).  ``occlusion_weight`` is the prior share of azimuths hidden by something the map
    does not hold (trees, buildings): measurements above the prediction then cost at most
    :func:`occlusion_cap_deg2`.  ``weights`` (0..1 per input azimuth: the detector's confidence, a
    mask) weigh the measurements.  ``map_sigma_m`` is the map's vertical error (1 sigma, metres):
    it adds (sigma_v / d)^2 to each azimuth's variance.  ``position_prior`` is the same belief as
    ``log_prior`` held in continuous form (a Gaussian in grid cells, e.g. a traverse's transported
    estimate): the exact fit between nodes weighs it, where the per-node prior cannot reach.
    ``rescore_floor`` is a first-pass lower log-posterior (unnormalised, nats) already reached on
    another part of the same lattice (:attr:`FirstPass.best_lower` on another tile): the nodes here are
    rescored only if they come within reach of it too, as one search over both parts would do.
    ``first`` is this skyline's :func:`first_pass` on this grid, made earlier (ValueError if it was
    made for another skyline or other arguments); None makes it here.  ``learn_noise`` (with an exact
    fit) replaces ``sigma_deg`` by the interval the best fit's residuals give and tempers the
    likelihood by the skyline's share of independent azimuths (``confidence.py``); ``sigma_deg`` then
    only steers the search.  A search over several grids keeps one sigma for all (False).
    ``sigma_floor_deg`` is the least sigma learned (the calibrated sensor's; None: the database's
    quantisation, ``confidence.SIGMA_FLOOR_DEG``).

    When the best fit leaves far more of the skyline to occluders than ``occlusion_weight`` says (a
    forest's edge, buildings), the search is made once more with the share it found.  When the sigma
    learned lies far below the search's (a skyline far cleaner than the search assumed)
    but its best fit is not down to the floor (where nothing finer could be told apart), the search is
    made once more with the learned interval: a search that weighs every azimuth as loosely as the wide
    interval does can settle on a place that only the clean skyline tells apart.  The answer whose best
    fit leaves the smaller residual is kept.
    """
    t0 = time.perf_counter()
    search = _Search(heading_tolerance_deg=heading_tolerance_deg, log_prior=log_prior,
                     min_field_of_view_deg=min_field_of_view_deg, refine=refine, height_m=height_m,
                     occlusion_weight=occlusion_weight, weights=weights, map_sigma_m=map_sigma_m,
                     position_prior=position_prior, rescore_floor=rescore_floor, first=first,
                     learn_noise=learn_noise, sigma_floor_deg=sigma_floor_deg)
    again = learn_noise and first is None and rescore_floor is None
    res = _estimate_once(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    lo, hi = res.sigma_deg
    at_floor = res.rms_residual_deg <= CONVERGED_RMS * search.floor_deg
    if again and res.sigma_learned and not at_floor and hi < SEARCH_AGAIN_RATIO * float(sigma_deg[0]):
        second = _estimate_once(grid, azimuth_deg, elevation_deg, (lo, 2.0 * hi), search)
        if second.rms_residual_deg <= res.rms_residual_deg:
            res = second
    elif again and res.sigma_learned and res.occluded_share > OCCLUSION_AGAIN_RATIO * occlusion_weight:
        # the occluders' share learned from the best fit (one step of EM on the occlusion mixture)
        search = replace(search, occlusion_weight=min(res.occluded_share, MAX_OCCLUDED_SHARE))
        res = _estimate_once(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    if again and res.heading_at_limit and heading_tolerance_deg is not None:
        res = _widened(grid, azimuth_deg, elevation_deg, res, replace(search, heading_tolerance_deg=min(
            heading_tolerance_deg + HEADING_WIDEN_DEG, 180.0)))
    return replace(res, elapsed_s=time.perf_counter() - t0)


def _widened(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, res: EstimateResult,
             search: _Search) -> EstimateResult:
    """``res``, whose heading correction reached the compass's tolerance, searched again with the wider
    tolerance of ``search``: the same place (SAME_ANSWER_CELLS) with a heading inside the wider band is
    the answer; another place means the compass's tolerance decides where the skyline was seen, and the
    better fit of the two is given, ambiguous."""
    wide = _estimate_once(grid, azimuth_deg, elevation_deg, res.sigma_deg_searched, search)
    if math.hypot(wide.row - res.row, wide.col - res.col) <= SAME_ANSWER_CELLS:
        return wide
    best = wide if wide.rms_residual_deg < res.rms_residual_deg else res
    note = ("ambiguous: with a wider compass tolerance the best place moves "
            f"{math.hypot(wide.row - res.row, wide.col - res.col):.0f} cells; the compass decides where it is")
    return replace(best, ambiguous=True, notes=[*best.notes, note])


@dataclass(frozen=True)
class _Search:
    """:func:`estimate`'s arguments beyond the skyline and sigma, for each of its searches."""

    heading_tolerance_deg: float | None
    log_prior: np.ndarray | None
    min_field_of_view_deg: float
    refine: bool
    height_m: float | None
    occlusion_weight: float
    weights: np.ndarray | None
    map_sigma_m: float
    position_prior: PositionPrior | None
    rescore_floor: float | None
    first: FirstPass | None
    learn_noise: bool
    sigma_floor_deg: float | None

    @property
    def floor_deg(self) -> float:
        """The least sigma learned: the calibrated sensor's, at least the database's quantisation."""
        return max(self.sigma_floor_deg or 0.0, confidence.SIGMA_FLOOR_DEG)


def _estimate_once(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                   sigma_deg: tuple[float, float], search: _Search) -> EstimateResult:
    """One search and its confidence (:func:`estimate`'s arguments)."""
    heading_tolerance_deg, log_prior, height_m = search.heading_tolerance_deg, search.log_prior, search.height_m
    position_prior, first = search.position_prior, search.first
    t0 = time.perf_counter()
    meas = _measure(grid, azimuth_deg, elevation_deg, sigma_deg, search.weights, search.occlusion_weight,
                    search.map_sigma_m, search.min_field_of_view_deg)
    given = first is not None
    if first is None:
        first = _scored_first_pass(grid, meas, heading_tolerance_deg)
    elif not first.made_for(grid, meas, heading_tolerance_deg):
        raise ValueError("the first pass given was made for another grid, skyline or search")
    # a uniform prior is a read-only view of one zero, not an array of the grid's size
    lp = (np.broadcast_to(0.0, (grid.codes.shape[0],)) if log_prior is None
          else np.asarray(log_prior, dtype=np.float64))
    if given and log_prior is None:
        # a first pass made earlier (a tiled search's floor) holds these bounds already; the
        # posteriors are made from them in place
        lo, up, scored = first.uniform_bounds()
        bounds = (lo.copy(), up.copy(), scored)
    else:
        bounds = _first_pass_bounds(first.scores, meas, lp)
    plausible = _plausible_nodes(bounds, search.rescore_floor)
    rescored = _rescore(grid, meas, plausible.nodes, first.scores.shifts(plausible.nodes))
    post = _posteriors(meas, lp, plausible, rescored)
    answer = _grid_answer(grid, meas, rescored, post)
    fits: list[Fit] = []
    best_fit: Fit | None = None
    notes: list[str] = []
    if search.refine:
        answer, fits, best_fit, notes = _refined(grid, meas, lp, rescored, post, answer, heading_tolerance_deg,
                                                 height_m, position_prior)
    searched, temper, learned = meas, 1.0, False
    if search.learn_noise and best_fit is not None and best_fit.residual_deg is not None:
        floor = search.floor_deg
        meas, _ = _learned(meas, best_fit, floor)
        # the fits ranked again at the noise the skyline has: under the search's wide interval a
        # place that fits to the noise and one that fits ten times worse can look alike
        best_fit = _best_fit(fits, grid, lp, meas, position_prior)
        meas, _ = _learned(searched, best_fit, floor)
        polished = _polished(grid, meas, best_fit, heading_tolerance_deg, height_m, position_prior)
        if polished is not None:
            best_fit = polished
            answer = _Answer(polished.row, polished.col, polished.heading_deg, polished.rms_deg,
                             polished.covariance_cells)
        meas, temper = _learned(searched, best_fit, floor)
        learned = True
        lo, up, scored = _first_pass_bounds(first.scores, meas)
        plausible = _Plausible(plausible.nodes, lo * temper + lp, up * temper + lp, scored)
        post = _posteriors(meas, lp, plausible, rescored, temper)
    rivals = [] if best_fit is None else _rival_fits(fits, best_fit, grid, lp, meas, temper, position_prior)
    conf = confidence.modes(post.posterior_mid, grid.n_rows, grid.n_cols, answer.row, answer.col,
                            same_cells=SAME_ANSWER_CELLS)
    cov_cells = _answer_covariance(best_fit, meas, temper, conf)
    answer_node = _nearest_node(grid, answer.row, answer.col)
    cov_m2 = confidence.grid_to_east_north(cov_cells, grid.dx_m, grid.dy_m,
                                           float(grid.convergence_deg[answer_node]))
    fit_cells = [_nearest_node(grid, f.row, f.col) for f in rivals]
    pinned = False
    cell_area = grid.dx_m * grid.dy_m
    hidden = 0.0 if best_fit is None else best_fit.occluded / max(best_fit.n, 1)
    poor = answer.rms_deg > searched.sigma_hi_deg or hidden > MAX_OCCLUDED_SHARE
    if learned:
        # the 95 % region: the answer's ellipse and the cells of the rival places
        rival_cells = np.union1d(conf.rivals, fit_cells).astype(np.int64)
        region = np.union1d(np.union1d(conf.region, rival_cells), [answer_node]).astype(np.int64)
        area = confidence.ellipse_area_m2(cov_m2) + rival_cells.size * cell_area
        # a heading correction at the compass's limit: the best place may lie with a heading beyond it
        pinned = (heading_tolerance_deg is not None
                  and abs(answer.heading_deg) > heading_tolerance_deg - HEADING_LIMIT_MARGIN_DEG)
        ambiguous = bool(rival_cells.size) or poor or pinned
        notes += _quality_notes(conf, rival_cells.size * cell_area, bool(rivals), answer.rms_deg, searched.sigma_hi_deg)
        if hidden > MAX_OCCLUDED_SHARE:
            notes.append(f"ambiguous: poor match: {hidden:.0%} of the skyline stands above the map's terrain at the "
                         "best place; the skyline may not come from this map")
        if pinned:
            notes.append(f"ambiguous: the heading correction {answer.heading_deg:+.1f} deg reaches the compass's "
                         f"tolerance of {heading_tolerance_deg:g} deg; the best place may need a larger one")
        if not np.all(np.isfinite(cov_m2)):
            ambiguous = True
            notes.append("ambiguous: the answer's covariance cannot be formed (the fit's curvature is singular)")
    else:
        # sigma as given: the nodes whose upper posterior reaches the best's lower one
        rival_cells = np.zeros(0, dtype=np.int64)
        region = np.union1d(post.region, [answer_node] + fit_cells).astype(np.int64)
        area = region.size * cell_area
        ambiguous = region.size > AMBIGUOUS_CELLS or bool(rivals) or poor
        notes += _region_notes(region.size, area)
        notes += _quality_notes(None, 0.0, bool(rivals), answer.rms_deg, searched.sigma_hi_deg)
    return EstimateResult(
        row=answer.row, col=answer.col, node=post.best_node, heading_correction_deg=answer.heading_deg,
        lower=float(np.exp(post.best_log_lower)), upper=float(np.exp(post.best_log_upper)),
        log_lower=post.best_log_lower,
        region_nodes=region, region_area_m2=area, log_lower_map=post.node_lower, log_upper_map=post.node_upper,
        posterior_map=post.posterior_mid, rms_residual_deg=answer.rms_deg, n_valid=meas.n_valid,
        sigma_deg=(meas.sigma_lo_deg, meas.sigma_hi_deg), ambiguous=ambiguous,
        candidates=plausible.scored_nodes * first.scores.band.size,
        elapsed_s=time.perf_counter() - t0, notes=notes, covariance_cells=cov_cells,
        log_evidence_lower=post.log_sum_lo, log_evidence_upper=post.log_sum_up, log_evidence_mid=post.log_sum_mid,
        log_lower_unnormalised=post.best_lo_unnormalised, log_upper_unnormalised=post.best_up_unnormalised,
        log_upper_unnormalised_map=post.node_upper_unnormalised, rescored=int(plausible.nodes.size),
        covariance_m2=cov_m2, independent_azimuths=meas.n_eff * temper, rival_nodes=rival_cells,
        main_mass=conf.main_mass, rival_mass=conf.rival_mass,
        eye_offset_m=math.nan if best_fit is None else best_fit.eye_offset_m, sigma_learned=learned,
        occluded_share=hidden, heading_at_limit=pinned,
        sigma_deg_searched=(searched.sigma_lo_deg, searched.sigma_hi_deg),
    )


def _learned(meas: _Measurement, fit: Fit, floor_deg: float) -> tuple[_Measurement, float]:
    """The measurement with sigma's interval learned from ``fit``'s residuals (each end at least
    ``floor_deg``), and the tempering of its likelihood: independent azimuths over measured ones
    (``confidence.py``)."""
    r = fit.residual_deg
    assert r is not None
    rms = math.sqrt(float(np.nanmean(r * r))) if np.isfinite(r).any() else meas.sigma_ref_deg
    independent = confidence.independent_azimuths(r)
    lo, hi = confidence.sigma_interval(rms, independent, floor_deg)
    temper = min(1.0, independent / max(float(np.isfinite(r).sum()), 1.0))
    learned = _Measurement(meas.elevation_deg, meas.weight, meas.valid, meas.n_valid, meas.n_eff, lo, hi,
                           0.5 * (lo + hi), meas.cap_deg2, meas.occlusion_weight, meas.map_sigma_m)
    return learned, temper


def _polished(grid: SkylineGrid, meas: _Measurement, fit: Fit, heading_tolerance_deg: float | None,
              height_m: float | None, position_prior: PositionPrior | None) -> Fit | None:
    """``fit`` fitted again from where it stands at the measurement's (learned) sigma: the weights,
    the occlusion cap and the point where the fit is at the noise follow the noise the skyline has,
    not the search's.  None when the new fit fails."""
    assert grid.terrain is not None
    sigma, step = meas.sigma_ref_deg, grid.az_step_deg
    tol = heading_tolerance_deg
    bounds = (-180.0, 180.0) if tol is None else (-tol - step, tol + step)
    node = _nearest_node(grid, fit.row, fit.col)
    n_row, n_col = divmod(node, grid.n_cols)
    model = Model(meas.weight, occlusion_cap_deg2(meas.occlusion_weight, sigma), meas.map_sigma_m)
    return refine_exact(grid.terrain, grid.dx_m, grid.dy_m, meas.elevation_deg, n_row, n_col, grid.n_cols,
                        fit.heading_deg, height_m, (fit.row, fit.col), sigma, bounds, model, position_prior,
                        start_spread_cells=POLISH_SPREAD_CELLS, tilt_sigma_deg=TILT_SIGMA_DEG)


def _rival_fits(fits: list[Fit], best: Fit, grid: SkylineGrid, lp: np.ndarray, meas: _Measurement, temper: float,
                position_prior: PositionPrior | None) -> list[Fit]:
    """The exact fits at other places (more than SAME_ANSWER_CELLS from ``best``) whose upper
    log-posterior, at the measurement's sigma interval and tempering, reaches ``best``'s lower one."""
    others = [f for f in fits if math.hypot(f.row - best.row, f.col - best.col) > SAME_ANSWER_CELLS]
    if not others:
        return []
    lo, up = _fit_bounds([best] + others, grid, lp, meas, position_prior, temper)
    return [f for i, f in enumerate(others, start=1) if up[i] >= lo[0]]


def _answer_covariance(fit: Fit | None, meas: _Measurement, temper: float,
                       conf: confidence.Modes) -> np.ndarray:
    """The answer's (row, col) covariance (cells^2): the exact fit's curvature at the learned sigma,
    tempered, with its priors; without one, the spread of the answer's mode over its nodes."""
    if fit is not None and fit.curvature is not None and fit.prior_information is not None:
        sig2 = meas.sigma_ref_deg**2 * confidence.COVARIANCE_SCALE
        cov = marginal_position_covariance(temper * fit.curvature / sig2 + fit.prior_information)
        if cov is not None:
            return cov
    return conf.main_covariance_cells


@dataclass(frozen=True)
class _Measurement:
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


def _measure(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, sigma_deg: tuple[float, float],
             weights: np.ndarray | None, occlusion_weight: float, map_sigma_m: float,
             min_field_of_view_deg: float) -> _Measurement:
    """Step 1: the measured skyline (deg) and its weights (0..1) resampled onto the grid's azimuths,
    the arguments checked (InputError), and sigma's midpoint (deg) and the occlusion cap (deg^2)."""
    sig_lo, sig_hi = float(sigma_deg[0]), float(sigma_deg[1])
    if not 0 < sig_lo <= sig_hi:
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
    sig_ref = 0.5 * (sig_lo + sig_hi)
    return _Measurement(m, w_grid, valid, n, float(w_grid.sum()), sig_lo, sig_hi, sig_ref,
                        occlusion_cap_deg2(occlusion_weight, sig_ref), occlusion_weight, map_sigma_m)


@dataclass(frozen=True)
class _FirstPass:
    """Every node scored on the first pass, and the fine shifts each node is rescored at."""

    ssd: np.ndarray  # (n_nodes, n_coarse_shifts) float32 weighted residual sums, deg^2
    occluded: np.ndarray  # (n_nodes, n_coarse_shifts) float32 weight of the occluded measurements
    penalty: np.ndarray  # (n_nodes,) float64 log-normalisers
    band: np.ndarray  # (n_fine_shifts,) azimuth steps around each node's centre
    centre: np.ndarray | None  # (n_nodes,) azimuth steps each node's band is centred on; None = 0 for all
    n_azimuths: int

    def shifts(self, rows: np.ndarray) -> np.ndarray:
        """The fine shifts (azimuth steps) nodes ``rows`` are rescored at, (len(rows), n_fine_shifts);
        made for those rows only."""
        if self.centre is None:
            return np.repeat(self.band[None, :], len(rows), axis=0)
        return (self.centre[rows, None] + self.band[None, :]) % self.n_azimuths


@dataclass(frozen=True)
class FirstPass:
    """One skyline's first pass over every node of a grid: where :func:`estimate` starts.  Made
    once, it serves the rounds of a tiled search that all start there (the pruning floor over
    every tile, each tile's grid search, its refinement)."""

    grid_id: int  # id() of the grid's codes it was made on
    meas: _Measurement
    heading_tolerance_deg: float | None
    scores: _FirstPass
    #: the bounds under a uniform prior once made (:meth:`uniform_bounds`).  Memoised by hand:
    #: functools.cached_property holds one lock across every instance (Python < 3.12), which would
    #: make the tiles searched on several threads wait for each other's bounds.
    _memo: dict[str, tuple[np.ndarray, np.ndarray, int]] = field(default_factory=dict, compare=False, repr=False)

    def uniform_bounds(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Every node's first-pass lower and upper log-likelihood (nats, read-only) and the count of
        nodes scored: made once, for the pruning floor (:attr:`best_lower`) and for :func:`estimate`
        under a uniform prior, which starts from the same numbers."""
        made = self._memo.get("uniform")
        if made is None:
            lo, up, scored = _first_pass_bounds(self.scores, self.meas)
            lo.flags.writeable = False
            up.flags.writeable = False
            made = self._memo["uniform"] = (lo, up, scored)
        return made

    @property
    def best_lower(self) -> float:
        """The best lower log-posterior (unnormalised, nats, uniform prior) of any node: what
        :func:`estimate` prunes its rescoring against.  Over the tiles of one lattice the largest of
        these is the ``rescore_floor`` that makes each tile's search rescore the nodes a search of
        the whole lattice would."""
        return float(np.max(self.uniform_bounds()[0]))

    @cached_property
    def nbytes(self) -> int:
        """The scores' bytes and those of the uniform prior's bounds (two float64 per node)."""
        s = self.scores
        return int(s.ssd.nbytes + s.occluded.nbytes + s.penalty.nbytes + (0 if s.centre is None else s.centre.nbytes)
                   + 16 * s.ssd.shape[0])

    def made_for(self, grid: SkylineGrid, meas: _Measurement, heading_tolerance_deg: float | None) -> bool:
        a, b = self.meas, meas
        return (self.grid_id == id(grid.codes) and self.scores.ssd.shape[0] == grid.codes.shape[0]
                and self.heading_tolerance_deg == heading_tolerance_deg
                and np.array_equal(a.elevation_deg, b.elevation_deg, equal_nan=True)
                and np.array_equal(a.weight, b.weight)
                and (a.sigma_lo_deg, a.sigma_hi_deg, a.occlusion_weight, a.map_sigma_m)
                == (b.sigma_lo_deg, b.sigma_hi_deg, b.occlusion_weight, b.map_sigma_m))


def first_pass(
    grid: SkylineGrid,
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    sigma_deg: tuple[float, float] = SIGMA_DEG,
    heading_tolerance_deg: float | None = HEADING_TOLERANCE_DEG,
    weights: np.ndarray | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    map_sigma_m: float = 0.0,
    min_field_of_view_deg: float = MIN_FIELD_OF_VIEW_DEG,
) -> FirstPass:
    """The skyline's first pass over every node of ``grid`` (arguments as :func:`estimate`'s), to
    give :func:`estimate` later or to read its :attr:`FirstPass.best_lower`."""
    meas = _measure(grid, azimuth_deg, elevation_deg, sigma_deg, weights, occlusion_weight, map_sigma_m,
                    min_field_of_view_deg)
    return _scored_first_pass(grid, meas, heading_tolerance_deg)


def _scored_first_pass(grid: SkylineGrid, meas: _Measurement, heading_tolerance_deg: float | None) -> FirstPass:
    return FirstPass(id(grid.codes), meas, heading_tolerance_deg, _first_pass(grid, meas, heading_tolerance_deg))


def _first_pass(grid: SkylineGrid, meas: _Measurement, heading_tolerance_deg: float | None) -> _FirstPass:
    """Step 2: every node scored cheaply, with a compass or over every heading (None)."""
    if heading_tolerance_deg is not None:
        return _compass_first_pass(grid, meas, heading_tolerance_deg)
    return _FirstPass(*_every_heading_first_pass(grid, meas.elevation_deg, meas.valid, meas.weight, meas.n_eff,
                                                 meas.sigma_ref_deg, meas.cap_deg2, meas.map_sigma_m))


def _compass_first_pass(grid: SkylineGrid, meas: _Measurement, heading_tolerance_deg: float) -> _FirstPass:
    """Step 2, with a compass: every node scored on skylines averaged over runs of COARSE_STRIDE
    azimuths, turned in whole runs across +-``heading_tolerance_deg``; every node is then rescored
    at every azimuth step of the band."""
    if heading_tolerance_deg < 0:
        raise InputError(f"heading tolerance {heading_tolerance_deg} must be >= 0")
    n_nodes = grid.codes.shape[0]
    n, n_eff = meas.n_valid, meas.n_eff
    k = int(math.ceil(heading_tolerance_deg / grid.az_step_deg - 1e-9))
    base_shifts = np.arange(-k, k + 1)
    # every heading of the band lies within half a run of one of the first pass's
    k_dec = int(math.ceil(k / COARSE_STRIDE))
    m_dec = box_decimate(meas.elevation_deg, COARSE_STRIDE)
    w_dec = box_decimate(np.where(meas.valid, meas.weight, np.nan), COARSE_STRIDE)
    scale = n / max(float(np.nansum(w_dec)), 1e-9) * n_eff / max(n, 1)
    tau_c = ((grid.coarse_tau2(meas.map_sigma_m), *parallax.tau2_tables(meas.sigma_ref_deg)) if grid.has_parallax
             else None)
    coarse_occ = np.empty((n_nodes, 2 * k_dec + 1), dtype=np.float32)
    coarse, coarse_pen = ssd_coarse(grid.coarse, grid.offset_deg, grid.step_deg, m_dec,
                                    np.arange(-k_dec, k_dec + 1), tau_c, np.nan_to_num(w_dec), meas.cap_deg2,
                                    coarse_occ)
    coarse *= np.float32(scale)
    coarse_occ *= np.float32(scale)
    coarse_pen = coarse_pen.astype(np.float64)
    coarse_pen *= scale
    return _FirstPass(coarse, coarse_occ, coarse_pen, base_shifts, None, grid.n_azimuths)


@dataclass(frozen=True)
class _Plausible:
    """The nodes worth rescoring, and every node's first-pass bounds (nats)."""

    nodes: np.ndarray  # sorted node indices
    log_lower: np.ndarray  # (n_nodes,) lower log-likelihood plus log prior
    log_upper: np.ndarray  # (n_nodes,) upper log-likelihood plus log prior
    scored_nodes: int  # nodes with a finite first-pass score


def _first_pass_bounds(first: _FirstPass, meas: _Measurement,
                       lp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Each node's first-pass lower and upper log-likelihood (nats, normaliser included; plus the
    log prior ``lp`` when given) and the count of nodes scored.  Both likelihood bounds fall as the
    residual grows, so each node's best first-pass shift decides for the node (an occluded
    measurement counting the cap there)."""
    n_nodes = first.ssd.shape[0]
    prior = np.zeros(1) if lp is None else lp
    if lp is None:
        prior = np.broadcast_to(prior, (n_nodes,))
    return best_column_bounds(first.ssd, first.occluded, first.penalty, prior, meas.cap_deg2, meas.n_eff,
                              meas.sigma_lo_deg, meas.sigma_hi_deg, meas.occlusion_weight)


def _plausible_nodes(bounds: tuple[np.ndarray, np.ndarray, int], floor: float | None) -> _Plausible:
    """Step 2, the nodes worth every azimuth: those whose first-pass upper log-posterior (nats,
    ``bounds``: :func:`_first_pass_bounds`, which the result takes over) comes within
    RESCORE_MARGIN_NATS of the best lower one (or of ``floor``, when higher: a lower bound reached
    elsewhere on the lattice), at least MIN_RESCORE of them."""
    node_lo, node_up, scored = bounds
    n_nodes = node_lo.size
    best_lo = float(np.max(node_lo)) if floor is None else max(float(np.max(node_lo)), floor)
    rescore = np.nonzero(node_up >= best_lo - RESCORE_MARGIN_NATS)[0]
    if rescore.size < MIN_RESCORE:
        rescore = np.sort(np.argpartition(-node_up, min(MIN_RESCORE, n_nodes) - 1)[:MIN_RESCORE])
    return _Plausible(rescore, node_lo, node_up, scored)


@dataclass(frozen=True)
class _Rescored:
    """The plausible nodes scored on every azimuth (float64)."""

    nodes: np.ndarray  # (n_r,) sorted node indices
    shifts: np.ndarray  # (n_r, n_k) azimuth steps
    ssd: np.ndarray  # (n_r, n_k) weighted residual sums, deg^2
    occluded: np.ndarray  # (n_r, n_k) weight of the occluded measurements
    half_penalty: np.ndarray  # (n_r, 1) half the log-normaliser, nats
    moves: np.ndarray  # (n_r, 4) linearised moves: east m, north m, heading deg, eye m (0 with no parallax)


def _rescore(grid: SkylineGrid, meas: _Measurement, rescore: np.ndarray, shifts: np.ndarray) -> _Rescored:
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
        k_best = np.argmin(_capped(ssd_r, occ_r, cap), axis=1)
        shifts_r = shifts_r[np.arange(rescore.size), k_best][:, None]
        ssd_lin, pen_lin, moves_r, occ_lin = _linearised(grid, m, w_grid, rescore, shifts_r[:, 0],
                                                         meas.sigma_ref_deg, cap, meas.map_sigma_m, gradient)
        ssd_r, occ_r = ssd_lin[:, None], occ_lin[:, None]
        pen_r = 0.5 * pen_lin[:, None]
    return _Rescored(rescore, shifts_r, ssd_r, occ_r, pen_r, moves_r)


@dataclass(frozen=True)
class _Posteriors:
    """The best candidate, every node's posterior bounds and the region (log posteriors in nats)."""

    best_r: int  # the best candidate's row in :class:`_Rescored`
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


def _posteriors(meas: _Measurement, lp: np.ndarray, plausible: _Plausible, rescored: _Rescored,
                temper: float = 1.0) -> _Posteriors:
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
    mid = 0.5 * (sig_lo + sig_hi)
    ll_mid = temper * mixture_log_likelihood(ssd_r, n_eff, occ_r, mid, occlusion_weight) + lp_r
    node_mid_r = np.logaddexp.reduce(np.where(np.isfinite(ll_mid), ll_mid, -np.inf), axis=1)
    log_sum_mid = float(np.logaddexp.reduce(node_mid_r))
    posterior_mid = np.zeros(node_lower.size)
    posterior_mid[rescore] = np.exp(node_mid_r - log_sum_mid)
    return _Posteriors(best_r, best_k, int(rescore[best_r]), best_lower_log,
                       float(post.log_upper.ravel()[best_flat]), node_lower, node_upper, region, posterior_mid,
                       log_sum_lo, log_sum_up, log_sum_mid, float((lo_r + lp_r)[best_r, best_k]),
                       float((up_r + lp_r)[best_r, best_k]), node_up_unnormalised)


@dataclass(frozen=True)
class _Answer:
    """A position in fractional grid (row, col), the heading correction (deg), the RMS residual (deg)
    and, for an exact fit, the covariance of (row, col) (cells^2)."""

    row: float
    col: float
    heading_deg: float
    rms_deg: float
    covariance_cells: np.ndarray | None = None


def _grid_answer(grid: SkylineGrid, meas: _Measurement, rescored: _Rescored, post: _Posteriors) -> _Answer:
    """Step 4's answer: the best candidate's node, its heading correction in (-180, 180] deg and its
    RMS residual (deg)."""
    n_az = grid.n_azimuths
    shift_steps = float(rescored.shifts[post.best_r, post.best_k])
    if shift_steps > n_az / 2:
        shift_steps -= n_az
    row, col = divmod(post.best_node, grid.n_cols)
    rms = math.sqrt(float(rescored.ssd[post.best_r, post.best_k]) / meas.n_valid)
    return _Answer(float(row), float(col), shift_steps * grid.az_step_deg, rms)


def _nearest_node(grid: SkylineGrid, row: float, col: float) -> int:
    """The node nearest fractional grid (row, col), clamped to the grid."""
    return (min(max(int(round(row)), 0), grid.n_rows - 1) * grid.n_cols
            + min(max(int(round(col)), 0), grid.n_cols - 1))


def _refined(grid: SkylineGrid, meas: _Measurement, lp: np.ndarray, rescored: _Rescored, post: _Posteriors,
             answer: _Answer, heading_tolerance_deg: float | None, height_m: float | None,
             position_prior: PositionPrior | None) -> tuple[_Answer, list[Fit], Fit | None, list[str]]:
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
    best_fit = _best_fit(fits, grid, lp, meas, position_prior)
    notes: list[str] = []
    if best_fit.occluded > 0.05 * best_fit.n:
        notes.append(f"occluded: {best_fit.occluded:.0f} of {best_fit.n} azimuths stand above the map's "
                     "terrain (trees, buildings, masts?) and were left out")
    rms = math.sqrt(best_fit.ssd / max(best_fit.n - best_fit.occluded, 1.0))
    return (_Answer(best_fit.row, best_fit.col, best_fit.heading_deg, rms, best_fit.covariance_cells),
            fits, best_fit, notes)


def _exact_fits(grid: SkylineGrid, meas: _Measurement, rescored: _Rescored, post: _Posteriors, scored: np.ndarray,
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


def _subcell_answer(grid: SkylineGrid, meas: _Measurement, lp: np.ndarray, rescored: _Rescored, post: _Posteriors,
                    scored: np.ndarray, answer: _Answer) -> _Answer:
    """Step 5 with no terrain: the most likely nodes of the region (the best first) refined between
    the database's skylines (``refine.py``); the fit of the best likelihood at sigma's midpoint plus
    the prior of its nearest node is kept, else the grid's ``answer``."""
    from appliance.estimator.refine import refine_subcell

    n_az, step, n, rescore = grid.n_azimuths, grid.az_step_deg, meas.n_valid, rescored.nodes
    mid = 0.5 * (meas.sigma_lo_deg + meas.sigma_hi_deg)
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
    return _Answer(frow, fcol, heading, rms)


def _quality_notes(conf: confidence.Modes | None, rival_area_m2: float, rival_fit: bool, rms_deg: float,
                   sigma_hi_deg: float) -> list[str]:
    """Notes on an answer the skyline does not single out (rival places of ``conf``, the modes of a
    learned posterior; rival fits) or fits poorly."""
    notes: list[str] = []
    if conf is not None and conf.rivals.size:
        notes.append(
            f"ambiguous: {conf.rival_mass:.0%} of the posterior lies at other places "
            f"({conf.rivals.size} cells, {rival_area_m2 / 1e6:.2f} km^2) inside the {confidence.LEVEL:.0%} region; "
            "the skyline does not single out one position"
        )
    if rival_fit:
        notes.append(
            f"ambiguous: exact renders at another place, more than {SAME_ANSWER_CELLS:.0f} cells away, "
            "fit as well as the best"
        )
    if rms_deg > sigma_hi_deg:
        notes.append(
            f"ambiguous: poor match: residual {rms_deg:.2f} deg RMS, more than the {sigma_hi_deg:.2f} deg the "
            "search allows; the skyline may not come from this map"
        )
    return notes


def _region_notes(region_cells: int, area_m2: float) -> list[str]:
    """The note on a region (sigma as given) too wide to single out one position."""
    if region_cells <= AMBIGUOUS_CELLS:
        return []
    return [f"ambiguous: {region_cells} cells ({area_m2 / 1e6:.2f} km^2) are as likely as the best; "
            "the skyline does not single out one position"]
