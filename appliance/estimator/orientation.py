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


@numba.njit(cache=True, inline="always", nogil=True, fastmath=FAST_FINITE)
def _fit_at(codes: np.ndarray, node: int, off: float, st: float, h: int, m: np.ndarray, w: np.ndarray,
            k_idx: np.ndarray, uc: np.ndarray, us: np.ndarray, tau_codes: np.ndarray, run: np.ndarray,
            lut_w: np.ndarray, lut_p: np.ndarray, sig2: float, lam1: float, lam2: float, bound1: float, bound2: float,
            clip2: float, rounds: int, least_seen: float, r: np.ndarray, keep: np.ndarray, has: np.ndarray,
            pw: np.ndarray) -> tuple[float, float, float]:
    """The robust tilt fit of one node at one yaw shift ``h``: (cost, t1, t2), cost inf where the node
    sees terrain at less than ``least_seen`` of the weight.  ``r``, ``keep``, ``has``, ``pw``: scratch."""
    n_az = codes.shape[1]
    n_k = m.size
    use_tau = tau_codes.shape[0] > 0
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
    if seen < least_seen:
        return np.inf, 0.0, 0.0
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
    return cost, t1, t2


@numba.njit(cache=True, inline="always", nogil=True, fastmath=FAST_FINITE)
def _best_fit(codes: np.ndarray, node: int, off: float, st: float, hs: np.ndarray, n_hs: int, m: np.ndarray,
              w: np.ndarray, k_idx: np.ndarray, uc: np.ndarray, us: np.ndarray, tau_codes: np.ndarray, run: np.ndarray,
              lut_w: np.ndarray, lut_p: np.ndarray, sig2: float, lam1: float, lam2: float, bound1: float,
              bound2: float, clip2: float, rounds: int, least_seen: float, r: np.ndarray, keep: np.ndarray,
              has: np.ndarray, pw: np.ndarray) -> tuple[float, int, float, float]:
    """:func:`_fit_at` at the yaw shifts ``hs[:n_hs]`` in turn: the least cost (the first of equal ones), its
    shift and its tilt terms (inf, -1, 0, 0 where none sees enough terrain)."""
    best = np.inf
    best_h = -1
    b1 = 0.0
    b2 = 0.0
    for i in range(n_hs):
        h = hs[i]
        cost, t1, t2 = _fit_at(codes, node, off, st, h, m, w, k_idx, uc, us, tau_codes, run, lut_w, lut_p, sig2,
                               lam1, lam2, bound1, bound2, clip2, rounds, least_seen, r, keep, has, pw)
        if cost < best:
            best = cost
            best_h = h
            b1 = t1
            b2 = t2
    return best, best_h, b1, b2


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
        r = np.empty(n_k)
        keep = np.empty(n_k)
        has = np.empty(n_k, dtype=np.bool_)
        pw = np.empty(n_k)
        best, best_h, b1, b2 = _best_fit(codes, node, off, st, shifts, shifts.size, m, w, k_idx, uc, us, tau_codes,
                                         run, lut_w, lut_p, sig2, lam1, lam2, bound1, bound2, clip2, rounds,
                                         min_seen * w_total, r, keep, has, pw)
        out_cost[ii] = best
        out_shift[ii] = best_h
        out_t[ii, 0] = b1
        out_t[ii, 1] = b2


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _screen_kept(codes: np.ndarray, offset: np.ndarray, step: np.ndarray, nodes: np.ndarray, m: np.ndarray,
                 w: np.ndarray, k_idx: np.ndarray, uc: np.ndarray, us: np.ndarray, shifts: np.ndarray,
                 m_d: np.ndarray, w_d: np.ndarray, uc_d: np.ndarray, us_d: np.ndarray, first: int, lam1: float,
                 lam2: float, bound1: float, bound2: float, clip2: float, rounds: int, min_seen: float, kept: int,
                 out_cost: np.ndarray, out_shift: np.ndarray, out_t: np.ndarray) -> None:
    n_az = codes.shape[1]
    n_k = m.size
    n_h = shifts.size  # shifts[g] == (shifts[0] + g) % n_az
    n_d = m_d.size
    w_total = 0.0
    for k in range(n_k):
        w_total += w[k]
    run = np.zeros(n_az, dtype=np.int64)
    no_tau = np.zeros((0, 1), dtype=np.uint8)
    no_lut = np.zeros(1, dtype=np.float32)
    # the first round's sums over every measurement (no azimuth missing): the same at every yaw
    c11 = lam1
    c12 = 0.0
    c22 = lam2
    c1 = 0.0
    c2 = 0.0
    for d in range(n_d):
        c11 += w_d[d] * uc_d[d] * uc_d[d]
        c12 += w_d[d] * uc_d[d] * us_d[d]
        c22 += w_d[d] * us_d[d] * us_d[d]
        c1 += w_d[d] * uc_d[d] * m_d[d]
        c2 += w_d[d] * us_d[d] * m_d[d]
    g0 = 0  # the least shift's place: the robust fit's yaws are tried in increasing order, as `_screen` tries them
    for g in range(1, n_h):
        if shifts[g] < shifts[g - 1]:
            g0 = g
    n_chunks = min(nodes.size, 256)
    for ch in numba.prange(n_chunks):
        ee = np.empty(n_h + n_d)
        s11 = np.empty(n_h)
        s12 = np.empty(n_h)
        s22 = np.empty(n_h)
        y1 = np.empty(n_h)
        y2 = np.empty(n_h)
        t1 = np.empty(n_h)
        t2 = np.empty(n_h)
        cost = np.empty(n_h)
        best_g = np.empty(kept, dtype=np.int64)
        best_c = np.empty(kept)
        r = np.empty(n_k)
        keep = np.empty(n_k)
        has = np.empty(n_k, dtype=np.bool_)
        pw = np.empty(n_k)
        hs = np.empty(n_h, dtype=shifts.dtype)
        for ii in range(ch * nodes.size // n_chunks, (ch + 1) * nodes.size // n_chunks):
            node = nodes[ii]
            off = offset[node]
            st = step[node]
            # the node's skyline from the first yaw's first measurement on, ee[g + d] read by yaw g and measurement d
            missing = False
            j = first
            for i in range(n_h + n_d):
                c = codes[node, j]
                missing |= c == MISSING_CODE
                ee[i] = off + st * c
                j += 1
                if j == n_az:
                    j = 0
            n_best = 0
            if missing:
                # azimuths without terrain: every yaw by the robust fit itself
                n_best = n_h
            else:
                # the robust fit at every yaw at once, yaws along the inner loops (which vectorise)
                for g in range(n_h):
                    s11[g] = c11
                    s12[g] = c12
                    s22[g] = c22
                    y1[g] = c1
                    y2[g] = c2
                    t1[g] = 0.0
                    t2[g] = 0.0
                for d in range(n_d):
                    a1 = w_d[d] * uc_d[d]
                    a2 = w_d[d] * us_d[d]
                    for g in range(n_h):
                        y1[g] -= a1 * ee[g + d]
                        y2[g] -= a2 * ee[g + d]
                for rnd in range(rounds):
                    if rnd > 0:
                        for g in range(n_h):
                            s11[g] = lam1
                            s12[g] = 0.0
                            s22[g] = lam2
                            y1[g] = 0.0
                            y2[g] = 0.0
                        for d in range(n_d):
                            a = w_d[d]
                            if a == 0.0:
                                continue
                            u = uc_d[d]
                            v = us_d[d]
                            md = m_d[d]
                            a11 = a * u * u
                            a12 = a * u * v
                            a22 = a * v * v
                            a1 = a * u
                            a2 = a * v
                            for g in range(n_h):
                                res = md - ee[g + d]
                                e = res - t1[g] * u - t2[g] * v
                                q = 1.0 if e * e < clip2 else 0.0
                                s11[g] += a11 * q
                                s12[g] += a12 * q
                                s22[g] += a22 * q
                                y1[g] += a1 * q * res
                                y2[g] += a2 * q * res
                    for g in range(n_h):
                        det = s11[g] * s22[g] - s12[g] * s12[g]
                        f1 = (s22[g] * y1[g] - s12[g] * y2[g]) / det
                        f2 = (s11[g] * y2[g] - s12[g] * y1[g]) / det
                        b1 = min(max(f1, -bound1), bound1)
                        b2 = min(max((y2[g] - s12[g] * b1) / s22[g], -bound2), bound2)
                        b1 = min(max((y1[g] - s12[g] * b2) / s11[g], -bound1), bound1)
                        outside = abs(f1) > bound1 or abs(f2) > bound2
                        t1[g] = b1 if outside else f1
                        t2[g] = b2 if outside else f2
                for g in range(n_h):
                    cost[g] = lam1 * t1[g] * t1[g] + lam2 * t2[g] * t2[g]
                for d in range(n_d):
                    a = w_d[d]
                    if a == 0.0:
                        continue
                    u = uc_d[d]
                    v = us_d[d]
                    md = m_d[d]
                    for g in range(n_h):
                        e = md - ee[g + d] - t1[g] * u - t2[g] * v
                        cost[g] += a * min(e * e, clip2)
                # the `kept` best yaws, by yaw
                for g in range(n_h):
                    cg = cost[g]
                    if n_best == kept and not cg < best_c[kept - 1]:
                        continue
                    i = min(n_best, kept - 1)
                    while i > 0 and cg < best_c[i - 1]:
                        best_c[i] = best_c[i - 1]
                        best_g[i] = best_g[i - 1]
                        i -= 1
                    best_c[i] = cg
                    best_g[i] = g
                    n_best = min(n_best + 1, kept)
                for a_ in range(1, n_best):
                    i = a_
                    gg = best_g[i]
                    while i > 0 and shifts[best_g[i - 1]] > shifts[gg]:
                        best_g[i] = best_g[i - 1]
                        i -= 1
                    best_g[i] = gg
            for b in range(n_best):
                hs[b] = shifts[best_g[b]] if not missing else shifts[(g0 + b) % n_h]
            best, best_h, o1, o2 = _best_fit(codes, node, off, st, hs, n_best, m, w, k_idx, uc, us, no_tau, run,
                                             no_lut, no_lut, 0.0, lam1, lam2, bound1, bound2, clip2, rounds,
                                             min_seen * w_total, r, keep, has, pw)
            out_cost[ii] = best
            out_shift[ii] = best_h
            out_t[ii, 0] = o1
            out_t[ii, 1] = o2


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
           relative_deg: np.ndarray | None = None,
           kept_yaws: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    relative azimuth of each lattice sample for the tilt's terms (default: its lattice position).

    ``kept_yaws``: None fits every yaw of every node by the robust fit one yaw at a time.  A count K
    (parallax None only) makes the same fit at every yaw of a node at once, yaws along the inner loops
    (the sums in another order: costs equal to about 1e-12 deg^2), and the robust fit one yaw at a time
    again at the K yaws that fit best, whose best is the node's answer: a node whose best yaw is among
    them gets the same cost, yaw and tilt as with None, about four times faster.  Nodes that miss
    terrain at some azimuth are fitted one yaw at a time at every yaw."""
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
    if kept_yaws is not None:
        if parallax is not None:
            raise ValueError("the screening's kept yaws are for the unweighted screening (parallax None)")
        if kept_yaws < 1:
            raise ValueError(f"kept_yaws {kept_yaws}: expected at least 1")
        _kept_screen(codes, np.asarray(offset_deg, np.float64), np.asarray(step_deg, np.float64), nodes, lattice,
                     np.asarray(elevation_deg, np.float64), np.asarray(weights, np.float64), uc, us, shifts, lam1,
                     lam2, tilt_bound_deg, clip_deg**2, rounds, kept_yaws, cost, shift, tilt)
        return cost, shift * az_step, tilt
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


def _kept_screen(codes: np.ndarray, offset: np.ndarray, step: np.ndarray, nodes: np.ndarray, lattice: np.ndarray,
                 m: np.ndarray, w: np.ndarray, uc: np.ndarray, us: np.ndarray, shifts: np.ndarray, lam1: float,
                 lam2: float, tilt_bound_deg: tuple[float, float], clip2: float, rounds: int, kept: int,
                 out_cost: np.ndarray, out_shift: np.ndarray, out_t: np.ndarray) -> None:
    """:func:`screen` with ``kept_yaws``: the measurements on the dense lattice from the first (gaps
    weighing 0) and the yaws as one run of shifts from the first, for :func:`_screen_kept`."""
    n_az = codes.shape[1]
    if shifts.size < n_az:
        # a bounded yaw is one run of shifts modulo n_az: start it at its first (it may wrap past 0)
        present = np.zeros(n_az, dtype=bool)
        present[shifts] = True
        start = int(np.flatnonzero(present & ~np.roll(present, 1))[0])
        shifts = np.mod(start + np.arange(shifts.size), n_az).astype(np.int64)
    k_idx = np.mod(lattice, n_az).astype(np.int64)
    if lattice.size == 0:
        out_cost[:] = np.inf
        out_shift[:] = -1
        out_t[:] = 0.0
        return
    if np.unique(k_idx).size != k_idx.size:
        raise ValueError("the screening's kept yaws need one measurement per azimuth of the lattice")
    low = int(lattice.min())
    span = int(lattice.max()) - low + 1
    d = lattice - low
    m_d, w_d, uc_d, us_d = np.zeros(span), np.zeros(span), np.zeros(span), np.zeros(span)
    m_d[d], w_d[d], uc_d[d], us_d[d] = m, w, uc, us
    first = (low + int(shifts[0])) % n_az
    _screen_kept(codes, offset, step, nodes, m, w, k_idx, uc, us, shifts, m_d, w_d, uc_d, us_d, first, lam1, lam2,
                 tilt_bound_deg[0], tilt_bound_deg[1], clip2, rounds, MIN_SEEN_SHARE, kept, out_cost, out_shift, out_t)


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
