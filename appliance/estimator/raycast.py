"""Exact skylines on a metric height grid: a compiled ray march for any viewpoint between nodes.

:class:`Terrain` holds the heights under a node grid (a fine grid near the eye, a coarse outer one
beyond); :func:`render` gives the skyline and the range of each horizon point from any fractional
node, through :func:`march`.

Rays are straight lines of the grid, one per azimuth, sampled on a distance schedule whose step
grows with distance (:func:`ray_distances`): a fiftieth of a cell near the eye, half a per cent of
the distance further out, a quarter cell at most.  The angular error of a missed peak is about the
step over the distance, so it stays below 0.02 deg at every range (on jacksboro, against a march
in fiftieth-cell steps), and the near terrain that forms a valley's horizon is sampled as finely as
the dense reference.  Heights are bilinear between the grid's nodes; curvature and refraction
enter as the parabolic drop d^2 / (2 R_eff).

A ray skips blocks of cells whose highest point could not rise above the horizon already found,
and stops once no height on the map could: ``(z_max - z_eye) / d - d / (2 R_eff)`` only falls with
distance.  In a valley the walls close most rays within a few kilometres.
"""

from __future__ import annotations

import functools
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from appliance.numerics import FAST_FINITE

#: The finest step (cells), the step as a fraction of the distance, the coarsest step (cells).
FINE_STEP_CELLS = 0.02
RELATIVE_STEP = 0.005
COARSE_STEP_CELLS = 0.25


def ray_distances(cell_m: float, reach_m: float, step_m: float | None = None, relative: float = RELATIVE_STEP,
                  coarse_cells: float = COARSE_STEP_CELLS) -> np.ndarray:
    """Sample distances (m) along a ray out to ``reach_m``: steps of max(FINE_STEP_CELLS cells,
    ``relative`` * distance), at most ``coarse_cells`` cells (or a uniform ``step_m``)."""
    if step_m is not None:
        d = np.arange(1, int(np.ceil(reach_m / step_m)) + 1) * float(step_m)
        return d[d <= reach_m + 1e-9]
    fine = FINE_STEP_CELLS * cell_m
    coarse = coarse_cells * cell_m
    d1 = fine / relative  # where the relative step overtakes the finest
    d2 = coarse / relative  # where the coarsest step takes over
    near = np.arange(1, int(round(d1 / fine)) + 1) * fine
    n_geo = int(math.ceil(math.log(d2 / d1) / math.log1p(relative)))
    mid = d1 * (1.0 + relative) ** np.arange(1, n_geo + 1)
    start = mid[-1] if mid.size else d1
    n_far = max(0, int(math.ceil((reach_m - start) / coarse)))
    far = start + np.arange(1, n_far + 1) * coarse
    d = np.concatenate([near, mid, far])
    return d[d <= reach_m + 1e-9]


#: Cells per side of the blocks whose maximum height lets a ray skip them.
BLOCK_CELLS = 8


def block_maxima(Z: np.ndarray, block: int = BLOCK_CELLS) -> np.ndarray:
    """Highest height of each block of ``block`` x ``block`` cells (cell (i, j) spans nodes i..i+1,
    j..j+1), -inf where all nodes are nodata."""
    n_rows, n_cols = Z.shape
    nb_r = (n_rows - 2) // block + 1
    nb_c = (n_cols - 2) // block + 1
    pad = np.full((nb_r * block + 1, nb_c * block + 1), -np.inf)
    zz = np.where(np.isfinite(Z), Z, -np.inf)
    pad[: min(n_rows, pad.shape[0]), : min(n_cols, pad.shape[1])] = zz[: pad.shape[0], : pad.shape[1]]
    core = pad[:-1, :-1].reshape(nb_r, block, nb_c, block).max(axis=(1, 3))
    # a cell's far edge belongs to the next block's first node row/column
    edge_r = np.maximum(core, pad[block::block, :-1].reshape(nb_r, nb_c, block).max(axis=2))
    edge_c = np.maximum(edge_r, pad[:-1, block::block].reshape(nb_r, block, nb_c).max(axis=1))
    corner = pad[block::block, block::block]
    return np.ascontiguousarray(np.maximum(edge_c, corner))


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _block_exit(row: float, col: float, dr: float, dc: float, bi: int, bj: int, block: int) -> float:
    """The distance at which the ray from (row, col) along (``dr``, ``dc``) per metre crosses the far
    edges of block (``bi``, ``bj``) of ``block`` cells."""
    exit_d = np.inf
    if dr > 0.0:
        exit_d = min(exit_d, ((bi + 1) * block - row) / dr)
    elif dr < 0.0:
        exit_d = min(exit_d, (bi * block - row) / dr)
    if dc > 0.0:
        exit_d = min(exit_d, ((bj + 1) * block - col) / dc)
    elif dc < 0.0:
        exit_d = min(exit_d, (bj * block - col) / dc)
    return exit_d


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _ray(Z: np.ndarray, row: float, col: float, eye_m: float, dr: float, dc: float, dist_m: np.ndarray,
         inv2r: float, rise: float, block_max: np.ndarray, block: int, shift: int) -> tuple[float, float]:
    """The horizon tangent along one ray from (row, col) moving (``dr``, ``dc``) cells per metre and
    its distance (-inf and NaN where it meets no terrain); ``rise`` is the map's highest point above
    the eye, ``inv2r`` the curvature's 1 / (2 R_eff), ``shift`` log2 of ``block`` when that is a power
    of two (else -1)."""
    n_rows, n_cols = Z.shape
    n_d = dist_m.size
    best = -np.inf
    bd = np.nan
    k = 0
    while k < n_d:
        d = dist_m[k]
        r = row + d * dr
        c = col + d * dc
        if r < 0.0 or c < 0.0 or r > n_rows - 1 or c > n_cols - 1:
            break
        # nothing further can rise above the horizon found so far
        if (rise >= 0.0 and rise / d - d * inv2r <= best) or (rise < 0.0 and best >= 0.0):
            break
        r0 = min(int(r), n_rows - 2)
        c0 = min(int(c), n_cols - 2)
        # r0, c0 >= 0: a power-of-two block is a shift, not an integer division at every sample
        if shift >= 0:
            bi = r0 >> shift
            bj = c0 >> shift
        else:
            bi = r0 // block
            bj = c0 // block
        zb = block_max[bi, bj] - eye_m
        if zb / d - d * inv2r <= best:
            # leave the block: the distance at which the ray crosses its far edges
            exit_d = _block_exit(row, col, dr, dc, bi, bj, block)
            k += 1
            while k < n_d and dist_m[k] < exit_d:
                k += 1
            continue
        fr = r - r0
        fc = c - c0
        z = ((Z[r0, c0] * (1.0 - fc) + Z[r0, c0 + 1] * fc) * (1.0 - fr)
             + (Z[r0 + 1, c0] * (1.0 - fc) + Z[r0 + 1, c0 + 1] * fc) * fr)
        if z == z:
            t = (z - eye_m) / d - d * inv2r
            if t > best:
                best = t
                bd = d
        k += 1
    return best, bd


@numba.njit(cache=True, nogil=True, fastmath=FAST_FINITE)
def march(
    Z: np.ndarray,
    dx_m: float,
    dy_m: float,
    row: float,
    col: float,
    eye_m: float,
    grid_azimuth_rad: np.ndarray,
    dist_m: np.ndarray,
    r_eff_m: float,
    block_max: np.ndarray,
    block: int,
    tan_out: np.ndarray,
    dist_out: np.ndarray,
) -> None:
    """Horizon tangent and its distance along each grid azimuth from fractional (row, col).

    ``Z[row, col]`` is north-up (rows grow southwards) with spacing ``dx_m`` east and ``dy_m``
    north; ``eye_m`` is the eye's height in Z's datum.  NaN where the ray meets no terrain.  A ray
    skips every block (:func:`block_maxima`) whose highest point cannot rise above the horizon
    found so far, and stops once no block of the map can.
    """
    inv2r = 0.5 / r_eff_m
    nb_r, nb_c = block_max.shape
    z_top = -np.inf
    for i in range(nb_r):
        for j in range(nb_c):
            z_top = max(z_top, block_max[i, j])
    rise = z_top - eye_m
    shift = -1
    if block > 0 and block & (block - 1) == 0:
        shift = 0
        while (1 << shift) < block:
            shift += 1
    for j in range(grid_azimuth_rad.size):
        a = grid_azimuth_rad[j]
        best, bd = _ray(Z, row, col, eye_m, -math.cos(a) / dy_m, math.sin(a) / dx_m, dist_m, inv2r, rise, block_max,
                        block, shift)
        if best == -np.inf:
            tan_out[j] = np.nan
            dist_out[j] = np.nan
        else:
            tan_out[j] = best
            dist_out[j] = bd


#: A render's azimuths are shared among numba's threads when each thread gets at least this many of them.
SHARED_MIN_AZIMUTHS = 64
_march_pools: dict[int, ThreadPoolExecutor] = {}
_march_pool_lock = threading.Lock()
# a forked child (the command server's) has none of its parent's pool threads: it makes its own pools
os.register_at_fork(after_in_child=_march_pools.clear)


def march_shared(Z: np.ndarray, dx_m: float, dy_m: float, row: float, col: float, eye_m: float,
                 grid_azimuth_rad: np.ndarray, dist_m: np.ndarray, r_eff_m: float, block_max: np.ndarray,
                 tan_out: np.ndarray, dist_out: np.ndarray) -> None:
    """:func:`march` with the azimuths shared among as many threads as the compiled kernels may use (numba's
    thread count: the caller's own and the others of a pool; on a thread that runs the kernels with one, as
    the looks' threads do, all on the caller's).  Each azimuth's ray is marched on its own by the same
    kernel, so the values are those of one march over all of them."""
    n = grid_azimuth_rad.size
    parts = min(numba.get_num_threads(), n // SHARED_MIN_AZIMUTHS)
    if parts <= 1:
        march(Z, dx_m, dy_m, row, col, eye_m, grid_azimuth_rad, dist_m, r_eff_m, block_max, BLOCK_CELLS, tan_out,
              dist_out)
        return
    with _march_pool_lock:
        pool = _march_pools.get(parts - 1)
        if pool is None:
            pool = _march_pools[parts - 1] = ThreadPoolExecutor(parts - 1, thread_name_prefix="viper-march",
                                                                initializer=numba.set_num_threads, initargs=(1,))
    edges = [n * i // parts for i in range(parts + 1)]
    others = [pool.submit(march, Z, dx_m, dy_m, row, col, eye_m, grid_azimuth_rad[a:b], dist_m, r_eff_m, block_max,
                          BLOCK_CELLS, tan_out[a:b], dist_out[a:b]) for a, b in zip(edges[1:-1], edges[2:])]
    march(Z, dx_m, dy_m, row, col, eye_m, grid_azimuth_rad[: edges[1]], dist_m, r_eff_m, block_max, BLOCK_CELLS,
          tan_out[: edges[1]], dist_out[: edges[1]])
    for f in others:
        f.result()


def bilinear(Z: np.ndarray, row: float, col: float) -> float:
    """Height at fractional (row, col) of Z (NaN outside or next to nodata)."""
    n_rows, n_cols = Z.shape
    if not (0.0 <= row <= n_rows - 1 and 0.0 <= col <= n_cols - 1):
        return float("nan")
    r0, c0 = min(int(row), n_rows - 2), min(int(col), n_cols - 2)
    fr, fc = row - r0, col - c0
    return float((Z[r0, c0] * (1 - fc) + Z[r0, c0 + 1] * fc) * (1 - fr)
                 + (Z[r0 + 1, c0] * (1 - fc) + Z[r0 + 1, c0 + 1] * fc) * fr)


#: The looks' distance schedule (``Terrain.look_distances``).
LOOK_RELATIVE_STEP = 0.02
LOOK_COARSE_CELLS = 1.0


@dataclass(frozen=True)
class Terrain:
    """The heights under a node grid, for exact renders between nodes.

    ``heights_m`` has the node grid's spacing; candidate node (0, 0) is its (row0, col0).
    ``convergence_deg[node]`` is the true azimuth of grid north at the node.

    With an ``outer`` grid (``outer_ratio`` times coarser, both grids square, of odd size and
    centred on the same point), this one is marched out to ``near_reach_m`` and the outer one beyond: fine
    heights near the eye, where a camera close to the ground sees the slopes under it, and coarse
    ones farther away, where a cell subtends little."""

    heights_m: np.ndarray
    row0: int
    col0: int
    convergence_deg: np.ndarray
    height_m: float
    r_eff_m: float
    reach_m: float
    outer: Terrain | None = None
    outer_ratio: float = 1.0
    near_reach_m: float = math.inf

    def outer_rc(self, row: float, col: float) -> tuple[float, float]:
        """The outer grid's fractional (row, col) of this grid's (row, col) (heights' indices)."""
        assert self.outer is not None
        c_in = 0.5 * (self.heights_m.shape[0] - 1)
        c_out = 0.5 * (self.outer.heights_m.shape[0] - 1)
        return c_out + (row - c_in) / self.outer_ratio, c_out + (col - c_in) / self.outer_ratio

    @cached_property
    def block_max(self) -> np.ndarray:
        return block_maxima(self.heights64)

    @cached_property
    def heights64(self) -> np.ndarray:
        return np.ascontiguousarray(self.heights_m, dtype=np.float64)

    def distances(self, cell_m: float) -> np.ndarray:
        """The fits' schedule (:func:`ray_distances`), read-only."""
        return _schedule(float(cell_m), float(self.reach_m), RELATIVE_STEP, COARSE_STEP_CELLS)

    def look_distances(self, cell_m: float) -> np.ndarray:
        """A coarser schedule for looks (two per cent of the distance, a cell at most): a quarter
        of the samples on a large map, angular errors of a few hundredths of a degree.  Read-only."""
        return _schedule(float(cell_m), float(self.reach_m), LOOK_RELATIVE_STEP, LOOK_COARSE_CELLS)


@functools.lru_cache(maxsize=64)
def _schedule(cell_m: float, reach_m: float, relative: float, coarse_cells: float) -> np.ndarray:
    """:func:`ray_distances` made once per cell size, reach and steps (every look and fit of an
    estimate marches on the same one), read-only."""
    d = ray_distances(cell_m, reach_m, relative=relative, coarse_cells=coarse_cells)
    d.flags.writeable = False
    return d


def render(terrain: Terrain, dx_m: float, dy_m: float, row: float, col: float, grid_azimuth_deg: np.ndarray,
           dist: np.ndarray, height_m: float, outer_looks: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Elevation (deg), range (m) per grid azimuth and ground height from fractional node (row, col).

    ``dist`` is the ray's schedule on this grid; an outer grid is sampled on its own
    :meth:`Terrain.distances`, or with ``outer_looks`` on the looks' coarser schedule."""
    Z = terrain.heights64
    tr, tc = row + terrain.row0, col + terrain.col0
    ground = bilinear(Z, tr, tc)
    tan = np.empty(grid_azimuth_deg.size)
    far = np.empty(grid_azimuth_deg.size)
    if not math.isfinite(ground):
        return np.full(grid_azimuth_deg.size, np.nan), far, ground
    az = np.radians(grid_azimuth_deg)
    outer = terrain.outer
    if outer is None:
        march_shared(Z, dx_m, dy_m, tr, tc, ground + height_m, az, dist, terrain.r_eff_m, terrain.block_max, tan,
                     far)
        return np.degrees(np.arctan(tan)), far, ground
    march_shared(Z, dx_m, dy_m, tr, tc, ground + height_m, az, dist[dist <= terrain.near_reach_m], terrain.r_eff_m,
                 terrain.block_max, tan, far)
    ratio = terrain.outer_ratio
    outer_cell = min(dx_m, dy_m) * ratio
    beyond = outer.look_distances(outer_cell) if outer_looks else outer.distances(outer_cell)
    tan_o = np.empty(az.size)
    far_o = np.empty(az.size)
    march_shared(outer.heights64, dx_m * ratio, dy_m * ratio, *terrain.outer_rc(tr, tc), ground + height_m, az,
                 beyond[beyond > terrain.near_reach_m], outer.r_eff_m, outer.block_max, tan_o, far_o)
    take = np.isfinite(tan_o) & ~(tan >= tan_o)
    tan = np.where(take, tan_o, tan)
    far = np.where(take, far_o, far)
    return np.degrees(np.arctan(tan)), far, ground


@numba.njit(cache=True, nogil=True, fastmath=FAST_FINITE)
def _edge_tangents(Z: np.ndarray, dx_m: float, dy_m: float, row: float, col: float, eye_m: float,
                   grid_azimuth_rad: np.ndarray, r_eff_m: float, reach_m: float, tan_out: np.ndarray,
                   dist_out: np.ndarray) -> None:
    """Along each grid azimuth from fractional (row, col): the distance of the map's last height
    before the ray leaves it (its array, or the nodata beyond its footprint), and that height's
    tangent seen from the eye, curvature included.  NaN where the ray reaches ``reach_m`` on the map."""
    n_rows, n_cols = Z.shape
    inv2r = 0.5 / r_eff_m
    back = min(dx_m, dy_m)
    for j in range(grid_azimuth_rad.size):
        a = grid_azimuth_rad[j]
        dr = -math.cos(a) / dy_m
        dc = math.sin(a) / dx_m
        d = reach_m
        if dr > 1e-12:
            d = min(d, (n_rows - 1 - row) / dr)
        elif dr < -1e-12:
            d = min(d, -row / dr)
        if dc > 1e-12:
            d = min(d, (n_cols - 1 - col) / dc)
        elif dc < -1e-12:
            d = min(d, -col / dc)
        tan_out[j] = np.nan
        dist_out[j] = np.nan
        if d >= reach_m:
            continue
        while d > back:
            r = row + d * dr
            c = col + d * dc
            r0 = max(min(int(r), n_rows - 2), 0)
            c0 = max(min(int(c), n_cols - 2), 0)
            fr = r - r0
            fc = c - c0
            z = ((Z[r0, c0] * (1.0 - fc) + Z[r0, c0 + 1] * fc) * (1.0 - fr)
                 + (Z[r0 + 1, c0] * (1.0 - fc) + Z[r0 + 1, c0 + 1] * fc) * fr)
            if z == z:
                tan_out[j] = (z - eye_m) / d - d * inv2r
                dist_out[j] = d
                break
            d -= back


def edge_relief(terrain: Terrain, dx_m: float, dy_m: float, row: float, col: float, grid_azimuth_deg: np.ndarray,
                elevation_deg: np.ndarray, eye_m: float) -> np.ndarray:
    """Per grid azimuth, how far (m) the ground at the map's edge lies under the sightline to the
    rendered horizon ``elevation_deg`` from an eye at ``eye_m`` (the map's datum): terrain beyond the
    edge that rose this much would stand in the skyline the render cannot show.  Inf where the ray
    reaches the render's reach on the map, or meets no terrain."""
    grid = terrain.outer if terrain.outer is not None else terrain
    ratio = terrain.outer_ratio if terrain.outer is not None else 1.0
    tr, tc = row + terrain.row0, col + terrain.col0
    if terrain.outer is not None:
        tr, tc = terrain.outer_rc(tr, tc)
    tan = np.empty(grid_azimuth_deg.size)
    dist = np.empty(grid_azimuth_deg.size)
    _edge_tangents(grid.heights64, dx_m * ratio, dy_m * ratio, tr, tc, eye_m, np.radians(grid_azimuth_deg),
                   grid.r_eff_m, grid.reach_m, tan, dist)
    relief = dist * (np.tan(np.radians(elevation_deg)) - tan)
    return np.where(np.isfinite(relief), relief, np.inf)
