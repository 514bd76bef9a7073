"""The compiled kernels of :mod:`appliance.terrain.sweep`: the line sweep with its upper hull, the
sweep with a cut-off at the maximum range, and the near field sampled on the exact ray.

Every kernel works on a canonical view of the grid, ``W[v, u]``: lines run along increasing ``u``
(ahead) and rise by ``tau`` rows per column.  Hulls live in the caller's buffers ``hs`` (distance
along the line) and ``hz`` (height lowered by the curvature, Z = z - s^2 / (2 R_eff)).
"""

from __future__ import annotations

import math

import numba
import numpy as np

import appliance.numerics  # noqa: F401  (scipy's BLAS and LAPACK for numba without scipy.linalg)


@numba.njit(cache=True, inline="always")
def _tangent(hs: np.ndarray, hz: np.ndarray, n: int, s: float, zo: float) -> int:
    """Index of the hull vertex of steepest slope from (s, zo); vertex n-1 is the nearest.

    Slopes from a point left of an upper hull rise from the near end to the tangent, then fall:
    gallop from the near end, then bisect.
    """
    hi = n - 1
    gap = 1
    lo = hi
    while True:
        cand = hi - gap
        if cand < 0:
            lo = 0
            break
        # compare slopes to cand and cand+1 by cross-multiplication (distances are positive)
        if (hz[cand] - zo) * (hs[cand + 1] - s) >= (hz[cand + 1] - zo) * (hs[cand] - s):
            hi = cand
            gap *= 2
        else:
            lo = cand
            break
    # the peak lies in [lo, hi]; slopes rise with decreasing index up to it
    while lo < hi:
        mid = (lo + hi) // 2
        if (hz[mid] - zo) * (hs[mid + 1] - s) >= (hz[mid + 1] - zo) * (hs[mid] - s):
            hi = mid
        else:
            lo = mid + 1
    return hi


@numba.njit(cache=True, inline="always")
def _push_behind(hs: np.ndarray, hz: np.ndarray, n: int, si: float, zp: float) -> int:
    """Push the point (si, zp) onto an upper hull of n vertices grown at its near end (vertex n-1 is
    the nearest, as the sweep from the far end builds it); returns the new vertex count."""
    while n >= 2:
        # drop the top vertex if on or under the segment from the new point to the next
        if (hz[n - 1] - zp) * (hs[n - 2] - si) <= (hz[n - 2] - zp) * (hs[n - 1] - si):
            n -= 1
        else:
            break
    hs[n] = si
    hz[n] = zp
    return n + 1


@numba.njit(cache=True, nogil=True)
def _sweep_canonical(
    W: np.ndarray,
    out: np.ndarray,
    far: np.ndarray,
    tau: float,
    step_m: float,
    height_m: float,
    r_eff: float,
    delay: int,
    spacing: float,
    hs: np.ndarray,
    hz: np.ndarray,
    v0: int,
    u0: int,
    voff: int,
    uoff: int,
) -> None:
    """Lines V = k*spacing + U*tau (0 <= tau <= 1) over W[v, u]; ahead is increasing u.

    (V, U) = (v + voff, u + uoff) are the lattice's coordinates: the lines, and which node each
    serves, are those of the whole lattice, whatever window of it W is.  ``out`` and ``far`` cover
    the nodes v0 <= v < v0 + out.shape[0], u0 <= u < u0 + out.shape[1]; only the lines through them
    are swept, and only from the far end to the window.

    A node takes its far-field horizon from the nearest line (at most spacing/2 rows away) and only
    from terrain at least ``delay`` columns ahead: the line's points enter the hull ``delay``
    columns late, leaving the near field to the exact ray samples of :func:`_near_field`.
    """
    nv, nu = W.shape
    wv, wu = out.shape
    v1 = v0 + wv
    u1 = u0 + wu
    kmin = int(math.floor((v0 + voff - 1 - (u1 - 1 + uoff) * tau) / spacing)) - 2
    kmax = int(math.ceil((v1 + voff - (u0 + uoff) * tau) / spacing)) + 2
    inv2r = 0.5 / r_eff
    for k in range(kmin, kmax + 1):
        n = 0
        for u in range(nu - 1, u0 - 1, -1):
            # enter the point of column u + delay into the hull
            ui = u + delay
            if ui <= nu - 1:
                vg = spacing * k + (ui + uoff) * tau
                if voff <= vg <= voff + nv - 1:
                    ag = int(math.floor(vg))
                    a = ag - voff
                    if a >= nv - 1:
                        z = W[nv - 1, ui]
                    else:
                        f = vg - ag
                        z = W[a, ui] * (1.0 - f) + W[a + 1, ui] * f
                    if not math.isnan(z):
                        si = ui * step_m
                        n = _push_behind(hs, hz, n, si, z - si * si * inv2r)
            if u >= u1:
                continue
            vg = spacing * k + (u + uoff) * tau
            if vg < v0 + voff - 0.5:
                break
            rg = int(math.floor(vg + 0.5))
            rn = rg - voff
            if rn < v0 or rn >= v1 or int(math.floor((rg - (u + uoff) * tau) / spacing + 0.5)) != k:
                continue
            zn = W[rn, u]
            if n == 0 or math.isnan(zn):
                continue
            s = u * step_m
            zo = zn + height_m - s * s * inv2r
            t = _tangent(hs, hz, n, s, zo)
            out[rn - v0, u - u0] = (hz[t] - zo) / (hs[t] - s) + s / r_eff
            far[rn - v0, u - u0] = hs[t] - s


@numba.njit(cache=True, inline="always")
def _tangent_ahead(hs: np.ndarray, hz: np.ndarray, n: int, s: float, zo: float) -> int:
    """Index of the hull vertex of steepest slope from (s, zo) on a hull whose vertex 0 is the
    nearest (a hull grown at its far end); the mirror of :func:`_tangent`.

    Slopes rise from the near end to the tangent, then fall: gallop up from vertex 0, then bisect.
    Among equal slopes the farthest vertex is taken, as :func:`_tangent` does.
    """
    lo = 0
    gap = 1
    hi = lo
    while True:
        cand = lo + gap
        if cand > n - 1:
            hi = n - 1
            break
        # slope to cand at least that to cand-1 (distances are positive)
        if (hz[cand] - zo) * (hs[cand - 1] - s) >= (hz[cand - 1] - zo) * (hs[cand] - s):
            lo = cand
            gap *= 2
        else:
            hi = cand
            break
    # the peak lies in [lo, hi]; slopes rise with increasing index up to it
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if (hz[mid] - zo) * (hs[mid - 1] - s) >= (hz[mid - 1] - zo) * (hs[mid] - s):
            lo = mid
        else:
            hi = mid - 1
    return lo


@numba.njit(cache=True, inline="always")
def _line_height(W: np.ndarray, vg: float, ui: int, voff: int) -> float:
    """Terrain of column ``ui`` on the line at lattice row ``vg``, linear between the two rows it
    crosses; NaN outside the grid's rows (as :func:`_sweep_canonical` reads it)."""
    nv = W.shape[0]
    if not voff <= vg <= voff + nv - 1:
        return math.nan
    ag = int(math.floor(vg))
    a = ag - voff
    if a >= nv - 1:
        return W[nv - 1, ui]
    f = vg - ag
    return W[a, ui] * (1.0 - f) + W[a + 1, ui] * f


@numba.njit(cache=True, inline="always")
def _push_ahead(hs: np.ndarray, hz: np.ndarray, n: int, si: float, zp: float) -> int:
    """Push the point (si, zp) onto an upper hull of n vertices grown at its far end (vertex 0 is the
    nearest); the mirror of :func:`_push_behind`.  Returns the new vertex count."""
    while n >= 2:
        # drop the top vertex if on or under the segment from the previous one to the new point
        if (hz[n - 1] - zp) * (hs[n - 2] - si) >= (hz[n - 2] - zp) * (hs[n - 1] - si):
            n -= 1
        else:
            break
    hs[n] = si
    hz[n] = zp
    return n + 1


@numba.njit(cache=True, inline="always")
def _served_row(k: int, u: int, spacing: float, tau: float, v0: int, v1: int, voff: int, uoff: int) -> int:
    """The window's row of the node at column ``u`` that line ``k`` serves (the line nearest to
    it), or -1 when line k serves no node of the window there."""
    vg = spacing * k + (u + uoff) * tau
    rg = int(math.floor(vg + 0.5))
    rn = rg - voff
    if rn < v0 or rn >= v1 or int(math.floor((rg - (u + uoff) * tau) / spacing + 0.5)) != k:
        return -1
    return rn


@numba.njit(cache=True, inline="always")
def _line_columns(k: int, tau: float, spacing: float, v0: int, v1: int, u0: int, u1: int, voff: int,
                  uoff: int) -> tuple[float, float]:
    """The first and last column where line k may serve a node of the window (a column of margin
    for rounding); the first lies beyond the last when it serves none."""
    lo_f = float(u0)
    hi_f = float(u1 - 1)
    if tau > 0.0:
        # clamped before rounding: a line nearly along the rows gives huge quotients
        x = min(max((v0 + voff - 0.5 - spacing * k) / tau - uoff, u0 - 2.0), u1 + 2.0)
        lo_f = max(lo_f, math.floor(x) - 1.0)
        x = min(max((v1 + voff - 0.5 - spacing * k) / tau - uoff, u0 - 2.0), u1 + 2.0)
        hi_f = min(hi_f, math.ceil(x) + 1.0)
    return lo_f, hi_f


@numba.njit(cache=True, nogil=True)
def _cut_suffix(
    W: np.ndarray, out: np.ndarray, far: np.ndarray, tau: float, step_m: float, height_m: float, r_eff: float,
    inv2r: float, delay: int, blk: int, spacing: float, hs: np.ndarray, hz: np.ndarray, k: int, ufirst: int,
    ulast: int, v0: int, u0: int, voff: int, uoff: int,
) -> None:
    """The suffixes of :func:`_sweep_canonical_cut` along line k: from the end of the block holding
    ulast's first point towards the near end, the hull emptied at each block's end; sets the
    horizons of the nodes at columns ufirst..ulast that the line serves."""
    nu = W.shape[1]
    v1 = v0 + out.shape[0]
    e_last = ulast + delay + uoff
    n = 0
    jcur = e_last // blk
    for u in range(min(nu - 1, ulast + blk - 1 - e_last % blk), ufirst - 1, -1):
        ui = u + delay
        j = (ui + uoff) // blk
        if j != jcur:
            n = 0
            jcur = j
        if ui <= nu - 1:
            z = _line_height(W, spacing * k + (ui + uoff) * tau, ui, voff)
            if not math.isnan(z):
                si = (ui + uoff) * step_m
                n = _push_behind(hs, hz, n, si, z - si * si * inv2r)
        if u > ulast:
            continue
        rn = _served_row(k, u, spacing, tau, v0, v1, voff, uoff)
        if rn < 0:
            continue
        zn = W[rn, u]
        if n == 0 or math.isnan(zn):
            continue
        s = (u + uoff) * step_m
        zo = zn + height_m - s * s * inv2r
        t = _tangent(hs, hz, n, s, zo)
        out[rn - v0, u - u0] = (hz[t] - zo) / (hs[t] - s) + s / r_eff
        far[rn - v0, u - u0] = hs[t] - s


@numba.njit(cache=True, nogil=True)
def _cut_prefix(
    W: np.ndarray, out: np.ndarray, far: np.ndarray, tau: float, step_m: float, height_m: float, r_eff: float,
    inv2r: float, delay: int, blk: int, spacing: float, hs: np.ndarray, hz: np.ndarray, k: int, ufirst: int,
    ulast: int, v0: int, u0: int, voff: int, uoff: int,
) -> None:
    """The prefixes of :func:`_sweep_canonical_cut` along line k: from the start of the block holding
    ufirst's first point towards the far end, the next block's points pushed onto a hull grown at
    its far end; raises the horizons :func:`_cut_suffix` set where the prefix's tangent is steeper."""
    nu = W.shape[1]
    v1 = v0 + out.shape[0]
    n = 0
    for u in range(ufirst - (ufirst + delay + uoff) % blk, ulast + 1):
        r = (u + delay + uoff) % blk
        if r == 0:
            n = 0
        else:
            # the next block's point that comes into range of the node at u
            ui = u + delay + blk - 1
            if 0 <= ui <= nu - 1:
                z = _line_height(W, spacing * k + (ui + uoff) * tau, ui, voff)
                if not math.isnan(z):
                    si = (ui + uoff) * step_m
                    n = _push_ahead(hs, hz, n, si, z - si * si * inv2r)
        if u < ufirst or n == 0:
            continue
        rn = _served_row(k, u, spacing, tau, v0, v1, voff, uoff)
        if rn < 0:
            continue
        zn = W[rn, u]
        if math.isnan(zn):
            continue
        s = (u + uoff) * step_m
        zo = zn + height_m - s * s * inv2r
        t = _tangent_ahead(hs, hz, n, s, zo)
        tan = (hz[t] - zo) / (hs[t] - s) + s / r_eff
        b = out[rn - v0, u - u0]
        if tan >= b or math.isnan(b):
            out[rn - v0, u - u0] = tan
            far[rn - v0, u - u0] = hs[t] - s


@numba.njit(cache=True, nogil=True)
def _sweep_canonical_cut(
    W: np.ndarray,
    out: np.ndarray,
    far: np.ndarray,
    tau: float,
    step_m: float,
    height_m: float,
    r_eff: float,
    delay: int,
    range_cols: int,
    spacing: float,
    hs: np.ndarray,
    hz: np.ndarray,
    v0: int,
    u0: int,
    voff: int,
    uoff: int,
) -> None:
    """:func:`_sweep_canonical` with a cut-off: a node at column u sees exactly the line's points
    at columns u + delay ... u + range_cols, whatever lies beyond them in the grid.

    Each line is cut into blocks of B = range_cols - delay + 1 columns (the length of a node's
    window), aligned on the lattice's columns.  The window [e, e + B - 1] of a node whose first
    point is e is the suffix of e's block from e plus a prefix of the next block.  The suffix comes
    from the plain sweep from the far end with the hull emptied at each block's end; the prefix from
    a sweep of the nodes towards the far end that pushes the next block's points, in increasing
    distance, onto a second hull (an upper hull grown at its far end is a stack too).  The horizon
    is the steeper of the two tangents, with the distance of its point.  Each point is pushed at
    most twice, so a line costs O(N log B).

    Distances are taken from the lattice's column 0 and the blocks are the lattice's, so a node's
    arithmetic is the same whichever window of the lattice W is: its horizon is bit-identical as
    long as W holds the terrain within range of it.
    """
    wv, wu = out.shape
    v1 = v0 + wv
    u1 = u0 + wu
    blk = range_cols - delay + 1
    kmin = int(math.floor((v0 + voff - 1 - (u1 - 1 + uoff) * tau) / spacing)) - 2
    kmax = int(math.ceil((v1 + voff - (u0 + uoff) * tau) / spacing)) + 2
    inv2r = 0.5 / r_eff
    for k in range(kmin, kmax + 1):
        lo_f, hi_f = _line_columns(k, tau, spacing, v0, v1, u0, u1, voff, uoff)
        if lo_f > hi_f:
            continue
        ufirst = int(lo_f)
        ulast = int(hi_f)
        _cut_suffix(W, out, far, tau, step_m, height_m, r_eff, inv2r, delay, blk, spacing, hs, hz, k, ufirst, ulast,
                    v0, u0, voff, uoff)
        _cut_prefix(W, out, far, tau, step_m, height_m, r_eff, inv2r, delay, blk, spacing, hs, hz, k, ufirst, ulast,
                    v0, u0, voff, uoff)


@numba.njit(cache=True, nogil=True)
def _near_field(
    W: np.ndarray, out: np.ndarray, far: np.ndarray, tau: float, step_m: float, height_m: float, r_eff: float,
    fractions: np.ndarray, v0: int, u0: int,
) -> None:
    """Raise ``out`` (tangents of the window's nodes, as in :func:`_sweep_canonical`) by terrain
    sampled on the exact ray at fractions of a column step, and set ``far`` to the distance of each
    sample that raised it.

    For one fraction every node's sample sits at the same offset from it, so the bilinear weights
    are shared and the inner loop runs over contiguous memory.
    """
    nv, nu = W.shape
    wv, wu = out.shape
    for fi in range(fractions.size):
        fr = fractions[fi]
        du0 = int(math.floor(fr))
        dv0 = int(math.floor(fr * tau))
        fu = fr - du0
        fv = fr * tau - dv0
        w00 = (1.0 - fu) * (1.0 - fv)
        w01 = fu * (1.0 - fv)
        w10 = (1.0 - fu) * fv
        w11 = fu * fv
        d = fr * step_m
        drop = height_m + d * d * (0.5 / r_eff)
        inv_d = 1.0 / d
        n_u = max(min(u0 + wu, nu - du0 - 1) - u0, 0)
        for v in range(v0, min(v0 + wv, nv - dv0 - 1)):
            # row slices, indexed by range variables: contiguous and vectorisable
            a0 = W[v + dv0, u0 + du0 : u0 + du0 + n_u]
            a1 = W[v + dv0, u0 + du0 + 1 : u0 + du0 + 1 + n_u]
            b0 = W[v + dv0 + 1, u0 + du0 : u0 + du0 + n_u]
            b1 = W[v + dv0 + 1, u0 + du0 + 1 : u0 + du0 + 1 + n_u]
            here = W[v, u0 : u0 + n_u]
            dest = out[v - v0, :n_u]
            dest_far = far[v - v0, :n_u]
            for u in range(n_u):
                z = a0[u] * w00 + a1[u] * w01 + b0[u] * w10 + b1[u] * w11
                t = (z - here[u] - drop) * inv_d
                b = dest[u]
                if t > b or (b != b and t == t):
                    dest[u] = t
                    dest_far[u] = d
