"""The first pass's compiled kernels: squared residuals on skylines averaged over runs of azimuths.

A database's codes are box-averaged over runs of azimuths once (:func:`decimated`), and so is the
measured skyline (:func:`box_decimate`); every node is then scored on those runs, at a few shifts
(:func:`ssd_coarse`, with a compass) or at every shift keeping its best (:func:`ssd_coarse_best`,
with none).  Terms are weighted by the parallax model's variance per run (tau^2 codes and their
weight and normaliser tables, ``parallax.py``); a node lacking terrain somewhere is scored over
the azimuths it has (``search.py``'s rule).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from appliance.estimator.likelihood import is_occluded, kernel_cap
from appliance.estimator.search import BLOCK, MAX_MISSING_FRACTION, MISSING_CODE
from appliance.numerics import FAST_FINITE


@numba.njit(cache=True, parallel=True, nogil=True)
def _decimate_codes(codes: np.ndarray, offset: np.ndarray, factor: int, out: np.ndarray,
                    partial: np.ndarray) -> None:
    """out[i, t] = mean code of azimuths t*factor .. t*factor+factor-1 of node i, rounded (255 if
    all of them lack terrain); partial[i] = the node lacks terrain somewhere, or is nodata."""
    n, n_az = codes.shape
    n_dec = n_az // factor
    for i in numba.prange(n):
        miss = False
        for t in range(n_dec):
            acc = 0
            cnt = 0
            for j in range(t * factor, (t + 1) * factor):
                c = codes[i, j]
                if c == MISSING_CODE:
                    miss = True
                else:
                    acc += c
                    cnt += 1
            out[i, t] = MISSING_CODE if cnt == 0 else (2 * acc + cnt) // (2 * cnt)
        partial[i] = miss or math.isnan(offset[i])


def decimated(codes: np.ndarray, offset_deg: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Box-averaged uint8 codes of every node, (n_nodes, n_az / factor), in each node's own offset
    and step, and the nodes that lack terrain somewhere (or are nodata).  Made once per database,
    for the first pass; a quarter of the database's size."""
    n, n_az = codes.shape
    out = np.empty((n, n_az // factor), dtype=np.uint8)
    partial = np.empty(n, dtype=np.bool_)
    _decimate_codes(codes, offset_deg, factor, out, partial)
    return out, partial


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _node_weights(trow: np.ndarray, w: np.ndarray, lut_w: np.ndarray, lut_p: np.ndarray, use_tau: bool,
                  ww: np.ndarray) -> float:
    """A node's parallax weight per decimated azimuth into ``ww`` (1 without ``use_tau``), from its
    tau^2 codes ``trow``, and its log-normaliser at shift 0 (0 without ``use_tau``).  ``lut_w`` and
    ``lut_p`` hold each code's weight and normaliser (float32).  Inlined in the kernels: the loop is
    bound by its loads, and a call per node with one complex64 table cost some 5 % more."""
    d = ww.size
    p = 0.0
    if use_tau:
        for t in range(d):
            c = trow[t]
            ww[t] = lut_w[c]
            p += w[t] * lut_p[c]
    else:
        for t in range(d):
            ww[t] = 1.0
    return p


@numba.njit(cache=True, fastmath=FAST_FINITE)
def _code_units(m: np.ndarray, offset: float, step: float, cap: float, mt: np.ndarray) -> tuple[np.float32, np.float32]:
    """The measurements in a node's code units into ``mt``; the factor back to deg^2 and the
    occlusion cap in code units."""
    inv = np.float32(1.0 / step)
    for t in range(m.size):
        mt[t] = (m[t] - offset) * inv
    return np.float32(step * step), np.float32(cap / (step * step))


@numba.njit(cache=True, fastmath=FAST_FINITE)
def _gappy_shift(row: np.ndarray, ww: np.ndarray, mt: np.ndarray, w: np.ndarray, sh: int, cap_c: np.float32,
                 scale: np.float32, n_meas: float) -> tuple[np.float32, np.float32]:
    """One shift of a node lacking terrain somewhere: the residual sum (deg^2) and the occluded
    weight over the azimuths it has, rescaled to the measured weight ``n_meas``; inf (and 0) when it
    lacks more than MAX_MISSING_FRACTION of them."""
    d = row.size
    acc = np.float32(0.0)
    occ = np.float32(0.0)
    cnt = 0.0
    for t in range(d):
        ts = (t + sh) % d
        c = row[ts]
        if w[t] > 0 and c != MISSING_CODE:
            e = mt[t] - np.float32(c)
            q = ww[ts] * e * e
            if is_occluded(e, q, cap_c):
                occ += w[t]
            else:
                acc += w[t] * q
            cnt += w[t]
    if cnt < (1.0 - MAX_MISSING_FRACTION) * n_meas or cnt == 0:
        return np.float32(np.inf), np.float32(0.0)
    return acc * scale * n_meas / cnt, occ * n_meas / cnt


@numba.njit(cache=True)
def _turns(shifts: np.ndarray, d: int) -> tuple[np.ndarray, int, int]:
    """Each shift as the nearest turn either way (decimated steps), and the padding those turns need
    below and above the circle's ``d`` azimuths."""
    n_shift = shifts.size
    turn = np.empty(n_shift, dtype=np.int64)
    pad_lo = 0
    pad_hi = 0
    for k in range(n_shift):
        v = shifts[k] % d
        if v > d // 2:
            v -= d
        turn[k] = v
        pad_lo = max(pad_lo, -v)
        pad_hi = max(pad_hi, v)
    return turn, pad_lo, pad_hi


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _lay_out_padded(row: np.ndarray, cf: np.ndarray, vf: np.ndarray, pad_lo: int, d: int) -> None:
    """A node's codes (``row``) as floats into ``cf`` from ``pad_lo`` on, and codes and weights
    (``vf``, already there) copied round the circle into the padding either side."""
    cc = cf[pad_lo : pad_lo + d]
    for t in range(d):
        cc[t] = np.float32(row[t])
    for j in range(pad_lo):
        cf[j] = cf[j + d]
        vf[j] = vf[j + d]
    for j in range(pad_lo + d, cf.size):
        cf[j] = cf[j - d]
        vf[j] = vf[j - d]


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _three_shifts(mt: np.ndarray, w: np.ndarray, c0: np.ndarray, c1: np.ndarray, c2: np.ndarray, v0: np.ndarray,
                  v1: np.ndarray, v2: np.ndarray, cap_c: np.float32) -> tuple[Any, Any, Any, Any, Any, Any]:
    """The residual sums (code units) and occluded weights of three shifts in one pass over the
    azimuths: ``c*`` and ``v*`` are the node's codes and weights laid out from each shift on."""
    a0 = np.float32(0.0)
    a1 = np.float32(0.0)
    a2 = np.float32(0.0)
    o0 = np.float32(0.0)
    o1 = np.float32(0.0)
    o2 = np.float32(0.0)
    for t in range(mt.size):
        mm = mt[t]
        wt = w[t]
        e = mm - c0[t]
        q = v0[t] * e * e
        h = is_occluded(e, q, cap_c)
        a0 += wt * (np.float32(0.0) if h else q)
        o0 += wt if h else np.float32(0.0)
        e = mm - c1[t]
        q = v1[t] * e * e
        h = is_occluded(e, q, cap_c)
        a1 += wt * (np.float32(0.0) if h else q)
        o1 += wt if h else np.float32(0.0)
        e = mm - c2[t]
        q = v2[t] * e * e
        h = is_occluded(e, q, cap_c)
        a2 += wt * (np.float32(0.0) if h else q)
        o2 += wt if h else np.float32(0.0)
    return a0, a1, a2, o0, o1, o2


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _ssd_coarse(C: np.ndarray, offset: np.ndarray, step: np.ndarray, partial: np.ndarray, m: np.ndarray,
                w: np.ndarray, shifts: np.ndarray, out: np.ndarray, T: np.ndarray, lut_w: np.ndarray, lut_p: np.ndarray,
                use_tau: bool, pen: np.ndarray, cap: float, occ_out: np.ndarray) -> None:
    """out[i, k] = sum_t w_t v_t (m_t - s_i[t + shifts[k]])^2 on decimated codes, in code units;
    v = sigma^2 / (sigma^2 + tau^2) from the tau^2 codes T with ``use_tau`` (else 1), and pen[i] the
    node's log-normaliser at shift 0.  A measurement above the model whose weighted square passes
    ``cap`` (deg^2) is an occluder: left out of the sum, counted by its weight in occ_out[i, k].

    Nodes are taken in blocks, their scratch rows made once per block.  A node with terrain
    everywhere is decoded once into float rows laid out around the circle (codes and weights,
    padded by the largest turn each way), and three shifts are scored per pass over the azimuths."""
    n, d = C.shape
    n_shift = shifts.size
    n_meas = 0.0
    for t in range(d):
        n_meas += w[t]
    turn, pad_lo, pad_hi = _turns(shifts, d)
    n_ext = pad_lo + d + pad_hi
    n_blocks = (n + BLOCK - 1) // BLOCK
    for b in numba.prange(n_blocks):
        mt = np.empty(d, dtype=np.float32)
        cf = np.empty(n_ext, dtype=np.float32)
        vf = np.empty(n_ext, dtype=np.float32)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            o = offset[i]
            pen[i] = 0.0
            if math.isnan(o):
                for k in range(n_shift):
                    out[i, k] = np.inf
                    occ_out[i, k] = 0.0
                continue
            ww = vf[pad_lo : pad_lo + d]
            pen[i] = _node_weights(T[i if use_tau else 0], w, lut_w, lut_p, use_tau, ww)
            scale, cap_c = _code_units(m, o, step[i], cap, mt)
            row = C[i]
            if not partial[i]:
                _lay_out_padded(row, cf, vf, pad_lo, d)
                for k0 in range(0, n_shift, 3):
                    # three shifts per pass (a last group of fewer repeats its last shift)
                    k1 = min(k0 + 1, n_shift - 1)
                    k2 = min(k0 + 2, n_shift - 1)
                    a0, a1, a2, o0, o1, o2 = _three_shifts(
                        mt, w, cf[pad_lo + turn[k0] :], cf[pad_lo + turn[k1] :], cf[pad_lo + turn[k2] :],
                        vf[pad_lo + turn[k0] :], vf[pad_lo + turn[k1] :], vf[pad_lo + turn[k2] :], cap_c)
                    out[i, k0] = a0 * scale
                    occ_out[i, k0] = o0
                    out[i, k1] = a1 * scale
                    occ_out[i, k1] = o1
                    out[i, k2] = a2 * scale
                    occ_out[i, k2] = o2
            else:
                for k in range(n_shift):
                    out[i, k], occ_out[i, k] = _gappy_shift(row, ww, mt, w, shifts[k] % d, cap_c, scale, n_meas)


#: Shifts of the every-heading kernel are scored in runs of this many (the vector width times the
#: unroll of the compiled loop), so no run ends in a scalar remainder.
SHIFT_RUN = 32


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _lay_out_twice(row: np.ndarray, ww: np.ndarray, cf: np.ndarray, vf: np.ndarray, acc: np.ndarray,
                   occ: np.ndarray) -> None:
    """A node's codes (``row``, as floats) and weights (``ww``) laid out twice around the circle into
    ``cf`` and ``vf``, and the per-shift sums ``acc`` and ``occ`` set to 0."""
    d = row.size
    k_pad = acc.size
    for j in range(d):
        cf[j] = np.float32(row[j])
        vf[j] = ww[j]
    for j in range(d, d + k_pad):
        cf[j] = cf[j - d]
        vf[j] = vf[j - d]
    for k in range(k_pad):
        acc[k] = 0.0
        occ[k] = 0.0


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _add_pairs(mt: np.ndarray, w: np.ndarray, cf: np.ndarray, vf: np.ndarray, acc: np.ndarray) -> int:
    """With no finite cap (nothing is an occluder): the terms of two azimuths per pass over the
    shifts added to ``acc``, each shift's sum still taken in azimuth order; the azimuth the pairs
    end at.  Two unmeasured azimuths (weight 0) would add exact zeros: they are skipped, so a
    narrow view costs its share."""
    d = mt.size
    k_pad = acc.size
    for t in range(0, d - 1, 2):
        w0 = w[t]
        w1 = w[t + 1]
        if w0 == 0 and w1 == 0:
            continue
        m0 = mt[t]
        m1 = mt[t + 1]
        c_0 = cf[t : t + k_pad]
        v_0 = vf[t : t + k_pad]
        c_1 = cf[t + 1 : t + 1 + k_pad]
        v_1 = vf[t + 1 : t + 1 + k_pad]
        for k in range(k_pad):
            e0 = m0 - c_0[k]
            e1 = m1 - c_1[k]
            acc[k] = (acc[k] + w0 * (v_0[k] * e0 * e0)) + w1 * (v_1[k] * e1 * e1)
    return d - d % 2


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _add_capped_fours(mt: np.ndarray, w: np.ndarray, cf: np.ndarray, vf: np.ndarray, acc: np.ndarray,
                      occ: np.ndarray, cap_c: np.float32) -> int:
    """With the cap ranked: the terms of four azimuths per pass over the shifts added to ``acc``, an
    occluder's weight to ``occ`` instead of its square; the azimuth the fours end at.  Each sum still
    takes its terms in azimuth order, one rounding each, as one azimuth per pass would
    (:func:`_add_singles`), with a quarter of the loads and stores of the sums; an unmeasured azimuth
    among measured ones adds an exact zero (weight 0)."""
    d = mt.size
    k_pad = acc.size
    zero = np.float32(0.0)
    for t in range(0, d - 3, 4):
        w0 = w[t]
        w1 = w[t + 1]
        w2 = w[t + 2]
        w3 = w[t + 3]
        if w0 == 0 and w1 == 0 and w2 == 0 and w3 == 0:
            continue
        m0 = mt[t]
        m1 = mt[t + 1]
        m2 = mt[t + 2]
        m3 = mt[t + 3]
        c_0 = cf[t : t + k_pad]
        v_0 = vf[t : t + k_pad]
        c_1 = cf[t + 1 : t + 1 + k_pad]
        v_1 = vf[t + 1 : t + 1 + k_pad]
        c_2 = cf[t + 2 : t + 2 + k_pad]
        v_2 = vf[t + 2 : t + 2 + k_pad]
        c_3 = cf[t + 3 : t + 3 + k_pad]
        v_3 = vf[t + 3 : t + 3 + k_pad]
        for k in range(k_pad):
            e0 = m0 - c_0[k]
            q0 = v_0[k] * e0 * e0
            h0 = is_occluded(e0, q0, cap_c)
            e1 = m1 - c_1[k]
            q1 = v_1[k] * e1 * e1
            h1 = is_occluded(e1, q1, cap_c)
            e2 = m2 - c_2[k]
            q2 = v_2[k] * e2 * e2
            h2 = is_occluded(e2, q2, cap_c)
            e3 = m3 - c_3[k]
            q3 = v_3[k] * e3 * e3
            h3 = is_occluded(e3, q3, cap_c)
            acc[k] = ((((acc[k] + w0 * (zero if h0 else q0)) + w1 * (zero if h1 else q1))
                       + w2 * (zero if h2 else q2)) + w3 * (zero if h3 else q3))
            occ[k] = ((((occ[k] + (w0 if h0 else zero)) + (w1 if h1 else zero))
                       + (w2 if h2 else zero)) + (w3 if h3 else zero))
    return d - d % 4


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _add_singles(mt: np.ndarray, w: np.ndarray, cf: np.ndarray, vf: np.ndarray, acc: np.ndarray, occ: np.ndarray,
                 t_start: int, d: int, k_pad: int, cap_c: np.float32, rank_cap: bool) -> None:
    """The terms of azimuths ``t_start`` on added to every shift's sum ``acc``, one azimuth per pass;
    with ``rank_cap`` a term above the model whose weighted square passes ``cap_c`` is an occluder,
    its weight added to ``occ`` instead (``d`` azimuths, ``k_pad`` shifts).  The loop over shifts
    compiles to vector loads and stores only while nothing in it branches (``is_occluded``)."""
    for t in range(t_start, d):
        wt = w[t]
        if wt == 0:
            continue
        mtt = mt[t]
        c_t = cf[t : t + k_pad]
        v_t = vf[t : t + k_pad]
        if rank_cap:
            for k in range(k_pad):
                e = mtt - c_t[k]
                q = v_t[k] * e * e
                hidden = is_occluded(e, q, cap_c)
                acc[k] += wt * (np.float32(0.0) if hidden else q)
                occ[k] += wt if hidden else np.float32(0.0)
        else:
            for k in range(k_pad):
                e = mtt - c_t[k]
                acc[k] += wt * (v_t[k] * e * e)


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _least_shift(acc: np.ndarray, occ: np.ndarray, d: int, scale: np.float32, cap32: np.float32,
                 rank_cap: bool) -> int:
    """The shift (0 .. d-1) of least sum (deg^2), each occluded weight counting ``cap32`` with
    ``rank_cap``: the first of equal ones."""
    best_k = 0
    best = np.float32(np.inf)
    for k in range(d):
        s = acc[k] * scale
        r = s + occ[k] * cap32 if rank_cap else s
        if r < best:
            best = r
            best_k = k
    return best_k


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _least_gappy_shift(row: np.ndarray, ww: np.ndarray, mt: np.ndarray, w: np.ndarray, cap_c: np.float32,
                       scale: np.float32, n_meas: float, cap32: np.float32,
                       rank_cap: bool) -> tuple[int, Any, Any]:
    """:func:`_least_shift` of a node lacking terrain somewhere (:func:`_gappy_shift`): the shift,
    its sum and its occluded weight."""
    best_k = 0
    best = np.float32(np.inf)
    best_s = np.float32(np.inf)
    best_o = np.float32(0.0)
    for sh in range(row.size):
        s, oc = _gappy_shift(row, ww, mt, w, sh, cap_c, scale, n_meas)
        r = s + oc * cap32 if rank_cap else s
        if r < best or (sh == 0):
            best = r
            best_k = sh
            best_s = s
            best_o = oc
    return best_k, best_s, best_o


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _ssd_coarse_best(C: np.ndarray, offset: np.ndarray, step: np.ndarray, partial: np.ndarray, m: np.ndarray,
                     w: np.ndarray, out: np.ndarray, occ_out: np.ndarray, arg_out: np.ndarray, T: np.ndarray,
                     lut_w: np.ndarray, lut_p: np.ndarray, use_tau: bool, pen: np.ndarray, cap: float,
                     rank_cap: bool) -> None:
    """Every circular shift k = 0 .. d-1 of each node's decimated codes scored as in
    :func:`_ssd_coarse`, keeping only the best: arg_out[i] = the k of least out + cap * occ (the first
    of equal ones), out[i] and occ_out[i] its residual sum (deg^2) and occluded weight, pen[i] the
    node's log-normaliser at shift 0; the cap enters the ranking only with ``rank_cap``.

    All shifts are scored at once: for each measured azimuth t, the terms of every shift are added
    to per-shift sums held in a contiguous scratch row (the node's codes and weights laid out twice
    around the circle), so the compiled loop runs along the shifts with no reduction and each
    shift's sum is taken in azimuth order."""
    n, d = C.shape
    n_meas = 0.0
    for t in range(d):
        n_meas += w[t]
    k_pad = ((d + SHIFT_RUN - 1) // SHIFT_RUN) * SHIFT_RUN
    n_blocks = (n + BLOCK - 1) // BLOCK
    cap32 = np.float32(cap)
    for b in numba.prange(n_blocks):
        ww = np.empty(d, dtype=np.float32)
        mt = np.empty(d, dtype=np.float32)
        cf = np.empty(d + k_pad, dtype=np.float32)
        vf = np.empty(d + k_pad, dtype=np.float32)
        acc = np.empty(k_pad, dtype=np.float32)
        occ = np.empty(k_pad, dtype=np.float32)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            o = offset[i]
            pen[i] = 0.0
            if math.isnan(o):
                out[i] = np.inf
                occ_out[i] = 0.0
                arg_out[i] = 0
                continue
            pen[i] = _node_weights(T[i if use_tau else 0], w, lut_w, lut_p, use_tau, ww)
            scale, cap_c = _code_units(m, o, step[i], cap, mt)
            row = C[i]
            if not partial[i]:
                _lay_out_twice(row, ww, cf, vf, acc, occ)
                if rank_cap:
                    t_start = _add_capped_fours(mt, w, cf, vf, acc, occ, cap_c)
                else:
                    t_start = _add_pairs(mt, w, cf, vf, acc)
                _add_singles(mt, w, cf, vf, acc, occ, t_start, d, k_pad, cap_c, rank_cap)
                best_k = _least_shift(acc, occ, d, scale, cap32, rank_cap)
                arg_out[i] = best_k
                out[i] = acc[best_k] * scale
                occ_out[i] = occ[best_k]
            else:
                arg_out[i], out[i], occ_out[i] = _least_gappy_shift(row, ww, mt, w, cap_c, scale, n_meas, cap32,
                                                                    rank_cap)


def _coarse_inputs(measured_dec: np.ndarray, weights_dec: np.ndarray | None,
                   tau: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> tuple[Any, ...]:
    """The first-pass kernels' inputs: the decimated measurements (0 where missing) and their
    weights (0 where missing) in float32, the tau^2 codes, their weight and normaliser tables
    (float32), and whether to use them (placeholders without ``tau``)."""
    valid = np.isfinite(measured_dec)
    m = np.where(valid, measured_dec, 0.0).astype(np.float32)
    w = valid.astype(np.float32) if weights_dec is None else np.where(valid, weights_dec, 0.0).astype(np.float32)
    if tau is None:
        return m, w, np.zeros((1, 1), np.uint8), np.ones(256, np.float32), np.zeros(256, np.float32), False
    codes, w_lut, p_lut = tau
    return m, w, codes, np.asarray(w_lut, np.float32), np.asarray(p_lut, np.float32), True


def ssd_coarse_best(
    coarse: tuple[np.ndarray, np.ndarray], offset_deg: np.ndarray, step_deg: np.ndarray,
    measured_dec: np.ndarray, tau: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    weights_dec: np.ndarray | None = None, cap_deg2: float = math.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every node's best circular shift (decimated steps) on decimated skylines: its SSD (deg^2),
    occluded weight, the shift, and the node's log-normaliser.  The same scores as
    :func:`ssd_coarse` over every shift followed by the least of ``ssd + cap_deg2 * occluded`` per
    node, without the (n_nodes, n_shifts) array; sums may differ from it in the last bits (their
    terms are added in azimuth order)."""
    C, partial = coarse
    m, w, T, lut_w, lut_p, use = _coarse_inputs(measured_dec, weights_dec, tau)
    n = C.shape[0]
    out = np.empty(n, dtype=np.float32)
    occ = np.empty(n, dtype=np.float32)
    arg = np.empty(n, dtype=np.int64)
    pen = np.empty(n, dtype=np.float32)
    _ssd_coarse_best(C, offset_deg, step_deg, partial, m, w, out, occ, arg, T, lut_w, lut_p, use, pen,
                     kernel_cap(cap_deg2), math.isfinite(cap_deg2))
    return out, occ, arg, pen


def ssd_coarse(
    coarse: tuple[np.ndarray, np.ndarray], offset_deg: np.ndarray, step_deg: np.ndarray,
    measured_dec: np.ndarray, shifts: np.ndarray, tau: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    weights_dec: np.ndarray | None = None, cap_deg2: float = math.inf, occluded: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """SSD (deg^2) of every node on decimated skylines (:func:`decimated`) for shifts in decimated
    steps, shape (n_nodes, len(shifts)), and each node's log-normaliser.  ``tau`` = (tau^2 codes,
    weight table, normaliser table) weights the residuals by the model variance; ``weights_dec``
    weighs the measured azimuths (default 1); ``cap_deg2`` is the occlusion cap, and ``occluded``
    (same shape as the result) receives the weight of the measurements taken for occluders."""
    C, partial = coarse
    m, w, T, lut_w, lut_p, use = _coarse_inputs(measured_dec, weights_dec, tau)
    out = np.empty((C.shape[0], len(shifts)), dtype=np.float32)
    pen = np.empty(C.shape[0], dtype=np.float32)
    occ = np.empty_like(out) if occluded is None else occluded
    _ssd_coarse(C, offset_deg, step_deg, partial, m, w, np.asarray(shifts, dtype=np.int64), out, T, lut_w, lut_p,
                use, pen, kernel_cap(cap_deg2), occ)
    return out, pen


def box_decimate(values: np.ndarray, factor: int) -> np.ndarray:
    """Mean of each run of ``factor`` azimuths (NaN-aware; all-missing runs stay NaN), last axis."""
    if factor == 1:
        return values
    n = values.shape[-1]
    if n % factor:
        raise ValueError(f"{n} azimuths are not a multiple of {factor}")
    blocks = values.reshape(values.shape[:-1] + (n // factor, factor))
    ok = np.isfinite(blocks)
    cnt = ok.sum(axis=-1)
    total = np.where(ok, blocks, 0.0).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, total / np.maximum(cnt, 1), np.nan)
