"""A photo whose orientation nobody surveyed: every node screened with its yaw and tilt as unknowns.

A photo's skyline comes as elevations at azimuths relative to its optical axis, read through a
nominal orientation (level, yaw 0).  The true orientation differs by a yaw, which shifts the whole
skyline along azimuth, and by a pitch and a roll of a few degrees.  Over the photo's arc, to first
order, pitch and roll change the elevation seen at relative azimuth u by

    t1 cos u + t2 sin u        (t1: the axis tilted down; t2: the right-hand side tilted up)

so a node's best fit at a yaw is a linear least-squares problem in (t1, t2), with a Gaussian prior
on each (the level's tolerance).  :func:`screen` scores every node at every yaw shift of the
database's azimuth step that way, robustly: the fit is made, the measurements left more than
``clip_deg`` from it (trees, masts, clouds the detector took for terrain) are dropped, the fit made
again, and every residual costs at most ``clip_deg`` squared.  Its answers are hypotheses
(node, yaw, tilt) for an exact orientation fit on renders; it decides nothing on its own.

Pure numpy and numba: the database's uint8 codes in, scores out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from appliance.estimator import parallax
from appliance.estimator.likelihood import is_occluded, variance_log_normaliser, variance_weight
from appliance.estimator.search import MISSING_CODE
from appliance.numerics import FAST_FINITE

#: A residual (deg) beyond which a measurement is taken for something the map lacks.
CLIP_DEG = 1.0
#: The least share of the measured azimuths a node must see terrain at to be scored.
MIN_SEEN_SHARE = 0.8
#: A node within this many cells of a hypothesis' node, at a yaw within this many degrees of its, is the same answer.
SAME_HYPOTHESIS_CELLS = 3.0
SAME_HYPOTHESIS_YAW_DEG = 3.0


@dataclass(frozen=True)
class Hypothesis:
    """A node and the orientation that fits it best: yaw (the true azimuth of relative azimuth 0,
    deg) and the tilt terms (deg) of the module's model; ``cost`` the robust sum of squares (deg^2)."""

    node: int
    yaw_deg: float
    t1_deg: float
    t2_deg: float
    cost: float


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _screen(codes: np.ndarray, offset: np.ndarray, step: np.ndarray, nodes: np.ndarray, m: np.ndarray,
            w: np.ndarray, k_idx: np.ndarray, uc: np.ndarray, us: np.ndarray, shifts: np.ndarray,
            tau_codes: np.ndarray, stride: int, lut_w: np.ndarray, lut_p: np.ndarray, sig2: float, lam1: float,
            lam2: float, bound1: float, bound2: float, clip2: float, rounds: int, min_seen: float,
            out_cost: np.ndarray, out_shift: np.ndarray, out_t: np.ndarray) -> None:
    n_az = codes.shape[1]
    n_k = m.size
    w_total = 0.0
    for k in range(n_k):
        w_total += w[k]
    # each azimuth's run of the parallax codes, once (not a division per measurement and yaw)
    run = np.empty(n_az, dtype=np.int64)
    for j in range(n_az):
        run[j] = j // stride
    for ii in numba.prange(nodes.size):
        node = nodes[ii]
        off = offset[node]
        st = step[node]
        best = np.inf
        best_h = -1
        b1 = 0.0
        b2 = 0.0
        r = np.empty(n_k)
        keep = np.empty(n_k)
        has = np.empty(n_k, dtype=np.bool_)
        pw = np.empty(n_k)
        use_tau = tau_codes.shape[0] > 0
        pen = 0.0
        for hh in range(shifts.size):
            h = shifts[hh]
            seen = 0.0
            pen = 0.0
            for k in range(n_k):
                j = k_idx[k] + h  # both in [0, n_az): the remainder is one subtraction at most
                if j >= n_az:
                    j -= n_az
                c = codes[node, j]
                has[k] = c != MISSING_CODE and w[k] > 0.0
                if not has[k]:
                    keep[k] = 0.0
                    r[k] = 0.0
                    pw[k] = 0.0
                else:
                    if use_tau:
                        tc = tau_codes[node, run[j]]
                        pw[k] = w[k] * lut_w[tc]
                        pen += w[k] * sig2 * lut_p[tc]
                    else:
                        pw[k] = w[k]
                    keep[k] = pw[k]
                    seen += w[k]
                    r[k] = m[k] - (off + st * c)
            if seen < min_seen * w_total:
                continue
            t1 = 0.0
            t2 = 0.0
            for rnd in range(rounds):
                s11 = lam1
                s12 = 0.0
                s22 = lam2
                y1 = 0.0
                y2 = 0.0
                for k in range(n_k):
                    q = keep[k]
                    if q > 0.0:
                        s11 += q * uc[k] * uc[k]
                        s12 += q * uc[k] * us[k]
                        s22 += q * us[k] * us[k]
                        y1 += q * uc[k] * r[k]
                        y2 += q * us[k] * r[k]
                det = s11 * s22 - s12 * s12
                if det <= 0.0:
                    break
                t1 = (s22 * y1 - s12 * y2) / det
                t2 = (s11 * y2 - s12 * y1) / det
                if abs(t1) > bound1 or abs(t2) > bound2:
                    # the level's tolerance is a bound: the best fit on the box's edge
                    t1 = min(max(t1, -bound1), bound1)
                    t2 = min(max((y2 - s12 * t1) / s22, -bound2), bound2)
                    t1 = min(max((y1 - s12 * t2) / s11, -bound1), bound1)
                if rnd == rounds - 1:
                    break  # the measurements kept after the last fit are not read
                changed = False
                for k in range(n_k):
                    if has[k]:
                        e = r[k] - t1 * uc[k] - t2 * us[k]
                        q = pw[k] if pw[k] * e * e < w[k] * clip2 else 0.0
                        if q != keep[k]:
                            changed = True
                        keep[k] = q
                if not changed:
                    # the same measurements kept: every further round would make this fit again
                    break
            cost = lam1 * t1 * t1 + lam2 * t2 * t2 + pen
            for k in range(n_k):
                if w[k] == 0.0:
                    continue
                if not has[k]:
                    cost += w[k] * clip2
                else:
                    e = r[k] - t1 * uc[k] - t2 * us[k]
                    cost += min(pw[k] * e * e, w[k] * clip2)
            if cost < best:
                best = cost
                best_h = h
                b1 = t1
                b2 = t2
        out_cost[ii] = best
        out_shift[ii] = best_h
        out_t[ii, 0] = b1
        out_t[ii, 1] = b2


def relative_on_lattice(relative_azimuth_deg: np.ndarray, elevation_deg: np.ndarray, weights: np.ndarray,
                        step_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The photo's skyline on the lattice of relative azimuths ``k * step_deg``: lattice indices
    (may be negative), elevations and weights (linear between the columns; missing across gaps)."""
    rel = np.asarray(relative_azimuth_deg, dtype=np.float64)
    el = np.asarray(elevation_deg, dtype=np.float64)
    wt = np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(rel) & np.isfinite(el) & (wt > 0)
    if ok.sum() < 2:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    rel, el, wt = rel[ok], el[ok], wt[ok]
    order = np.argsort(rel)
    rel, el, wt = rel[order], el[order], wt[order]
    k = np.arange(math.ceil(rel[0] / step_deg), math.floor(rel[-1] / step_deg) + 1, dtype=np.int64)
    q = k * step_deg
    hi = np.clip(np.searchsorted(rel, q), 1, rel.size - 1)
    lo = hi - 1
    span = rel[hi] - rel[lo]
    t = np.where(span > 0, (q - rel[lo]) / np.where(span > 0, span, 1.0), 0.0)
    e = el[lo] * (1 - t) + el[hi] * t
    wk = np.minimum(wt[lo], wt[hi])
    gap = span > 2.0 * step_deg
    return k[~gap], e[~gap], wk[~gap]


def screen(codes: np.ndarray, offset_deg: np.ndarray, step_deg: np.ndarray, nodes: np.ndarray,
           lattice: np.ndarray, elevation_deg: np.ndarray, weights: np.ndarray, tilt_bound_deg: tuple[float, float],
           noise_deg: float = 0.3, yaw_deg: tuple[float, float] | None = None, clip_deg: float = CLIP_DEG,
           rounds: int = 3, parallax: tuple[np.ndarray, int, np.ndarray, np.ndarray] | None = None,
           relative_deg: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every node of ``nodes`` scored at every yaw: the robust cost (deg^2), the yaw (deg, a multiple
    of the database's azimuth step) and the tilt terms (deg, (n, 2)) of its best fit.

    ``lattice``, ``elevation_deg``, ``weights``: the photo's skyline on the relative-azimuth lattice
    (:func:`relative_on_lattice`, in steps of 360 / n_az).  ``tilt_bound_deg``: the bounds of |t1|
    and |t2| (the level's tolerance); half of each is the prior's sigma, against measurements of
    ``noise_deg``.  ``yaw_deg`` = (centre, half-width) bounds the
    yaw (a compass); None searches every yaw.  A node that sees terrain at fewer than MIN_SEEN_SHARE
    of the measurements costs inf.  ``parallax``: the nodes' tau^2 codes over runs of ``stride``
    azimuths and the tables of each code's weight sigma^2 / (sigma^2 + tau^2) and normaliser
    log(1 + tau^2 / sigma^2) (``parallax.tau2_tables`` at ``noise_deg``): each residual then counts
    as the parallax model says a node's cell blurs it; None weighs all alike.  ``relative_deg``: the
    relative azimuth of each lattice sample for the tilt's terms (default: its lattice position)."""
    n_az = codes.shape[1]
    az_step = 360.0 / n_az
    rel = lattice * az_step if relative_deg is None else np.asarray(relative_deg, np.float64)
    uc, us = np.cos(np.radians(rel)), np.sin(np.radians(rel))
    if yaw_deg is None:
        shifts = np.arange(n_az, dtype=np.int64)
    else:
        centre, half = yaw_deg
        lo = math.floor((centre - half) / az_step)
        hi = math.ceil((centre + half) / az_step)
        shifts = np.unique(np.mod(np.arange(lo, hi + 1), n_az)).astype(np.int64)
    lam1 = (2.0 * noise_deg / max(tilt_bound_deg[0], 1e-3)) ** 2
    lam2 = (2.0 * noise_deg / max(tilt_bound_deg[1], 1e-3)) ** 2
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    cost = np.empty(nodes.size)
    shift = np.empty(nodes.size, dtype=np.int64)
    tilt = np.empty((nodes.size, 2))
    if parallax is None:
        tau = (np.zeros((0, 1), np.uint8), 1, np.ones(256, np.float32), np.zeros(256, np.float32))
    else:
        tau = parallax
    _screen(codes, np.asarray(offset_deg, np.float64), np.asarray(step_deg, np.float64), nodes,
            np.asarray(elevation_deg, np.float64), np.asarray(weights, np.float64),
            np.mod(lattice, n_az).astype(np.int64), uc, us, shifts, tau[0], tau[1], tau[2], tau[3], noise_deg**2,
            lam1, lam2, tilt_bound_deg[0], tilt_bound_deg[1],
            clip_deg**2, rounds,
            MIN_SEEN_SHARE, cost, shift, tilt)
    return cost, shift * az_step, tilt


def same_hypothesis(r: float, c: float, yaw_deg: float, h: Hypothesis, n_cols: int) -> bool:
    """Whether a node at (``r``, ``c``) with ``yaw_deg`` is the same answer as ``h``: within
    SAME_HYPOTHESIS_CELLS of its node at a yaw within SAME_HYPOTHESIS_YAW_DEG of its."""
    hr, hc = divmod(h.node, n_cols)
    dyaw = abs((yaw_deg - h.yaw_deg + 180.0) % 360.0 - 180.0)
    return math.hypot(r - hr, c - hc) <= SAME_HYPOTHESIS_CELLS and dyaw <= SAME_HYPOTHESIS_YAW_DEG


def distinct_hypotheses(nodes: np.ndarray, cost: np.ndarray, yaw_deg: np.ndarray, tilt_deg: np.ndarray,
                        n_cols: int, count: int) -> list[Hypothesis]:
    """The ``count`` best nodes of a screening that are distinct places or orientations: a node
    that is the :func:`same_hypothesis` as a better one is not."""
    order = np.argsort(cost, kind="stable")
    chosen: list[Hypothesis] = []
    for i in order:
        if not np.isfinite(cost[i]):
            break
        node = int(nodes[i])
        r, c = divmod(node, n_cols)
        if not any(same_hypothesis(r, c, float(yaw_deg[i]), h, n_cols) for h in chosen):
            chosen.append(Hypothesis(node, float(yaw_deg[i]) % 360.0, float(tilt_deg[i, 0]), float(tilt_deg[i, 1]),
                                     float(cost[i])))
            if len(chosen) == count:
                break
    return chosen


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _linearised_tilt_fit(codes: np.ndarray, dist: np.ndarray, offset: np.ndarray, step: np.ndarray,
                         ge: np.ndarray, gn: np.ndarray, gamma_deg: np.ndarray, jj: np.ndarray, m: np.ndarray,
                         wj: np.ndarray, uc: np.ndarray, us: np.ndarray, rows: np.ndarray, shifts: np.ndarray,
                         tilt0: np.ndarray, rho2: float, inv_d2: np.ndarray, sig2: float, lin2: float,
                         offset_prior_m2: float, heading_prior_deg2: float, tilt_prior_deg2: float, cap: float,
                         map2: float, out: np.ndarray, delta: np.ndarray) -> None:
    n_az = codes.shape[1]
    az_step = 360.0 / n_az
    sin_az = np.empty(n_az)
    cos_az = np.empty(n_az)
    for j in range(n_az):
        sin_az[j] = math.sin(j * az_step / parallax.DEG)
        cos_az[j] = math.cos(j * az_step / parallax.DEG)
    n_t = jj.size
    for r in numba.prange(rows.size):
        i = rows[r]
        o = offset[i]
        st = step[i]
        for q in range(6):
            delta[r, q] = 0.0
        if math.isnan(o):
            out[r] = np.inf
            continue
        sg = math.sin(gamma_deg[i] / parallax.DEG)
        cg = math.cos(gamma_deg[i] / parallax.DEG)
        g2 = ge[i] * ge[i] + gn[i] * gn[i]
        A = np.zeros((6, 6))
        b = np.zeros(6)
        row = np.zeros(6)
        prow = np.zeros(4)
        rr = 0.0
        pen = 0.0
        occ = 0.0
        cnt = 0
        sh = shifts[r] % n_az
        for t in range(n_t):
            idx = (jj[t] + sh) % n_az
            c = codes[i, idx]
            if c == MISSING_CODE or wj[t] == 0.0:
                continue
            cnt += 1
            e_deg = o + st * c
            res = m[t] - tilt0[r, 0] * uc[t] - tilt0[r, 1] * us[t] - e_deg
            t2 = lin2 * parallax.tau2_at(codes, dist, i, idx, n_az, o, st, az_step, g2, rho2, inv_d2)
            t2 += parallax.map_var_at(dist, i, idx, map2, inv_d2)
            w = variance_weight(sig2, t2)
            pen += wj[t] * sig2 * variance_log_normaliser(sig2, t2)
            if is_occluded(res, w * res * res, cap):
                occ += wj[t]
                continue
            w *= wj[t]
            parallax.parallax_row(codes, dist, inv_d2, i, idx, st, e_deg, sin_az, cos_az, sg, cg, ge[i], gn[i], prow)
            for u in range(4):
                row[u] = prow[u]
            row[4] = uc[t]
            row[5] = us[t]
            for u in range(6):
                b[u] += w * row[u] * res
                for v in range(6):
                    A[u, v] += w * row[u] * row[v]
            rr += w * res * res
        if cnt < MIN_SEEN_SHARE * n_t or cnt == 0:
            out[r] = np.inf
            continue
        parallax.add_move_prior(A, sig2, g2, offset_prior_m2, heading_prior_deg2)
        A[4, 4] += sig2 / tilt_prior_deg2
        A[5, 5] += sig2 / tilt_prior_deg2
        x = np.linalg.solve(A, b)
        for q in range(6):
            delta[r, q] = x[q]
        fit = 0.0
        for q in range(6):
            fit += b[q] * x[q]
        out[r] = (max(rr - fit, 0.0) + pen + occ * cap) * n_t / cnt


def linearised_screen(grid_codes: np.ndarray, distance_codes: np.ndarray, offset_deg: np.ndarray,
                      step_deg: np.ndarray, ground_gradient: tuple[np.ndarray, np.ndarray], gamma_deg: np.ndarray,
                      nodes: np.ndarray, yaw_deg: np.ndarray, tilt_deg: np.ndarray, lattice: np.ndarray,
                      elevation_deg: np.ndarray, weights: np.ndarray, rho2_m2: float, inverse_range2: np.ndarray,
                      cell_half_m: float, noise_deg: float, tilt_sigma_deg: float, cap_deg2: float,
                      map_sigma_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Each screened node at its yaw moved within its cell by the first-order parallax model
    (``parallax.linearised_fit``'s move: east, north, heading, eye height) with the tilt refined
    from ``tilt_deg`` (two more linear terms): the cost (deg^2 at ``noise_deg``, with the wider
    Gaussians' normaliser and the occluded azimuths at the cap) and the move (n, 6: east m,
    north m, heading deg, eye m, t1 deg, t2 deg).  What the coarse screening misses between nodes,
    where a camera near the ground sees the terrain beside it move by degrees, this recovers."""
    n_az = grid_codes.shape[1]
    az_step = 360.0 / n_az
    rel = np.radians(lattice * az_step)
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    shifts = np.round(np.asarray(yaw_deg) / az_step).astype(np.int64)
    out = np.empty(nodes.size)
    delta = np.empty((nodes.size, 6))
    ge, gn = ground_gradient
    _linearised_tilt_fit(grid_codes, distance_codes, np.asarray(offset_deg, np.float64),
                         np.asarray(step_deg, np.float64), ge, gn, np.asarray(gamma_deg, np.float64),
                         np.mod(lattice, n_az).astype(np.int64), np.asarray(elevation_deg, np.float64),
                         np.asarray(weights, np.float64), np.cos(rel), np.sin(rel), nodes, shifts,
                         np.ascontiguousarray(tilt_deg, np.float64), rho2_m2, inverse_range2, noise_deg**2,
                         parallax.LINEARISED_SCALE**2, cell_half_m**2, az_step**2, tilt_sigma_deg**2, cap_deg2,
                         map_sigma_m**2, out, delta)
    return out, delta
