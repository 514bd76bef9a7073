"""Horizon of every node of a metric grid along one azimuth, by a line sweep with an upper hull.

For one azimuth the grid is crossed by parallel lines, half a row apart, that run along it.  Each
line is swept from its far end towards its near end while the upper convex hull of the terrain
profile ahead is kept on a stack; the horizon of an observer on the line is the tangent from the
observer to that hull, found by binary search.  Each point is pushed and popped at most once, so
an azimuth costs O(N log H) for N nodes (Dozier-style sweep; Stewart's hull variant).

Curvature and refraction are exact in the parabolic approximation: with s the distance along the
line and Z = z - s^2 / (2 R_eff), the tangent of the elevation from an observer at s_o is
(Z_t - Z_o) / (s_t - s_o) + s_o / R_eff, so the hull is built on (s, Z) once for every observer.

A node takes the horizon of the nearest line through its column, at most a quarter row away from
it, with its own ground height as the eye's base.  Terrain is interpolated linearly between the two
rows that a line crosses in each column (bilinear along the line).
"""

from __future__ import annotations

import math

import numba
import numpy as np


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


@numba.njit(cache=True, parallel=True)
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
    scratch: np.ndarray,
) -> None:
    """Lines v = k*spacing + u*tau (0 <= tau <= 1) over W[v, u]; ahead is increasing u.

    A node takes its far-field horizon from the nearest line (at most spacing/2 rows away) and only
    from terrain at least ``delay`` columns ahead: the line's points enter the hull ``delay``
    columns late, leaving the near field to the exact ray samples of :func:`_near_field`.
    """
    nv, nu = W.shape
    kmin = int(math.floor(-(nu - 1) * tau / spacing)) - 2
    kmax = int(math.ceil(nv / spacing)) + 2
    inv2r = 0.5 / r_eff
    for kk in numba.prange(kmax - kmin + 1):
        k = kmin + kk
        tid = numba.get_thread_id()
        hs = scratch[tid, 0]
        hz = scratch[tid, 1]
        n = 0
        for u in range(nu - 1, -delay - 1, -1):
            # enter the point of column u + delay into the hull
            ui = u + delay
            if ui <= nu - 1:
                vi = spacing * k + ui * tau
                if 0.0 <= vi <= nv - 1:
                    a = int(math.floor(vi))
                    if a >= nv - 1:
                        z = W[nv - 1, ui]
                    else:
                        f = vi - a
                        z = W[a, ui] * (1.0 - f) + W[a + 1, ui] * f
                    if not math.isnan(z):
                        si = ui * step_m
                        zp = z - si * si * inv2r
                        while n >= 2:
                            # drop the top vertex if on or under the segment from the new point to the next
                            if (hz[n - 1] - zp) * (hs[n - 2] - si) <= (hz[n - 2] - zp) * (hs[n - 1] - si):
                                n -= 1
                            else:
                                break
                        hs[n] = si
                        hz[n] = zp
                        n += 1
            if u < 0:
                continue
            v = spacing * k + u * tau
            if v < -0.5:
                break
            rn = int(math.floor(v + 0.5))
            if rn < 0 or rn > nv - 1 or int(math.floor((rn - u * tau) / spacing + 0.5)) != k:
                continue
            zn = W[rn, u]
            if n == 0 or math.isnan(zn):
                continue
            s = u * step_m
            zo = zn + height_m - s * s * inv2r
            t = _tangent(hs, hz, n, s, zo)
            out[rn, u] = (hz[t] - zo) / (hs[t] - s) + s / r_eff
            far[rn, u] = hs[t] - s


@numba.njit(cache=True, parallel=True)
def _near_field(
    W: np.ndarray, out: np.ndarray, far: np.ndarray, tau: float, step_m: float, height_m: float, r_eff: float,
    fractions: np.ndarray,
) -> None:
    """Raise ``out`` (tangents) by terrain sampled on the exact ray at fractions of a column step,
    and set ``far`` to the distance of each sample that raised it.

    For one fraction every node's sample sits at the same offset from it, so the bilinear weights
    are shared and the inner loop runs over contiguous memory.
    """
    nv, nu = W.shape
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
        u_end = nu - du0 - 1
        v_end = nv - dv0 - 1
        n_u = max(u_end, 0)
        for v in numba.prange(max(v_end, 0)):
            # row slices, indexed by range variables: contiguous and vectorisable
            a0 = W[v + dv0, du0 : du0 + n_u]
            a1 = W[v + dv0, du0 + 1 : du0 + 1 + n_u]
            b0 = W[v + dv0 + 1, du0 : du0 + n_u]
            b1 = W[v + dv0 + 1, du0 + 1 : du0 + 1 + n_u]
            here = W[v, :n_u]
            dest = out[v, :n_u]
            dest_far = far[v, :n_u]
            for u in range(n_u):
                z = a0[u] * w00 + a1[u] * w01 + b0[u] * w10 + b1[u] * w11
                t = (z - here[u] - drop) * inv_d
                b = dest[u]
                if t > b or (b != b and t == t):
                    dest[u] = t
                    dest_far[u] = d


#: Near-field samples on the exact ray (columns ahead): a horizon a cell away moves by degrees
#: within a cell, so the near field is sampled at tenths of a column.
NEAR_FIELD_FRACTIONS = np.concatenate([np.arange(1, 11) * 0.1, [1.25, 1.5, 1.75, 2.0]])
NEAR_FIELD_COLUMNS = 2
#: Rows between neighbouring sweep lines: a node is at most half of it beside its line.
LINE_SPACING_ROWS = 0.5


class HorizonSweeper:
    """Horizons of every node of one grid, azimuth after azimuth, reusing its buffers.

    ``elevation_m[row, col]`` is a north-up grid (row increases southwards) with spacing ``dx_m``
    east and ``dy_m`` north.  The kernels march along rows of a canonical view of the grid (the
    azimuth turned into increasing columns, rows rising by at most one per column); the eight
    canonical copies are made once.
    """

    def __init__(self, elevation_m: np.ndarray, dx_m: float, dy_m: float, height_m: float, r_eff_m: float):
        self.Z = np.ascontiguousarray(elevation_m, dtype=np.float64)
        self.dx_m, self.dy_m = float(dx_m), float(dy_m)
        self.height_m, self.r_eff_m = float(height_m), float(r_eff_m)
        self.result = np.full(self.Z.shape, np.nan)
        self.distance_m = np.full(self.Z.shape, np.nan)
        self._canonical: dict[tuple[bool, bool, bool], np.ndarray] = {}
        self._work: dict[tuple[int, int], np.ndarray] = {}
        self._work_far: dict[tuple[int, int], np.ndarray] = {}
        n = max(self.Z.shape) + NEAR_FIELD_COLUMNS + 2
        self._scratch = np.empty((int(numba.config.NUMBA_NUM_THREADS), 2, n))  # type: ignore[attr-defined]

    @staticmethod
    def _orient(a: np.ndarray, transpose: bool, flip_u: bool, flip_v: bool) -> np.ndarray:
        v = a.T if transpose else a
        if flip_u:
            v = v[:, ::-1]
        if flip_v:
            v = v[::-1, :]
        return v

    def tan_grid(self, grid_azimuth_deg: float) -> np.ndarray:
        """Tangent of the horizon elevation at every node along one grid azimuth (clockwise from grid
        north); NaN where the node is nodata or no terrain lies ahead.  The array is the sweeper's
        own buffer, overwritten by the next call; ``distance_m`` then holds the ground distance (m)
        to the terrain point that forms each node's horizon."""
        a = math.radians(grid_azimuth_deg)
        dcol = math.sin(a) / self.dx_m
        drow = -math.cos(a) / self.dy_m
        du, dv, du_m, dv_m = dcol, drow, self.dx_m, self.dy_m
        transpose = abs(drow) > abs(dcol)
        if transpose:
            du, dv, du_m, dv_m = drow, dcol, self.dy_m, self.dx_m
        key = (transpose, du < 0, dv < 0)
        W = self._canonical.get(key)
        if W is None:
            W = np.ascontiguousarray(self._orient(self.Z, *key))
            self._canonical[key] = W
        out = self._work.get(W.shape)
        far = self._work_far.get(W.shape)
        if out is None or far is None:
            out = np.empty(W.shape)
            far = np.empty(W.shape)
            self._work[W.shape] = out
            self._work_far[W.shape] = far
        out.fill(np.nan)
        far.fill(np.nan)
        tau = abs(dv / du)
        step = math.hypot(du_m, tau * dv_m)
        _sweep_canonical(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_COLUMNS,
                         LINE_SPACING_ROWS, self._scratch)
        _near_field(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_FRACTIONS)
        self._orient(self.result, *key)[...] = out
        self._orient(self.distance_m, *key)[...] = far
        return self.result


def horizon_tan_grid(
    elevation_m: np.ndarray,
    dx_m: float,
    dy_m: float,
    grid_azimuth_deg: float,
    height_m: float,
    r_eff_m: float,
) -> np.ndarray:
    """Tangent of the horizon elevation at every node along one grid azimuth (see HorizonSweeper)."""
    return HorizonSweeper(elevation_m, dx_m, dy_m, height_m, r_eff_m).tan_grid(grid_azimuth_deg).copy()
