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

from appliance.locating.position import Position, place_tiled
from appliance.locating.surface_fit import fit_on_surface
from appliance.locating.tile_cache import SearchParams
from appliance.locating.tile_combination import best_tile, combine, combine_tiles
from appliance.locating.tile_search import search_tile, tile_floor
from appliance.locating.tiled_index import Box, TiledIndex, TileEntry, select_tiles
from appliance.skyline import Skyline
from appliance.terrain.dem import Dem


def locate_tiled(index: TiledIndex, skyline: Skyline, params: SearchParams, *, box: Box | None = None,
                 client: Any = None, source: str = "", surface: Dem | None = None) -> Position:
    """The answer to ``skyline`` (named ``source``) over the tiles that ``box`` meets (every tile
    with None), combined.

    First every tile's best first-pass lower bound, the largest of which each tile's rescoring is
    then pruned against, as one search of the whole lattice would prune (a tile of sea or of
    valleys that do not match rescores a handful of nodes, not all of them).  Then two rounds:
    every tile on its grid alone, combined; then the exact refinement, only on the best tile.  The
    refinement moves a tile's answer between its nodes and adds the cells of its fits to its
    region, but changes none of the posteriors the combination weighs: the best tile stays the
    best, and the combination takes the answer and the region's own cells from the best tile
    only (every other tile's part of the region comes from its grid posteriors).  Refining the
    other tiles (most of a hopeless tile's time: it finds no fit to stop at) would change nothing.
    With a ``distributed.Client`` every tile is one task of each round on its cluster,
    each worker mapping its own tile; without one the tiles are searched here, side by side on a
    thread per core (:func:`_tile_pool`).  The combination is the same either way, so the answer
    is too.

    With the ``surface`` a whole-body database was built from
    (:func:`appliance.locating.tiled_index.open_surface`), the answer is fitted on that map itself
    (:func:`appliance.locating.surface_fit.fit_on_surface`) instead of refined on the facets'
    resampled grid."""
    t0 = time.perf_counter()
    tiles = select_tiles(index, box)
    placed: dict[str, str] = {}
    floors = _run(index, tile_floor, tiles, client, skyline, params, placed=placed)
    floor = max(floors, default=-math.inf)
    first = _run(index, search_tile, tiles, client, skyline, params, source=source, refine=False,
                 rescore_floor=floor, region=False, placed=placed)
    best = best_tile(first)
    best_tiles = [t for t in tiles if t.file == best]
    if surface is not None:
        # the best tile's region without its refinement: the fits on the map replace that
        grid = _run(index, search_tile, best_tiles, client, skyline, params, source=source, refine=False,
                    rescore_floor=floor, placed=placed)
        fitted = fit_on_surface(index, combine_tiles(grid + [o for o in first if o.file != best], index.body),
                                surface, skyline, params)
        if fitted is not None:
            return place_tiled(dataclasses.replace(fitted, elapsed_s=time.perf_counter() - t0), source)
    refined = _run(index, search_tile, best_tiles, client, skyline, params, source=source, refine=True,
                   rescore_floor=floor, placed=placed)
    outcomes = refined + [o for o in first if o.file != best]
    return combine(outcomes, index.body, elapsed_s=time.perf_counter() - t0, source=source)

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
