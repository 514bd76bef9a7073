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
import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from appliance.errors import EstimationError, InputError
from appliance.estimator.likelihood import log_likelihood_bounds, posterior_bounds
from appliance.estimator.search import box_decimate, decimated, ssd_all_shifts, ssd_coarse, ssd_for_shifts

COARSE_STRIDE = 4
#: Nodes whose first-pass upper log-likelihood lies within this many nats of the best first-pass
#: lower log-likelihood are rescored on every azimuth.
RESCORE_MARGIN_NATS = 200.0
MIN_RESCORE = 64
#: A region wider than this many map cells is reported as ambiguous.
AMBIGUOUS_CELLS = 25
#: How many of the region's most likely nodes the sub-cell refinement examines.
REFINE_NODES = 3


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

    @property
    def n_azimuths(self) -> int:
        return int(self.codes.shape[1])

    @cached_property
    def coarse(self) -> tuple[np.ndarray, np.ndarray]:
        """Codes averaged over runs of COARSE_STRIDE azimuths, and the nodes lacking terrain
        somewhere: made once, on first use, for every estimate on this grid."""
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
    sigma_deg: tuple[float, float] = (0.2, 0.4),
    heading_tolerance_deg: float | None = 4.0,
    log_prior: np.ndarray | None = None,
    min_valid_fraction: float = 0.2,
    refine: bool = True,
) -> EstimateResult:
    """Estimate the position from one skyline.

    ``heading_tolerance_deg`` = None means no compass: every heading is searched.  ``log_prior``
    is a per-node log prior (uniform in heading), e.g. from fusion; None is uniform.
    """
    t0 = time.perf_counter()
    sig_lo, sig_hi = float(sigma_deg[0]), float(sigma_deg[1])
    if not 0 < sig_lo <= sig_hi:
        raise InputError(f"sigma interval [{sig_lo}, {sig_hi}] must satisfy 0 < lo <= hi")
    n_az = grid.n_azimuths
    m = resample_to_grid(azimuth_deg, elevation_deg, n_az)
    valid = np.isfinite(m)
    n = int(valid.sum())
    if n < min_valid_fraction * n_az:
        raise InputError(
            f"skyline has {n} valid azimuths of {n_az} ({100.0 * n / n_az:.0f}%), "
            f"fewer than the {100 * min_valid_fraction:.0f}% needed"
        )
    step = grid.az_step_deg
    n_nodes = grid.codes.shape[0]
    notes: list[str] = []

    if heading_tolerance_deg is not None:
        if heading_tolerance_deg < 0:
            raise InputError(f"heading tolerance {heading_tolerance_deg} must be >= 0")
        k = int(math.ceil(heading_tolerance_deg / step - 1e-9))
        base_shifts = np.arange(-k, k + 1)
        # first pass on skylines averaged over runs of COARSE_STRIDE azimuths, turned in whole runs:
        # every heading of the band lies within half a run of one of them
        k_dec = int(math.ceil(k / COARSE_STRIDE))
        m_dec = box_decimate(m, COARSE_STRIDE)
        scale = n / max(int(np.isfinite(m_dec).sum()), 1)
        coarse = ssd_coarse(grid.coarse, grid.offset_deg, grid.step_deg, m_dec, np.arange(-k_dec, k_dec + 1))
        coarse *= np.float32(scale)
        node_shifts = np.broadcast_to(base_shifts, (n_nodes, base_shifts.size))
    else:
        coarse_best = np.full(n_nodes, np.inf, dtype=np.float64)
        coarse_arg = np.zeros(n_nodes, dtype=np.int64)
        scale = n / max(int(np.isfinite(box_decimate(m, COARSE_STRIDE)).sum()), 1)
        for start, block in ssd_all_shifts(grid.codes, grid.offset_deg, grid.step_deg, m, COARSE_STRIDE):
            stop = start + block.shape[0]
            coarse_arg[start:stop] = np.argmin(block, axis=1)
            coarse_best[start:stop] = np.min(block, axis=1) * scale
        # the coarse shift is good to half a coarse step: search a band of fine shifts around it
        half = COARSE_STRIDE // 2 + 1
        band = np.arange(-half, half + 1)
        node_shifts = (coarse_arg[:, None] * COARSE_STRIDE + band[None, :]) % n_az
        coarse = np.repeat(coarse_best[:, None], band.size, axis=1).astype(np.float32)

    # first pass -> plausible nodes -> rescored on every azimuth.  Both likelihood bounds fall as
    # the residual grows, so each node's best first-pass shift decides for the node.
    cmin = np.min(coarse, axis=1).astype(np.float64)
    c_lo, c_up = log_likelihood_bounds(cmin, n, sig_lo, sig_hi)
    lp = np.zeros(n_nodes) if log_prior is None else np.asarray(log_prior, dtype=np.float64)
    node_up = c_up + lp
    best_lo = float(np.max(c_lo + lp))
    rescore = np.nonzero(node_up >= best_lo - RESCORE_MARGIN_NATS)[0]
    if rescore.size < MIN_RESCORE:
        rescore = np.sort(np.argpartition(-node_up, min(MIN_RESCORE, n_nodes) - 1)[:MIN_RESCORE])
    ssd_r = ssd_for_shifts(grid.codes, grid.offset_deg, grid.step_deg, m, node_shifts[rescore], rows=rescore)
    ssd_r = ssd_r.astype(np.float64)
    if not np.isfinite(ssd_r).any():
        raise EstimationError("no candidate node has terrain along the measured azimuths")

    # Exact posteriors over the rescored candidates.  The others lie hundreds of nats below the
    # best: their share of the sums is nil, and their own posteriors are their likelihood over the
    # (unchanged) sum of the rest.
    lp_r = lp[rescore, None]
    lo_r, up_r = log_likelihood_bounds(ssd_r, n, sig_lo, sig_hi)
    post = posterior_bounds(lo_r + lp_r, up_r + lp_r)
    best_flat = int(np.argmax(post.log_lower))
    best_r, best_k = divmod(best_flat, ssd_r.shape[1])
    best_node = int(rescore[best_r])
    best_lower_log = float(post.log_lower.ravel()[best_flat])
    log_sum_up = float(np.logaddexp.reduce((up_r + lp_r).ravel()))
    log_sum_lo = float(np.logaddexp.reduce((lo_r + lp_r).ravel()))
    node_lower = c_lo + lp - log_sum_up
    node_upper = node_up - log_sum_lo
    node_lower[rescore] = np.max(post.log_lower, axis=1)
    node_upper[rescore] = np.max(post.log_upper, axis=1)
    region = np.nonzero(node_upper >= best_lower_log)[0]

    # a precise posterior at sigma's midpoint, marginal over heading: what fusion carries forward
    mid = 0.5 * (sig_lo + sig_hi)
    node_mid = np.full(n_nodes, -np.inf)
    ll_mid = -ssd_r / (2.0 * mid * mid) + lp_r
    node_mid[rescore] = np.logaddexp.reduce(np.where(np.isfinite(ll_mid), ll_mid, -np.inf), axis=1)
    node_mid -= np.logaddexp.reduce(node_mid[rescore])
    posterior_mid = np.exp(node_mid)

    shift_steps = float(node_shifts[best_node, best_k])
    if shift_steps > n_az / 2:
        shift_steps -= n_az
    row, col = divmod(best_node, grid.n_cols)
    frow, fcol, heading = float(row), float(col), shift_steps * step
    rms = math.sqrt(float(ssd_r[best_r, best_k]) / n)
    if refine:
        from appliance.estimator.refine import refine_subcell

        # refine the most likely nodes of the region (the best first) and keep the closest fit
        in_rescore = np.zeros(n_nodes, dtype=bool)
        in_rescore[rescore] = True
        scored = region[in_rescore[region]]
        order = np.argsort(-node_lower[scored])[:REFINE_NODES]
        tries = [best_node] + [int(v) for v in scored[order] if int(v) != best_node]
        # scored like the grid: likelihood at sigma's midpoint plus the prior of the nearest node
        best_fit = (-math.inf, rms, frow, fcol, heading)
        for cand in tries:
            k_c = int(np.argmin(ssd_r[np.searchsorted(rescore, cand)]))
            sh = float(node_shifts[cand, k_c])
            if sh > n_az / 2:
                sh -= n_az
            r_c, c_c, h_c, rms_c = refine_subcell(grid, m, cand, sh * step, math.inf)
            near = int(round(r_c)) * grid.n_cols + int(round(c_c))
            score = -n * rms_c * rms_c / (2.0 * mid * mid) + lp[near]
            if score > best_fit[0]:
                best_fit = (score, rms_c, r_c, c_c, h_c)
        if math.isfinite(best_fit[0]):
            _, rms, frow, fcol, heading = best_fit

    cell_area = grid.dx_m * grid.dy_m
    area = region.size * cell_area
    ambiguous = region.size > AMBIGUOUS_CELLS
    if ambiguous:
        notes.append(
            f"ambiguous: {region.size} cells ({area / 1e6:.2f} km^2) are as likely as the best; "
            "the skyline does not single out one position"
        )
    if rms > 3.0 * sig_hi:
        notes.append(
            f"poor match: residual {rms:.2f} deg RMS against sigma up to {sig_hi:.2f} deg; "
            "the skyline may not come from this map"
        )
    return EstimateResult(
        row=frow, col=fcol, node=best_node, heading_correction_deg=heading,
        lower=float(np.exp(best_lower_log)), upper=float(np.exp(post.log_upper.ravel()[best_flat])),
        log_lower=best_lower_log,
        region_nodes=region, region_area_m2=area, log_lower_map=node_lower, log_upper_map=node_upper,
        posterior_map=posterior_mid, rms_residual_deg=rms, n_valid=n, sigma_deg=(sig_lo, sig_hi),
        ambiguous=ambiguous, candidates=int(np.isfinite(cmin).sum()) * node_shifts.shape[1],
        elapsed_s=time.perf_counter() - t0, notes=notes,
    )
