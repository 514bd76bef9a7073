"""Position from a skyline against a tiled skyline database: a folder of ordinary databases.

A tiled database (:mod:`appliance.locating.tiled_index`) holds one database per tile.  A search runs
the ordinary estimator on every tile that the search area touches (:mod:`appliance.locating.tile_search`:
in process, or one Dask task per tile on a cluster) and then combines the tiles as one grid would
have been combined (:mod:`appliance.locating.tile_combination`); the answer is a
:class:`appliance.locating.position.Position`, as from one database, carrying the combination.  A
whole-body database's answer is then fitted on the map's own surface
(:mod:`appliance.locating.surface_fit`).

Nothing here touches devices or logs: the module maps a folder and skylines to numbers.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba

from appliance.estimator import confidence
from appliance.locating.position import Position, place_tiled
from appliance.locating.surface_fit import fit_on_surface, with_surface_fit
from appliance.locating.tile_cache import SearchParams
from appliance.locating.tile_combination import best_tile, combine_tiles
from appliance.locating.tile_search import search_tile, tile_floor
from appliance.locating.tiled_answer import TileCombination
from appliance.locating.tiled_index import Box, TiledIndex, TileEntry, select_tiles
from appliance.skyline import Skyline
from appliance.terrain.dem import Dem


def locate_tiled(index: TiledIndex, skyline: Skyline, params: SearchParams, *, box: Box | None = None,
                 client: Any = None, source: str = "", surface: Dem | None = None, learn_noise: bool = True,
                 sigma_floor_deg: float | None = None) -> Position:
    """The answer to ``skyline`` (named ``source``) over the tiles that ``box`` meets (every tile
    with None), combined.

    A first round at the sigma interval of ``params`` (:func:`_searched`) finds the answer; with
    ``learn_noise``, its fit's residuals then give the noise the skyline has (sigma's interval, at
    least ``sigma_floor_deg`` or the database's quantisation, and the share of independent
    azimuths, ``appliance.estimator.confidence``), and a second round weighs every tile at that
    noise, as one grid's search does (:func:`appliance.estimator.estimate`).  Only the tiles that
    held the first round's region are searched again: at the narrower noise the others stand
    further below the best.  The second round's region and rivals decide whether the answer is
    ambiguous (its fit judged by the interval given); its best tile's fit is polished at that noise,
    with the head's residual tilt, as one grid's search polishes it, and the answer's covariance is
    that fit's at that noise.

    With the ``surface`` a whole-body database was built from
    (:func:`appliance.locating.tiled_index.open_surface`), the answer is fitted on that map itself
    (:func:`appliance.locating.surface_fit.fit_on_surface`) instead of refined on the facets'
    resampled grid; the second round then weighs the facets' grid at the RMS its best node leaves
    (the facets' own error besides the skyline's), with the fit's share of independent azimuths."""
    t0 = time.perf_counter()
    tiles = select_tiles(index, box)
    placed: dict[str, str] = {}
    floor_deg = max(sigma_floor_deg or 0.0, confidence.SIGMA_FLOOR_DEG)
    found = _searched(index, tiles, skyline, params, client, source, surface, placed, learn_noise, floor_deg)
    noise = _learned(found, floor_deg) if learn_noise else None
    if noise is not None:
        # the fits are still judged by the interval given: a skyline no place fits is no better a
        # match for the wider interval its own residuals give
        again = dataclasses.replace(params, sigma_deg=(noise[0], noise[1]), temper=noise[2],
                                    allowed_sigma_deg=params.sigma_deg[1], polish=True)
        held = {found.best.file} | {c.tile for c in found.region} | ({found.fit.tile} if found.fit else set())
        near = [t for t in tiles if t.file in held]
        second = _searched(index, near, skyline, again, client, source, None, placed, False, floor_deg)
        if found.fit is not None:
            second = with_surface_fit(index, second, found.fit, params.sigma_deg[1])
        found = dataclasses.replace(second, noise=noise, tiles_searched=found.tiles_searched,
                                    tiles_failed=found.tiles_failed)
    return place_tiled(dataclasses.replace(found, elapsed_s=time.perf_counter() - t0), source)


def _learned(found: TileCombination, floor_deg: float) -> tuple[float, float, float] | None:
    """The noise the first round's answer leaves: sigma's interval (deg) and the tempering; None
    where no fit gave residuals.  On the map's own surface, sigma's interval is the one the grid's
    best node leaves over the fit's independent azimuths (the grid's skylines carry the facets'
    resampling error too)."""
    if found.fit is None:
        return found.best.noise
    if found.fit.noise is None:
        return None
    lo, hi, temper = found.fit.noise
    grid_rms = float(found.best.record.get("rms_residual_deg", math.nan))
    n = float(found.best.record.get("valid_azimuths", 0))
    if math.isfinite(grid_rms) and grid_rms > found.fit.rms_deg and n > 0:
        lo, hi = confidence.sigma_interval(grid_rms, temper * n, floor_deg)
    return lo, hi, temper


def _searched(index: TiledIndex, tiles: list[TileEntry], skyline: Skyline, params: SearchParams, client: Any,
              source: str, surface: Dem | None, placed: dict[str, str], learn_noise: bool,
              floor_deg: float) -> TileCombination:
    """One round of :func:`locate_tiled` over ``tiles`` at ``params``.

    First every tile's best first-pass lower bound, the largest of which each tile's rescoring is
    then pruned against, as one search of the whole lattice would prune (a tile of sea or of
    valleys that do not match rescores a handful of nodes, not all of them).  Then two steps:
    every tile on its grid alone, combined; then the exact refinement, only on the best tile (which
    learns the noise from its fit with ``learn_noise``).  The refinement moves a tile's answer
    between its nodes and adds the cells of its fits to its region, but changes none of the
    posteriors the combination weighs: the best tile stays the best, and the combination takes the
    answer and the region's own cells from the best tile only (every other tile's part of the
    region comes from its grid posteriors).  Refining the other tiles (most of a hopeless tile's
    time: it finds no fit to stop at) would change nothing.  With a ``distributed.Client`` every
    tile is one task of each step on its cluster, each worker mapping its own tile; without one
    the tiles are searched here, side by side on a thread per core (:func:`_tile_pool`).  The
    combination is the same either way, so the answer is too.  With the ``surface``, the answer
    is fitted on it instead of refined (sigma learned at least ``floor_deg``)."""
    floors = _run(index, tile_floor, tiles, client, skyline, params, placed=placed)
    # the floors are first-pass likelihoods, which the tiles' searches temper as they weigh them
    floor = max(floors, default=-math.inf) * params.temper
    first = _run(index, search_tile, tiles, client, skyline, params, source=source, refine=False,
                 rescore_floor=floor, region=False, placed=placed)
    best = best_tile(first)
    best_tiles = [t for t in tiles if t.file == best]
    others = [o for o in first if o.file != best]
    if surface is not None:
        # the best tile's region without its refinement: the fits on the map replace that
        grid = _run(index, search_tile, best_tiles, client, skyline, params, source=source, refine=False,
                    rescore_floor=floor, placed=placed)
        combined = combine_tiles(grid + others, index.body)
        fitted = fit_on_surface(index, combined, surface, skyline, params, floor_deg)
        if fitted is not None:
            return fitted
    refined = _run(index, search_tile, best_tiles, client, skyline, params, source=source, refine=True,
                   rescore_floor=floor, placed=placed, learn_noise=learn_noise)
    learned = refined[0].noise if refined[0].error is None else None
    if learned is not None:
        # the refined tile's posteriors are at the noise it learned, on another scale than the other
        # tiles': weighed with theirs it may no longer be the best.  The round's answer only tells
        # the noise and which tiles to search again, weighed at the given noise as on the grid
        on_grid = next(o for o in first if o.file == best)
        return combine_tiles([dataclasses.replace(on_grid, has_region=True, noise=learned)] + others, index.body)
    return combine_tiles(refined + others, index.body)


def _run(index: TiledIndex, task: Callable[..., Any], tiles: Sequence[TileEntry], client: Any, skyline: Skyline,
         params: SearchParams, *, placed: dict[str, str] | None = None, **kwargs: Any) -> list[Any]:
    """``task(folder, tile, skyline, params, expect=..., **kwargs)`` for every tile, in
    order: here on the threads of :func:`_tile_pool`, or one task per tile on the ``client``'s
    cluster.  On a cluster, ``placed`` maps a tile to the worker that first ran one of its tasks,
    which then holds the tile's first pass: the tile's later tasks ask for that worker (any other
    may still take them, making the first pass again)."""
    folder = str(index.folder)
    kwargs["expect"] = (index.n_azimuths, index.height_m)
    if client is None:
        numba_threads = numba.get_num_threads()  # which also starts the threading layer read below
        threads = min(numba_threads if TILE_THREADS is None else TILE_THREADS, len(tiles))
        # numba's own work queue (where neither OpenMP nor TBB is installed) aborts the process when
        # two threads run parallel kernels at once: there the tiles go one after the other
        if threads <= 1 or numba.threading_layer() == "workqueue":
            return [task(folder, t, skyline, params, **kwargs) for t in tiles]
        return list(_tile_pool(threads).map(lambda t: task(folder, t, skyline, params, **kwargs), tiles))
    placed = {} if placed is None else placed
    futures = []
    for t in tiles:
        where = {"workers": [placed[t.file]], "allow_other_workers": True} if t.file in placed else {}
        futures.append(client.submit(task, folder, t, skyline, params, pure=False, **where, **kwargs))
    out = list(client.gather(futures))
    held = client.who_has(futures)
    for t, f in zip(tiles, futures, strict=True):
        if held.get(f.key):
            placed.setdefault(t.file, held[f.key][0])
    return out


#: Threads an in-process search runs its tiles on; None: numba's thread count (one per core,
#: unless NUMBA_NUM_THREADS or numba.set_num_threads say otherwise), 1: one tile after the other.
TILE_THREADS: int | None = None
_tile_pools: dict[int, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def _tile_pool(threads: int) -> ThreadPoolExecutor:
    """Threads that search the tiles of an in-process search side by side, as many as the compiled
    kernels would use (numba's thread count), each running those kernels on its own thread only.

    Run one after the other, every kernel call on every tile forks its loop over the cores and
    joins it again: tens of fork-joins per search, each as slow as its slowest share, so that
    beside another busy process half of each call waits for the core the other holds.  Whole
    tiles taken by whichever thread is free balance themselves instead, and the kernels release
    the GIL (``nogil``).  Each tile is still searched by one thread from start to end with the
    same compiled code, and its results are returned in tile order: the same answers."""
    with _pool_lock:
        pool = _tile_pools.get(threads)
        if pool is None:
            pool = _tile_pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="viper-tile",
                                                             initializer=numba.set_num_threads, initargs=(1,))
        return pool
