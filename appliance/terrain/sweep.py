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

With a maximum range the horizon of a node comes from exactly the points of its line at most
``range_columns(max_range_m, step_m)`` columns ahead, so it depends on the terrain within range
only, not on how far the grid extends: a map built in tiles, each with a halo of the maximum range,
equals a build of the whole map node for node (see
:func:`appliance.terrain._sweep_kernels._sweep_canonical_cut`).
"""

from __future__ import annotations

import math
import threading

import numpy as np

from appliance.errors import InputError
from appliance.terrain._sweep_kernels import _near_field, _sweep_canonical, _sweep_canonical_cut

#: Near-field samples on the exact ray (columns ahead): a horizon a cell away moves by degrees
#: within a cell, so the near field is sampled at tenths of a column.
NEAR_FIELD_FRACTIONS = np.concatenate([np.arange(1, 11) * 0.1, [1.25, 1.5, 1.75, 2.0]])
NEAR_FIELD_COLUMNS = 2
#: Canonical terrain copies a sweeper keeps (``HorizonSweeper._view``).
CACHED_VIEWS = 2
#: Rows between neighbouring sweep lines: a node is at most half of it beside its line.
LINE_SPACING_ROWS = 0.5
#: The shortest maximum range, in grid diagonals (the longest step between columns of a line):
#: the near field's samples and at least one swept column beyond them lie within range along
#: every azimuth.
MIN_RANGE_CELLS = NEAR_FIELD_COLUMNS + 1


def range_columns(max_range_m: float, step_m: float) -> int:
    """Columns of a sweep line within ``max_range_m``: floor(max_range_m / step_m), with
    ``step_m`` the distance along the line between neighbouring columns.

    A node sees the line's points at most this many columns ahead.  The step depends only on the
    grid's spacing and the azimuth, so every window of a lattice (every tile of a map) computes the
    same count; -1 for an infinite range (no cut-off)."""
    q = max_range_m / step_m
    if math.isinf(q):
        return -1
    return int(math.floor(q))


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

    ``max_range_m`` cuts the horizon off: a node sees the points of its line at most
    :func:`range_columns` columns ahead (at most ``max_range_m`` away) and nothing beyond, so its
    horizon depends only on the terrain within range.  Where no two nodes of the lattice on a line
    are farther apart than that (always with the default infinite range), nothing is cut and the
    plain sweep runs, with results bit-identical to a sweep without a cut-off.
    """

    def __init__(self, elevation_m: np.ndarray, dx_m: float, dy_m: float, height_m: float, r_eff_m: float,
                 window: tuple[int, int, int, int] | None = None,
                 lattice_origin: tuple[int, int] = (0, 0), lattice_shape: tuple[int, int] | None = None,
                 max_range_m: float = math.inf):
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
        self.max_range_m = float(max_range_m)
        # the step along a line is at most the grid's diagonal, so this bounds every azimuth's columns
        shortest = MIN_RANGE_CELLS * math.hypot(self.dx_m, self.dy_m)
        if not self.max_range_m >= shortest:
            raise InputError(f"maximum range {max_range_m} m below {MIN_RANGE_CELLS} grid diagonals "
                             f"({shortest:.1f} m): the horizon's near field ({NEAR_FIELD_COLUMNS} cells) "
                             f"would reach beyond it; use a longer range or a finer grid")
        self._canonical: dict[tuple[bool, bool, bool], np.ndarray] = {}
        self._lock = threading.Lock()
        self._local = threading.local()

    def _view(self, key: tuple[bool, bool, bool]) -> np.ndarray:
        """The canonical copy of the terrain for one orientation.  Each orientation serves a run of 45
        degrees of azimuth, and builds sweep azimuths in order, so only the last CACHED_VIEWS copies
        are kept: a tile's terrain is copied a few times, not eight (a thread still sweeping an evicted
        orientation keeps its copy until it is done)."""
        with self._lock:
            W = self._canonical.get(key)
            if W is None:
                W = np.ascontiguousarray(_orient(self.Z, *key))
                self._canonical[key] = W
                while len(self._canonical) > CACHED_VIEWS:
                    del self._canonical[next(iter(self._canonical))]
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
        range_cols = range_columns(self.max_range_m, step)
        # the lattice's extent along the line: a cut-off at least that long cuts nothing
        lattice_cols = self.lattice_shape[0] if transpose else self.lattice_shape[1]
        if range_cols < 0 or range_cols >= lattice_cols - 1:
            _sweep_canonical(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_COLUMNS,
                             LINE_SPACING_ROWS, hs, hz, v0, u0, voff, uoff)
        else:
            _sweep_canonical_cut(W, out, far, tau, step, self.height_m, self.r_eff_m, NEAR_FIELD_COLUMNS,
                                 range_cols, LINE_SPACING_ROWS, hs, hz, v0, u0, voff, uoff)
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
