"""Grid search: squared residuals between one measured skyline and every database skyline.

For a candidate node and a heading correction of k azimuth steps, the residual sum is

    SSD(node, k) = sum_j w_j (m_j - s_node[j + k])^2,

m on the database's azimuth grid (w = 0 where m is missing).  With a compass k spans a few steps
around zero: a compiled loop over nodes (numba, both cores) decodes each node's uint8 skyline
once and scores every shift on contiguous memory.  With no compass every shift of a node is
scored at once, the terms of each measured azimuth added to per-shift sums along a contiguous
row, and only the node's best shift is kept.

A database azimuth with no terrain (code 255) at a node is left out of that node's sum and the
sum rescaled to the measured count; a node missing more than a tenth of them is not a candidate.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from appliance.estimator.likelihood import is_occluded, kernel_cap, variance_weight
from appliance.estimator.parallax import map_var_at, tau2_at
from appliance.numerics import FAST_FINITE

MISSING_CODE = 255
MAX_MISSING_FRACTION = 0.1
BLOCK = 256


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _tau_weights(codes: np.ndarray, dist: np.ndarray, i: int, lo: int, hi: int, o: float, st: float, az_step: float,
                 g2: float, rho2: float, inv_d2: np.ndarray, map2: float, sig2: float, wn: np.ndarray) -> None:
    """wn[j] = sigma^2 / (sigma^2 + tau^2) (float32) of node i at azimuths lo <= j < hi (``parallax.py``)."""
    n_az = codes.shape[1]
    for j in range(lo, hi):
        t2 = tau2_at(codes, dist, i, j, n_az, o, st, az_step, g2, rho2, inv_d2)
        t2 += map_var_at(dist, i, j, map2, inv_d2)
        wn[j] = np.float32(variance_weight(sig2, t2))


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _tau_arc(codes: np.ndarray, dist: np.ndarray, i: int, first: int, count: int, o: float, st: float,
             az_step: float, g2: float, rho2: float, inv_d2: np.ndarray, map2: float, sig2: float,
             wn: np.ndarray) -> None:
    """:func:`_tau_weights` over ``count`` azimuths from ``first`` on, round the circle."""
    n_az = codes.shape[1]
    end = first + count
    _tau_weights(codes, dist, i, first, min(end, n_az), o, st, az_step, g2, rho2, inv_d2, map2, sig2, wn)
    if end > n_az:
        _tau_weights(codes, dist, i, 0, end - n_az, o, st, az_step, g2, rho2, inv_d2, map2, sig2, wn)


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _node_tau(codes: np.ndarray, dist: np.ndarray, i: int, o: float, st: float, g2: float, rho2: float,
              inv_d2: np.ndarray, map2: float, sig2: float, jj: np.ndarray, wj: np.ndarray, want_pen: bool,
              start: int, arc: int, reach: int, shift0: int, wn: np.ndarray, wp: np.ndarray) -> float:
    """Node i's weights sigma^2 / (sigma^2 + tau^2) into ``wn`` where its shifts read them (from
    ``start`` + ``shift0`` on, ``reach`` >= 0; everywhere, -1), and its log-normaliser over the
    measured azimuths ``jj`` (0 unless ``want_pen``, or with ``reach`` >= 0 unless ``arc`` > 0;
    ``wp`` is scratch): :func:`_ssd_shifts`'s arguments."""
    n_az = codes.shape[1]
    az_step = 360.0 / n_az
    p = 0.0
    if reach < 0:
        _tau_weights(codes, dist, i, 0, n_az, o, st, az_step, g2, rho2, inv_d2, map2, sig2, wn)
        if want_pen:
            for t in range(jj.size):
                p -= wj[t] * math.log(wn[jj[t]])
    else:
        # the normaliser's weights over the measured arc (none asked for: arc 0), then the
        # shifts' over theirs
        if arc > 0:
            _tau_arc(codes, dist, i, start, arc, o, st, az_step, g2, rho2, inv_d2, map2, sig2, wp)
            for t in range(jj.size):
                p -= wj[t] * math.log(wp[jj[t]])
        _tau_arc(codes, dist, i, (start + shift0) % n_az, reach, o, st, az_step, g2, rho2, inv_d2, map2, sig2, wn)
    return p


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _shift_sum(codes: np.ndarray, i: int, sh: int, jj: np.ndarray, mt: np.ndarray, wj: np.ndarray, wn: np.ndarray,
               cap_c: np.float32) -> tuple[Any, Any, int]:
    """Node i's weighted residual sum at shift ``sh`` (code units), the weight of the measurements
    taken for occluders, and how many of the measured azimuths ``jj`` it has terrain at."""
    n_az = codes.shape[1]
    acc = np.float32(0.0)
    occ = np.float32(0.0)
    cnt = 0
    for t in range(jj.size):
        idx = jj[t] + sh
        if idx >= n_az:
            idx -= n_az
        c = codes[i, idx]
        if c != MISSING_CODE:
            d = mt[t] - np.float32(c)
            q = wn[idx] * d * d
            if is_occluded(d, q, cap_c):
                occ += wj[t]
            else:
                acc += wj[t] * q
            cnt += 1
    return acc, occ, cnt


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _ssd_shifts(codes: np.ndarray, offset: np.ndarray, step: np.ndarray, jj: np.ndarray, mj: np.ndarray,
                rows: np.ndarray, shifts: np.ndarray, out: np.ndarray, dist: np.ndarray, g2: np.ndarray, rho2: float,
                inv_d2: np.ndarray, sig2: float, use_tau: bool, pen: np.ndarray, want_pen: bool, wj: np.ndarray,
                cap: float, map2: float, occ_out: np.ndarray, start: int, arc: int, reach: int) -> None:
    """out[r, k] = sum_t w_t (mj[t] - s_i[jj[t] + shifts[r, k]])^2 for node i = rows[r].

    Works in each node's code units, (m - offset) / step against the uint8 codes, so a skyline is
    never decoded; azimuths where the node has no terrain are left out and the sum rescaled.  With
    ``use_tau`` each term is weighted by sigma^2 / (sigma^2 + tau^2) (``parallax.py``) and pen[r]
    is the node's log-normaliser, sum_t log(1 + tau^2 / sigma^2) at shift 0 (0 unless ``want_pen``).
    ``wj`` weighs the measured azimuths; a measurement above the model whose weighted square passes
    ``cap`` (deg^2) is an occluder, not evidence against the node: it is left out of the sum and
    counted (by its weight) in occ_out[r, k].  ``reach`` >= 0 says the measured azimuths lie among
    the ``arc`` from ``start`` on and every azimuth the shifts of row r read among the ``reach`` from
    ``start`` + shifts[r, 0] on (circularly): the weights are made there only, a narrow view's few
    dozen azimuths rather than the whole circle (the same numbers), and pen[r] = 0 when ``arc`` is 0;
    -1: everywhere.
    """
    n_az = codes.shape[1]
    n_shift = shifts.shape[1]
    n_t = jj.size
    n_rows = rows.size
    n_blocks = (n_rows + BLOCK - 1) // BLOCK
    for b in numba.prange(n_blocks):
        mt = np.empty(n_t, dtype=np.float32)
        wn = np.ones(n_az, dtype=np.float32)
        wp = np.ones(n_az, dtype=np.float32)
        for r in range(b * BLOCK, min(n_rows, (b + 1) * BLOCK)):
            i = rows[r]
            o = offset[i]
            pen[r] = 0.0
            if math.isnan(o):
                for k in range(n_shift):
                    out[r, k] = np.inf
                    occ_out[r, k] = 0.0
                continue
            st = step[i]
            if use_tau:
                pen[r] = _node_tau(codes, dist, i, o, st, g2[i], rho2, inv_d2, map2, sig2, jj, wj, want_pen, start,
                                   arc, reach, shifts[r, 0], wn, wp)
            inv = np.float32(1.0 / st)
            for t in range(n_t):
                mt[t] = (mj[t] - o) * inv
            scale = np.float32(st * st)
            cap_c = np.float32(cap / (st * st))
            for k in range(n_shift):
                acc, occ, cnt = _shift_sum(codes, i, shifts[r, k] % n_az, jj, mt, wj, wn, cap_c)
                if cnt == n_t:
                    out[r, k] = acc * scale
                    occ_out[r, k] = occ
                elif cnt < (1.0 - MAX_MISSING_FRACTION) * n_t:
                    out[r, k] = np.inf
                    occ_out[r, k] = 0.0
                else:
                    out[r, k] = acc * scale * n_t / cnt
                    occ_out[r, k] = occ * n_t / cnt


def ssd_for_shifts(
    codes: np.ndarray,
    offset_deg: np.ndarray,
    step_deg: np.ndarray,
    measured_deg: np.ndarray,
    shifts: np.ndarray,
    rows: np.ndarray | None = None,
    tau: TauModel | None = None,
    weights: np.ndarray | None = None,
    cap_deg2: float = math.inf,
    occluded: np.ndarray | None = None,
) -> np.ndarray:
    """SSD (deg^2) of nodes ``rows`` (default all) for each shift (azimuth steps).

    ``shifts`` is 1-D (the same for every node) or (len(rows), k) per node.  ``measured_deg`` is on
    the database's azimuth grid with NaN where missing.  inf marks nodes
    that cannot be candidates (nodata, or too many azimuths without terrain).  ``weights`` weigh
    the measured azimuths; measurements above a node's skyline by more than ``cap_deg2`` (weighted
    square) are occluders, left out of the sum and counted in ``occluded`` (same shape as the result).
    """
    valid = np.isfinite(measured_deg)
    jj = np.nonzero(valid)[0].astype(np.int64)
    mj = np.asarray(measured_deg)[jj].astype(np.float32)
    wj = np.ones(jj.size, np.float32) if weights is None else np.asarray(weights, np.float32)[jj]
    cap = kernel_cap(cap_deg2)
    idx = np.arange(codes.shape[0], dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    sh = np.asarray(shifts, dtype=np.int64)
    if sh.ndim == 1:
        sh = np.broadcast_to(sh, (idx.size, sh.size))
    sh = np.ascontiguousarray(sh)
    out = np.empty((idx.size, sh.shape[1]), dtype=np.float32)
    pen = np.empty(idx.size, dtype=np.float64)
    occ = np.empty(out.shape, dtype=np.float32) if occluded is None else occluded
    if tau is None:
        _ssd_shifts(codes, offset_deg, step_deg, jj, mj, idx, sh, out, np.zeros((1, 1), np.uint8),
                    np.zeros(1, np.float32), 0.0, np.zeros(256, np.float32), 1.0, False, pen, False, wj, cap, 0.0, occ,
                    0, 0, -1)
    else:
        start, arc, reach = _shift_reach(jj, sh, codes.shape[1])
        if not tau.with_penalty:
            arc = 0
        _ssd_shifts(codes, offset_deg, step_deg, jj, mj, idx, sh, out, tau.distance_codes, tau.g2, tau.rho2,
                    tau.inv_d2, tau.sigma_ref**2, True, pen, tau.with_penalty, wj, cap, tau.map_sigma_m**2, occ, start,
                    arc, reach)
        if tau.with_penalty:
            tau.penalty = pen
    return out


def _shift_reach(jj: np.ndarray, shifts: np.ndarray, n_az: int) -> tuple[int, int, int]:
    """Where the measured azimuths ``jj`` lie and where the shifts of each row read them (the
    ``start``, ``arc`` and ``reach`` of :func:`_ssd_shifts`): the shortest arc holding ``jj``, and
    that arc widened by the spread of a row's shifts.  (0, 0, -1), the whole circle, when the two
    arcs together cover more than half of it (the weights of every azimuth, made in one sweep, cost
    no more) or the rows' shifts are not one pattern moved along it."""
    if jj.size == 0 or shifts.shape[0] == 0:
        return 0, 0, -1
    # the arc starts after the widest gap between measured azimuths (circularly)
    gaps = np.diff(np.append(jj, jj[0] + n_az))
    widest = int(np.argmax(gaps))
    start = int(jj[(widest + 1) % jj.size])
    arc = n_az - int(gaps[widest]) + 1
    if 2 * arc > n_az // 2:
        return 0, 0, -1
    rel = (shifts - shifts[:, :1]) % n_az
    if not (rel == rel[:1]).all():
        return 0, 0, -1
    reach = arc + int(rel[0].max())
    return (start, arc, reach) if arc + reach <= n_az // 2 else (0, 0, -1)


class TauModel:
    """The parallax model's inputs for the full-resolution kernel (``parallax.py``); ``penalty``
    receives each scored node's log-normaliser, unless ``with_penalty`` is False (a caller that
    wants the sums only: a narrow view's kernel then skips the normaliser's weights)."""

    def __init__(self, distance_codes: np.ndarray, g2: np.ndarray, rho2: float, inv_d2: np.ndarray,
                 sigma_ref: float, map_sigma_m: float = 0.0, with_penalty: bool = True):
        self.distance_codes, self.g2, self.rho2, self.inv_d2 = distance_codes, g2, rho2, inv_d2
        self.sigma_ref, self.map_sigma_m = sigma_ref, map_sigma_m
        self.with_penalty = with_penalty
        self.penalty = np.zeros(0)
