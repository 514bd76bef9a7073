"""Worlds that differ from the map: forest canopy, buildings, correlated height error, finer grids.

The estimator's skyline database is built from a map (a DEM); a real camera sees the world, which
holds trees, buildings and the map's own vertical and resolution error.  These functions make such a
world from a map's height array, so that a benchmark can render the measured skyline from the world
and locate it on the map's database.  Pure numpy over height arrays; the only georeferencing they
touch is the affine transform of :func:`decimate`.

Units: heights and distances in metres, lengths on the grid in cells (``*_cells``); ``cell_m`` is
the ground size (x, y) of one cell.  Arrays are indexed ``[row, col]``, row 0 at the top (north).

- :func:`correlated_noise_m`: Gaussian-filtered white noise; its autocorrelation is
  exp(-r^2 / L^2) with L the correlation length (the 1/e distance), so the filter's sigma is L / 2.
- :func:`forest_canopy_m`: flat-topped elliptical patches, 15-25 m by default, one height per
  patch, with a smooth edge (a smoothstep over the outer part of each ellipse), added until the
  requested fraction of the eligible cells is covered; the tallest patch wins where patches overlap.
- :func:`carve_clearings`: discs cut out of the canopy (meadows, cuts), with a smooth rim.
- :func:`add_buildings_m`: blocky flat-roofed buildings near given points.
- :func:`decimate`: a coarser map of a finer world (block mean or subsample) with its transform.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from affine import Affine

COVER_THRESHOLD_M = 1.0  # a cell counts as covered by canopy above this height


@dataclass(frozen=True)
class Clearing:
    """A disc cut out of the canopy: centre in fractional pixel-centre (row, col), radius in metres."""

    row: float
    col: float
    radius_m: float


def gaussian_kernel(sigma_cells: float) -> np.ndarray:
    """Normalised 1-D Gaussian kernel reaching 4 sigma each side."""
    if sigma_cells <= 0:
        return np.ones(1)
    half = max(1, int(math.ceil(4.0 * sigma_cells)))
    x = np.arange(-half, half + 1, dtype=float)
    k = np.exp(-0.5 * (x / sigma_cells) ** 2)
    return k / k.sum()


def _convolve_axis(a: np.ndarray, kernel: np.ndarray, axis: int) -> np.ndarray:
    half = kernel.size // 2
    pad = [(0, 0), (0, 0)]
    pad[axis] = (half, half)
    p = np.pad(a, pad, mode="reflect" if a.shape[axis] > half else "edge")
    out = np.zeros(a.shape)
    n = a.shape[axis]
    for i, w in enumerate(kernel):
        out += w * (p[i : i + n, :] if axis == 0 else p[:, i : i + n])
    return out


def gaussian_smooth(field: np.ndarray, sigma_cells: tuple[float, float]) -> np.ndarray:
    """Separable Gaussian filter with (row, col) sigmas in cells; edges reflected."""
    out = _convolve_axis(np.asarray(field, dtype=float), gaussian_kernel(sigma_cells[0]), 0)
    return _convolve_axis(out, gaussian_kernel(sigma_cells[1]), 1)


def correlated_noise_m(shape: tuple[int, int], rms_m: float, correlation_m: float, cell_m: tuple[float, float],
                       rng: np.random.Generator) -> np.ndarray:
    """Stationary Gaussian height noise: standard deviation ``rms_m``, autocorrelation
    exp(-r^2 / correlation_m^2) (r in metres).

    White noise through a Gaussian filter of sigma correlation_m / 2, scaled by the filter's own
    white-noise gain (so the standard deviation is ``rms_m`` in expectation, not forced on the sample).
    """
    sig = (0.5 * correlation_m / cell_m[1], 0.5 * correlation_m / cell_m[0])
    k_rows, k_cols = gaussian_kernel(sig[0]), gaussian_kernel(sig[1])
    gain = math.sqrt(float(np.sum(k_rows**2)) * float(np.sum(k_cols**2)))
    white = rng.standard_normal(shape)
    return gaussian_smooth(white, sig) * (rms_m / gain)


def smoothstep(t: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, 3t^2 - 2t^3 between."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def forest_canopy_m(
    eligible: np.ndarray,
    cell_m: tuple[float, float],
    rng: np.random.Generator,
    cover_fraction: float = 0.65,
    height_range_m: tuple[float, float] = (15.0, 25.0),
    semi_axis_range_m: tuple[float, float] = (150.0, 700.0),
    edge_fraction: float = 0.35,
    batch: int = 500,
) -> np.ndarray:
    """Canopy heights (m, >= 0) over the ``eligible`` cells covering about ``cover_fraction`` of them.

    Each patch is an ellipse (semi-axes uniform in ``semi_axis_range_m``, random orientation) with
    one height uniform in ``height_range_m``; the height falls smoothly to zero over the outer
    ``edge_fraction`` of the ellipse's radius.  Patches are added in batches until the covered
    share (canopy above :data:`COVER_THRESHOLD_M`) of the eligible cells reaches ``cover_fraction``.
    Cells outside ``eligible`` get no canopy.
    """
    if not 0.0 <= cover_fraction < 1.0:
        raise ValueError(f"cover fraction {cover_fraction} outside [0, 1)")
    n_rows, n_cols = eligible.shape
    canopy = np.zeros(eligible.shape)
    n_eligible = int(np.count_nonzero(eligible))
    if n_eligible == 0 or cover_fraction == 0.0:
        return canopy
    dx_m, dy_m = cell_m
    lo, hi = semi_axis_range_m
    for _ in range(100_000):
        covered = np.count_nonzero((canopy > COVER_THRESHOLD_M) & eligible) / n_eligible
        if covered >= cover_fraction:
            break
        # a batch small enough not to overshoot the target by much
        remaining = cover_fraction - covered
        mean_area_cells = math.pi * ((lo + hi) / 2) ** 2 / (dx_m * dy_m)
        n_new = max(1, min(batch, int(remaining * n_eligible / mean_area_cells / 2) + 1))
        centres = rng.integers(0, eligible.size, n_new)
        for flat in centres:
            r0, c0 = divmod(int(flat), n_cols)
            if not eligible[r0, c0]:
                continue
            a_m, b_m = rng.uniform(lo, hi, 2)
            theta = rng.uniform(0.0, math.pi)
            h = rng.uniform(*height_range_m)
            reach_m = max(a_m, b_m)
            rr = int(math.ceil(reach_m / dy_m))
            rc = int(math.ceil(reach_m / dx_m))
            rs, re_ = max(0, r0 - rr), min(n_rows, r0 + rr + 1)
            cs, ce = max(0, c0 - rc), min(n_cols, c0 + rc + 1)
            north_m = (r0 - np.arange(rs, re_))[:, None] * dy_m
            east_m = (np.arange(cs, ce) - c0)[None, :] * dx_m
            u = east_m * math.cos(theta) + north_m * math.sin(theta)
            v = -east_m * math.sin(theta) + north_m * math.cos(theta)
            rho = np.sqrt((u / a_m) ** 2 + (v / b_m) ** 2)
            patch = h * smoothstep((1.0 - rho) / edge_fraction)
            window = canopy[rs:re_, cs:ce]
            np.maximum(window, np.where(eligible[rs:re_, cs:ce], patch, 0.0), out=window)
    return canopy


def treeline_taper(ground_m: np.ndarray, treeline_m: float, taper_m: float) -> np.ndarray:
    """Factor on canopy height: 1 below ``treeline_m - taper_m``, falling smoothly to 0 at the
    treeline (and 0 on nodata)."""
    z = np.where(np.isfinite(ground_m), ground_m, treeline_m)
    return smoothstep((treeline_m - z) / taper_m)


def carve_clearings(canopy_m: np.ndarray, cell_m: tuple[float, float], rng: np.random.Generator, count: int,
                    radius_range_m: tuple[float, float] = (150.0, 300.0), rim_m: float = 60.0,
                    inside: np.ndarray | None = None) -> tuple[np.ndarray, list[Clearing]]:
    """Cut ``count`` clearings into the forest: canopy is zero within each disc's radius and rises
    back over ``rim_m`` beyond it.  Centres are canopy-covered cells (inside the ``inside`` mask when
    given), so every clearing is surrounded by forest.  Returns the new canopy and the clearings."""
    n_rows, n_cols = canopy_m.shape
    dx_m, dy_m = cell_m
    forest = canopy_m > COVER_THRESHOLD_M
    if inside is not None:
        forest &= inside
    cells = np.flatnonzero(forest)
    out = canopy_m.copy()
    clearings: list[Clearing] = []
    if cells.size == 0 or count <= 0:
        return out, clearings
    for flat in rng.choice(cells, size=min(count, cells.size), replace=False):
        r0, c0 = divmod(int(flat), n_cols)
        radius = float(rng.uniform(*radius_range_m))
        reach = radius + rim_m
        rr, rc = int(math.ceil(reach / dy_m)), int(math.ceil(reach / dx_m))
        rs, re_ = max(0, r0 - rr), min(n_rows, r0 + rr + 1)
        cs, ce = max(0, c0 - rc), min(n_cols, c0 + rc + 1)
        d_m = np.hypot(((np.arange(rs, re_) - r0) * dy_m)[:, None], ((np.arange(cs, ce) - c0) * dx_m)[None, :])
        out[rs:re_, cs:ce] *= smoothstep((d_m - radius) / rim_m)
        clearings.append(Clearing(float(r0), float(c0), radius))
    return out, clearings


def add_buildings_m(ground_m: np.ndarray, cell_m: tuple[float, float], sites_rc: list[tuple[float, float]],
                    rng: np.random.Generator, per_site: int = 3, distance_range_m: tuple[float, float] = (120.0, 500.0),
                    height_range_m: tuple[float, float] = (10.0, 30.0),
                    footprint_cells: tuple[int, int] = (1, 2)) -> np.ndarray:
    """Heights of ``ground_m`` with blocky buildings: ``per_site`` of them around each (row, col)
    site, at a distance in ``distance_range_m``, footprint 1..``footprint_cells`` cells a side, a
    flat roof ``height_range_m`` above the highest ground cell of the footprint.  No footprint cell
    comes nearer than ``distance_range_m[0]`` to any site, so the ground under a camera is untouched."""
    out = np.array(ground_m, dtype=float)
    n_rows, n_cols = out.shape
    dx_m, dy_m = cell_m
    for r_site, c_site in sites_rc:
        for _ in range(per_site):
            d = rng.uniform(*distance_range_m)
            az = rng.uniform(0.0, 2.0 * math.pi)
            r0 = int(round(r_site - d * math.cos(az) / dy_m))
            c0 = int(round(c_site + d * math.sin(az) / dx_m))
            h_cells, w_cells = (int(rng.integers(footprint_cells[0], footprint_cells[1] + 1)) for _ in range(2))
            rs, re_ = max(0, r0), min(n_rows, r0 + h_cells)
            cs, ce = max(0, c0), min(n_cols, c0 + w_cells)
            if rs >= re_ or cs >= ce:
                continue
            fr, fc = np.mgrid[rs:re_, cs:ce]
            if any(np.min(np.hypot((fr - r) * dy_m, (fc - c) * dx_m)) < distance_range_m[0] for r, c in sites_rc):
                continue  # no footprint comes nearer any site than the closest distance
            block = out[rs:re_, cs:ce]
            if not np.isfinite(block).all():
                continue
            out[rs:re_, cs:ce] = np.nanmax(ground_m[rs:re_, cs:ce]) + rng.uniform(*height_range_m)
    return out


def decimate(elevation_m: np.ndarray, transform: Affine, factor: int,
             method: str = "mean") -> tuple[np.ndarray, Affine]:
    """A map ``factor`` times coarser than the world: each map cell covers a ``factor`` x ``factor``
    block of world cells, with the same outer edges; its height is the block's mean ("mean", NaN if
    any cell is nodata) or its centre cell ("subsample"; ``factor`` odd).  Returns (heights, transform):
    the transform is the world's scaled by ``factor``, so map pixel (0, 0)'s edges are world pixel
    (0, 0)'s top-left edge and world pixel (factor, factor)'s; rows and columns that do not fill a
    whole block are dropped."""
    if factor < 1:
        raise ValueError(f"decimation factor {factor} must be >= 1")
    n_rows, n_cols = (s // factor for s in elevation_m.shape)
    z = np.asarray(elevation_m, dtype=float)[: n_rows * factor, : n_cols * factor]
    if method == "mean":
        out = z.reshape(n_rows, factor, n_cols, factor).mean(axis=(1, 3))
    elif method == "subsample":
        if factor % 2 == 0:
            raise ValueError(f"subsampling needs an odd factor to keep cell centres, got {factor}")
        out = z[factor // 2 :: factor, factor // 2 :: factor].copy()
    else:
        raise ValueError(f"decimation method {method!r}: expected 'mean' or 'subsample'")
    return out, transform @ Affine.scale(factor)


def heights_sha256(elevation_m: np.ndarray, label: str) -> str:
    """A content hash for a derived height array (identifies a derived map to its skyline database)."""
    h = hashlib.sha256(label.encode())
    h.update(np.ascontiguousarray(elevation_m, dtype=np.float64).tobytes())
    return h.hexdigest()


def local_maxima(z: np.ndarray, half_window_cells: int = 2) -> np.ndarray:
    """Cells that are the strict-or-tied maximum of the (2h+1)^2 window around them (NaN never)."""
    h = half_window_cells
    p = np.pad(np.where(np.isfinite(z), z, -np.inf), h, mode="constant", constant_values=-np.inf)
    n_rows, n_cols = z.shape
    best = np.full(z.shape, -np.inf)
    for dr in range(2 * h + 1):
        for dc in range(2 * h + 1):
            np.maximum(best, p[dr : dr + n_rows, dc : dc + n_cols], out=best)
    return np.isfinite(z) & (z >= best)


def slope_deg(z: np.ndarray, cell_m: tuple[float, float]) -> np.ndarray:
    """Ground slope (degrees) from central differences."""
    gy, gx = np.gradient(np.asarray(z, dtype=float), cell_m[1], cell_m[0])
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def max_within_m(field: np.ndarray, cell_m: tuple[float, float], radius_m: float) -> np.ndarray:
    """The largest value of ``field`` among cells whose centres lie within ``radius_m`` of each cell."""
    dx_m, dy_m = cell_m
    rr, rc = int(radius_m // dy_m), int(radius_m // dx_m)
    n_rows, n_cols = field.shape
    p = np.pad(field, ((rr, rr), (rc, rc)), mode="edge")
    out = np.full(field.shape, -np.inf)
    for dr in range(-rr, rr + 1):
        for dc in range(-rc, rc + 1):
            if (dr * dy_m) ** 2 + (dc * dx_m) ** 2 <= radius_m**2:
                np.maximum(out, p[rr + dr : rr + dr + n_rows, rc + dc : rc + dc + n_cols], out=out)
    return out


def autocorrelation(field: np.ndarray, lag_cells: int, axis: int) -> float:
    """Sample autocorrelation of ``field`` at a lag of whole cells along ``axis``."""
    a = np.asarray(field, dtype=float) - float(np.mean(field))
    n = a.shape[axis]
    x = np.take(a, np.arange(0, n - lag_cells), axis=axis)
    y = np.take(a, np.arange(lag_cells, n), axis=axis)
    return float(np.mean(x * y) / np.mean(a * a))
