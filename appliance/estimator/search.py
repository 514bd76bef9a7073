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
        wn[j] = np.float32(sig2 / (sig2 + t2))


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


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _ssd_shifts(
    codes: np.ndarray,
    offset: np.ndarray,
    step: np.ndarray,
    jj: np.ndarray,
    mj: np.ndarray,
    rows: np.ndarray,
    shifts: np.ndarray,
    out: np.ndarray,
    dist: np.ndarray,
    g2: np.ndarray,
    rho2: float,
    inv_d2: np.ndarray,
    sig2: float,
    use_tau: bool,
    pen: np.ndarray,
    want_pen: bool,
    wj: np.ndarray,
    cap: float,
    map2: float,
    occ_out: np.ndarray,
    start: int,
    arc: int,
    reach: int,
) -> None:
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
    az_step = 360.0 / n_az
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
                p = 0.0
                if reach < 0:
                    _tau_weights(codes, dist, i, 0, n_az, o, st, az_step, g2[i], rho2, inv_d2, map2, sig2, wn)
                    if want_pen:
                        for t in range(n_t):
                            p -= wj[t] * math.log(wn[jj[t]])
                else:
                    # the normaliser's weights over the measured arc (none asked for: arc 0), then the
                    # shifts' over theirs
                    if arc > 0:
                        _tau_arc(codes, dist, i, start, arc, o, st, az_step, g2[i], rho2, inv_d2, map2, sig2, wp)
                        for t in range(n_t):
                            p -= wj[t] * math.log(wp[jj[t]])
                    _tau_arc(codes, dist, i, (start + shifts[r, 0]) % n_az, reach, o, st, az_step, g2[i], rho2,
                             inv_d2, map2, sig2, wn)
                pen[r] = p
            inv = np.float32(1.0 / st)
            for t in range(n_t):
                mt[t] = (mj[t] - o) * inv
            scale = np.float32(st * st)
            cap_c = np.float32(cap / (st * st))
            for k in range(n_shift):
                sh = shifts[r, k] % n_az
                acc = np.float32(0.0)
                occ = np.float32(0.0)
                cnt = 0
                for t in range(n_t):
                    idx = jj[t] + sh
                    if idx >= n_az:
                        idx -= n_az
                    c = codes[i, idx]
                    if c != MISSING_CODE:
                        d = mt[t] - np.float32(c)
                        q = wn[idx] * d * d
                        if d > 0 and q > cap_c:
                            occ += wj[t]
                        else:
                            acc += wj[t] * q
                        cnt += 1
                if cnt == n_t:
                    out[r, k] = acc * scale
                    occ_out[r, k] = occ
                elif cnt < (1.0 - MAX_MISSING_FRACTION) * n_t:
                    out[r, k] = np.inf
                    occ_out[r, k] = 0.0
                else:
                    out[r, k] = acc * scale * n_t / cnt
                    occ_out[r, k] = occ * n_t / cnt


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
            if e > 0 and q > cap_c:
                occ += w[t]
            else:
                acc += w[t] * q
            cnt += w[t]
    if cnt < (1.0 - MAX_MISSING_FRACTION) * n_meas or cnt == 0:
        return np.float32(np.inf), np.float32(0.0)
    return acc * scale * n_meas / cnt, occ * n_meas / cnt


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
    # each shift as the nearest turn either way, and the padding those turns need around the circle
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
                cc = cf[pad_lo : pad_lo + d]
                for t in range(d):
                    cc[t] = np.float32(row[t])
                for j in range(pad_lo):
                    cf[j] = cf[j + d]
                    vf[j] = vf[j + d]
                for j in range(pad_lo + d, n_ext):
                    cf[j] = cf[j - d]
                    vf[j] = vf[j - d]
                for k0 in range(0, n_shift, 3):
                    # three shifts per pass (a last group of fewer repeats its last shift)
                    k1 = min(k0 + 1, n_shift - 1)
                    k2 = min(k0 + 2, n_shift - 1)
                    c0 = cf[pad_lo + turn[k0] :]
                    c1 = cf[pad_lo + turn[k1] :]
                    c2 = cf[pad_lo + turn[k2] :]
                    v0 = vf[pad_lo + turn[k0] :]
                    v1 = vf[pad_lo + turn[k1] :]
                    v2 = vf[pad_lo + turn[k2] :]
                    a0 = np.float32(0.0)
                    a1 = np.float32(0.0)
                    a2 = np.float32(0.0)
                    o0 = np.float32(0.0)
                    o1 = np.float32(0.0)
                    o2 = np.float32(0.0)
                    for t in range(d):
                        mm = mt[t]
                        wt = w[t]
                        e = mm - c0[t]
                        q = v0[t] * e * e
                        h = e > 0 and q > cap_c
                        a0 += wt * (np.float32(0.0) if h else q)
                        o0 += wt if h else np.float32(0.0)
                        e = mm - c1[t]
                        q = v1[t] * e * e
                        h = e > 0 and q > cap_c
                        a1 += wt * (np.float32(0.0) if h else q)
                        o1 += wt if h else np.float32(0.0)
                        e = mm - c2[t]
                        q = v2[t] * e * e
                        h = e > 0 and q > cap_c
                        a2 += wt * (np.float32(0.0) if h else q)
                        o2 += wt if h else np.float32(0.0)
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
                for j in range(d):
                    cf[j] = np.float32(row[j])
                    vf[j] = ww[j]
                for j in range(d, d + k_pad):
                    cf[j] = cf[j - d]
                    vf[j] = vf[j - d]
                for k in range(k_pad):
                    acc[k] = 0.0
                    occ[k] = 0.0
                t_start = 0
                if not rank_cap:
                    # no finite cap, nothing is an occluder: two azimuths per pass over the shifts,
                    # each shift's sum still taken in azimuth order.  Two unmeasured azimuths (weight
                    # 0) would add exact zeros: they are skipped, so a narrow view costs its share.
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
                    t_start = d - d % 2
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
                            hidden = e > 0 and q > cap_c
                            acc[k] += wt * (np.float32(0.0) if hidden else q)
                            occ[k] += wt if hidden else np.float32(0.0)
                    else:
                        for k in range(k_pad):
                            e = mtt - c_t[k]
                            acc[k] += wt * (v_t[k] * e * e)
                best_k = 0
                best = np.float32(np.inf)
                for k in range(d):
                    s = acc[k] * scale
                    r = s + occ[k] * cap32 if rank_cap else s
                    if r < best:
                        best = r
                        best_k = k
                arg_out[i] = best_k
                out[i] = acc[best_k] * scale
                occ_out[i] = occ[best_k]
            else:
                best_k = 0
                best = np.float32(np.inf)
                best_s = np.float32(np.inf)
                best_o = np.float32(0.0)
                for sh in range(d):
                    s, oc = _gappy_shift(row, ww, mt, w, sh, cap_c, scale, n_meas)
                    r = s + oc * cap32 if rank_cap else s
                    if r < best or (sh == 0):
                        best = r
                        best_k = sh
                        best_s = s
                        best_o = oc
                arg_out[i] = best_k
                out[i] = best_s
                occ_out[i] = best_o


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
                     float(min(cap_deg2, 1e30)), math.isfinite(cap_deg2))
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
                use, pen, float(min(cap_deg2, 1e30)), occ)
    return out, pen


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
    cap = float(min(cap_deg2, 1e30))
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
