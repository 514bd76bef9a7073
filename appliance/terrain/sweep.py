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
import threading

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


#: Near-field samples on the exact ray (columns ahead): a horizon a cell away moves by degrees
#: within a cell, so the near field is sampled at tenths of a column.
NEAR_FIELD_FRACTIONS = np.concatenate([np.arange(1, 11) * 0.1, [1.25, 1.5, 1.75, 2.0]])
NEAR_FIELD_COLUMNS = 2
#: Rows between neighbouring sweep lines: a node is at most half of it beside its line.
LINE_SPACING_ROWS = 0.5


def _orient(a: np.ndarray, transpose: bool, flip_u: bool, flip_v: bool) -> np.ndarray:
    v = a.T if transpose else a
    if flip_u:
        v = v[:, ::-1]
    if flip_v:
        v = v[::-1, :]
    return v


def _unorient(a: np.ndarray, transpose: bool, flip_u: bool, flip_v: bool) -> np.ndarray:
    """The inverse of :func:`_orient`: a canonical view back in the grid's rows and columns."""
    if flip_v:
        a = a[::-1, :]
    if flip_u:
        a = a[:, ::-1]
    return a.T if transpose else a


class HorizonSweeper:
    """Horizons of the nodes of a window of one grid, one azimuth per call; calls from several
    threads run in parallel (the kernels release the GIL, and each thread has its own buffers).

    ``elevation_m[row, col]`` is a north-up grid (row increases southwards) with spacing ``dx_m``
    east and ``dy_m`` north.  ``window`` = (row0, col0, n_rows, n_cols) are the nodes whose horizons
    are wanted (default: every node).  The grid is a window of a larger lattice of ``lattice_shape``
    whose node (row, col) is the grid's (row - lattice_origin[0], col - lattice_origin[1]): the
    sweep lines are placed on the lattice, so a node's horizon does not depend on which window of
    the lattice the grid is, as long as it holds the terrain the horizon sees.  The kernels march
    along rows of a canonical view of the grid (the azimuth turned into increasing columns, rows
    rising by at most one per column); the canonical copies are made once each.
    """

    def __init__(self, elevation_m: np.ndarray, dx_m: float, dy_m: float, height_m: float, r_eff_m: float,
                 window: tuple[int, int, int, int] | None = None,
                 lattice_origin: tuple[int, int] = (0, 0), lattice_shape: tuple[int, int] | None = None):
        self.Z = np.ascontiguousarray(elevation_m, dtype=np.float64)
        self.dx_m, self.dy_m = float(dx_m), float(dy_m)
        self.height_m, self.r_eff_m = float(height_m), float(r_eff_m)
        nr, nc = self.Z.shape
        self.window = (0, 0, nr, nc) if window is None else tuple(int(v) for v in window)
        r0, c0, wr, wc = self.window
        if not (0 <= r0 and 0 <= c0 and wr >= 1 and wc >= 1 and r0 + wr <= nr and c0 + wc <= nc):
            raise ValueError(f"window {self.window} outside the grid {self.Z.shape}")
        self.lattice_origin = (int(lattice_origin[0]), int(lattice_origin[1]))
        self.lattice_shape = (nr, nc) if lattice_shape is None else (int(lattice_shape[0]), int(lattice_shape[1]))
        self._canonical: dict[tuple[bool, bool, bool], np.ndarray] = {}
        self._lock = threading.Lock()
        self._local = threading.local()

    def _view(self, key: tuple[bool, bool, bool]) -> np.ndarray:
        with self._lock:
            W = self._canonical.get(key)
            if W is None:
                W = np.ascontiguousarray(_orient(self.Z, *key))
                self._canonical[key] = W
        return W

    def _placement(self, key: tuple[bool, bool, bool]) -> tuple[int, int, int, int, int, int]:
        """The window's first canonical node (v0, u0), its canonical shape, and the lattice offsets
        (voff, uoff) of canonical node (0, 0)."""
        transpose, flip_u, flip_v = key
        nr, nc = self.Z.shape
        r0, c0, wr, wc = self.window
        lr, lc = self.lattice_origin
        NR, NC = self.lattice_shape
        # (axis extent, window start, window size, lattice start, lattice extent) along canonical v and u
        rows = (nr, r0, wr, lr, NR)
        cols = (nc, c0, wc, lc, NC)
        along_v, along_u = (cols, rows) if transpose else (rows, cols)

        def place(axis: tuple[int, int, int, int, int], flip: bool) -> tuple[int, int, int]:
            n, start, size, lat0, lat_n = axis
            if flip:
                return n - start - size, size, (lat_n - 1 - lat0) - (n - 1)
            return start, size, lat0

        v0, wv, voff = place(along_v, flip_v)
        u0, wu, uoff = place(along_u, flip_u)
        return v0, u0, wv, wu, voff, uoff

    def _buffers(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        loc = self._local
        if getattr(loc, "shape", None) != shape:
            n = max(self.Z.shape) + NEAR_FIELD_COLUMNS + 2
            loc.out, loc.far = np.empty(shape), np.empty(shape)
            loc.hs, loc.hz = np.empty(n), np.empty(n)
            loc.shape = shape
        return loc.out, loc.far, loc.hs, loc.hz

    def horizons(self, grid_azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(tangent of the horizon elevation, ground distance (m) to the terrain point that forms
        it) at every node of the window along one grid azimuth (clockwise from grid north); NaN
        where the node is nodata or no terrain lies ahead.  Views of this thread's own buffers,
        overwritten by its next call."""
        a = math.radians(grid_azimuth_deg)
        dcol = math.sin(a) / self.dx_m
        drow = -math.cos(a) / self.dy_m
        du, dv, du_m, dv_m = dcol, drow, self.dx_m, self.dy_m
        transpose = abs(drow) > abs(dcol)
        if transpose:
            du, dv, du_m, dv_m = drow, dcol, self.dy_m, self.dx_m
        key = (transpose, du < 0, dv < 0)
        W = self._view(key)
        v0, u0, wv, wu, voff, uoff = self._placement(key)
        out, far, hs, hz = self._buffers((wv, wu))
        out.fill(np.nan)
        far.fill(np.nan)
        tau = abs(dv / du)
        step = math.hypot(du_m, tau * dv_m)
        _sweep_canonical(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_COLUMNS,
                         LINE_SPACING_ROWS, hs, hz, v0, u0, voff, uoff)
        _near_field(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_FRACTIONS, v0, u0)
        return _unorient(out, *key), _unorient(far, *key)


def horizon_tan_grid(
    elevation_m: np.ndarray,
    dx_m: float,
    dy_m: float,
    grid_azimuth_deg: float,
    height_m: float,
    r_eff_m: float,
) -> np.ndarray:
    """Tangent of the horizon elevation at every node along one grid azimuth (see HorizonSweeper)."""
    return HorizonSweeper(elevation_m, dx_m, dy_m, height_m, r_eff_m).horizons(grid_azimuth_deg)[0].copy()
