"""Step 2's first pass: every node scored cheaply, on skylines averaged over runs of azimuths.

Every node is scored on skylines averaged over runs of COARSE_STRIDE azimuths (the compiled
kernels of ``coarse_kernels.py``): with a compass, at the runs' headings across the compass's
tolerance; with none, at every heading, keeping each node's best.  Each node's first-pass score bounds its likelihood
(:func:`first_pass_bounds`); the plausible nodes are then rescored on every azimuth
(``rescore.py``), and the nodes left here keep their first-pass bounds in the posterior's sums.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from appliance.errors import InputError
from appliance.estimator import parallax
from appliance.estimator.coarse_kernels import box_decimate, ssd_coarse, ssd_coarse_best
from appliance.estimator.likelihood import best_column_bounds
from appliance.estimator.measurement import Measurement
from appliance.estimator.skyline_grid import COARSE_STRIDE, SkylineGrid


@dataclass(frozen=True)
class CoarseScores:
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
    """One skyline's first pass over every node of a grid: where :func:`appliance.estimator.estimate` starts.  Made
    once, it serves the rounds of a tiled search that all start there (the pruning floor over
    every tile, each tile's grid search, its refinement)."""

    grid_id: int  # id() of the grid's codes it was made on
    meas: Measurement
    heading_tolerance_deg: float | None
    scores: CoarseScores
    #: the bounds under a uniform prior once made (:meth:`uniform_bounds`).  Memoised by hand:
    #: functools.cached_property holds one lock across every instance (Python < 3.12), which would
    #: make the tiles searched on several threads wait for each other's bounds.
    _memo: dict[str, tuple[np.ndarray, np.ndarray, int]] = field(default_factory=dict, compare=False, repr=False)

    def uniform_bounds(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Every node's first-pass lower and upper log-likelihood (nats, read-only) and the count of
        nodes scored: made once, for the pruning floor (:attr:`best_lower`) and for :func:`appliance.estimator.estimate`
        under a uniform prior, which starts from the same numbers."""
        made = self._memo.get("uniform")
        if made is None:
            lo, up, scored = first_pass_bounds(self.scores, self.meas)
            lo.flags.writeable = False
            up.flags.writeable = False
            made = self._memo["uniform"] = (lo, up, scored)
        return made

    @property
    def best_lower(self) -> float:
        """The best lower log-posterior (unnormalised, nats, uniform prior) of any node: what
        :func:`appliance.estimator.estimate` prunes its rescoring against.  Over the tiles of one lattice the largest of
        these is the ``rescore_floor`` that makes each tile's search rescore the nodes a search of
        the whole lattice would."""
        return float(np.max(self.uniform_bounds()[0]))

    @cached_property
    def nbytes(self) -> int:
        """The scores' bytes and those of the uniform prior's bounds (two float64 per node)."""
        s = self.scores
        return int(s.ssd.nbytes + s.occluded.nbytes + s.penalty.nbytes + (0 if s.centre is None else s.centre.nbytes)
                   + 16 * s.ssd.shape[0])

    def made_for(self, grid: SkylineGrid, meas: Measurement, heading_tolerance_deg: float | None) -> bool:
        a, b = self.meas, meas
        return (self.grid_id == id(grid.codes) and self.scores.ssd.shape[0] == grid.codes.shape[0]
                and self.heading_tolerance_deg == heading_tolerance_deg
                and np.array_equal(a.elevation_deg, b.elevation_deg, equal_nan=True)
                and np.array_equal(a.weight, b.weight)
                and (a.sigma_lo_deg, a.sigma_hi_deg, a.occlusion_weight, a.map_sigma_m)
                == (b.sigma_lo_deg, b.sigma_hi_deg, b.occlusion_weight, b.map_sigma_m))


def scored_first_pass(grid: SkylineGrid, meas: Measurement, heading_tolerance_deg: float | None) -> FirstPass:
    """The first pass of measurement ``meas`` over every node of ``grid``."""
    return FirstPass(id(grid.codes), meas, heading_tolerance_deg, _coarse_scores(grid, meas, heading_tolerance_deg))


def _coarse_scores(grid: SkylineGrid, meas: Measurement, heading_tolerance_deg: float | None) -> CoarseScores:
    """Step 2: every node scored cheaply, with a compass or over every heading (None)."""
    if heading_tolerance_deg is not None:
        return _compass_first_pass(grid, meas, heading_tolerance_deg)
    return CoarseScores(*_every_heading_first_pass(grid, meas.elevation_deg, meas.valid, meas.weight, meas.n_eff,
                                                 meas.sigma_ref_deg, meas.cap_deg2, meas.map_sigma_m))


def _compass_first_pass(grid: SkylineGrid, meas: Measurement, heading_tolerance_deg: float) -> CoarseScores:
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
    return CoarseScores(coarse, coarse_occ, coarse_pen, base_shifts, None, grid.n_azimuths)



def first_pass_bounds(first: CoarseScores, meas: Measurement, lp: np.ndarray | None = None,
                      serial: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """Each node's first-pass lower and upper log-likelihood (nats, normaliser included; plus the
    log prior ``lp`` when given) and the count of nodes scored.  Both likelihood bounds fall as the
    residual grows, so each node's best first-pass shift decides for the node (an occluded
    measurement counting the cap there).  ``serial``: on the caller's thread alone (the same numbers)."""
    n_nodes = first.ssd.shape[0]
    prior = np.zeros(1) if lp is None else lp
    if lp is None:
        prior = np.broadcast_to(prior, (n_nodes,))
    return best_column_bounds(first.ssd, first.occluded, first.penalty, prior, meas.cap_deg2, meas.n_eff,
                              meas.sigma_lo_deg, meas.sigma_hi_deg, meas.occlusion_weight, serial)



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
