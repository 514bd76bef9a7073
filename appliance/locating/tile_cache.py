"""The tiles a process keeps open between searches, and each tile's first pass of a skyline.

A tile is memory-mapped once per process (on a Dask worker, by the worker) and kept while its file
stays the same; a search's rounds (the pruning floor, the grid search, the refinement) all start
from each tile's first pass of the skyline, made once per search and kept for the next round.  The
tiles of an in-process search run on several threads at once: the caches are guarded by a lock.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from appliance.errors import DatabaseError
from appliance.estimator.estimate import OCCLUSION_WEIGHT, FirstPass, SkylineGrid, first_pass
from appliance.locating.search_grid import skyline_grid
from appliance.locating.tiled_index import TileEntry
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase, load_database


@dataclass(frozen=True)
class SearchParams:
    """What every tile's search shares (the arguments of :func:`appliance.locating.position.locate`)."""

    sigma_deg: tuple[float, float]
    heading_tolerance_deg: float | None
    height_m: float | None = None
    occlusion_weight: float = OCCLUSION_WEIGHT
    map_sigma_m: float = 0.0
    #: the share of an independent azimuth each measured one counts for: below 1 in a search's
    #: second round, made at the noise its first round's answer left (:func:`appliance.estimator.estimate`)
    temper: float = 1.0
    #: the most noise (deg) a fit may leave before the skyline is a poor match; None: the upper end
    #: of ``sigma_deg`` (a second round's is the interval its first round was given)
    allowed_sigma_deg: float | None = None
    #: whether a refined tile polishes its best fit at ``sigma_deg`` (a second round: as one grid's
    #: search polishes it at the noise it learned)
    polish: bool = False


#: Candidate nodes of the tiles a process keeps mapped between searches (checksums verified once,
#: at the first load): a whole-body database or a few 1-degree tiles at 90 m, a few hundred MB of
#: per-node arrays besides the mapped files.
OPEN_TILE_NODES = 16_000_000
_open_tiles: dict[tuple[str, int, int], tuple[SkylineDatabase, SkylineGrid]] = {}
#: Guards the per-process caches (_open_tiles, _first_passes): the tiles of an in-process search
#: run on several threads at once.  Held only to look up, insert and evict, never while a tile
#: is loaded or scored.
_cache_lock = threading.Lock()


def open_tile(folder: str, tile: TileEntry, expect: tuple[int, float] | None,
              key: tuple[str, int, int] | None = None) -> tuple[SkylineDatabase, SkylineGrid]:
    """A tile's database and search grid, memory-mapped (on a Dask worker the worker maps its own
    tile) and kept for the next search of this process while the file stays the same (path, size,
    modification time: ``key``, :func:`_tile_key`, when the caller has it already).  ``expect``
    (the index's azimuth count and camera height) refuses a tile built otherwise: likelihoods over
    other azimuths or heights cannot be weighed together."""
    path = Path(folder) / tile.file
    key = _tile_key(path) if key is None else key
    with _cache_lock:
        held = _open_tiles.get(key)
    if held is None:
        db = load_database(path)
        made = (db, skyline_grid(db))
        with _cache_lock:
            # another thread may have mapped the same file meanwhile: keep the first
            held = _open_tiles.get(key)
            if held is None:
                nodes = sum(d.grid.n_nodes for d, _ in _open_tiles.values())
                while _open_tiles and nodes + db.grid.n_nodes > OPEN_TILE_NODES:
                    nodes -= _open_tiles.pop(next(iter(_open_tiles)))[0].grid.n_nodes
                held = _open_tiles[key] = made
    db, grid = held
    if expect is not None and (db.n_azimuths != expect[0] or not math.isclose(db.height_m, expect[1])):
        raise DatabaseError(f"{path}: {db.n_azimuths} azimuths at {db.height_m} m, but "
                            f"the tiled index says {expect[0]} at {expect[1]} m; rebuild the tile")
    return db, grid


def _tile_key(path: Path) -> tuple[str, int, int]:
    """A tile file's identity while it stays the same: path, size, modification time."""
    try:
        st = path.stat()
    except OSError as exc:
        raise DatabaseError(f"{path}: cannot read the tile ({exc.strerror or exc})") from None
    return str(path.resolve()), st.st_size, st.st_mtime_ns


#: Bytes of first passes a process keeps between the rounds of a tiled search, which all start from
#: each tile's first pass (the pruning floor, the grid search, the refinement): the 15 tiles of
#: the two-tile seam mosaic at +-4 deg take about 150 MB.  Oldest out first.
FIRST_PASS_BYTES = 512 * 2**20
_first_passes: dict[tuple[Any, ...], FirstPass] = {}


def _skyline_digest(skyline: Skyline) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in (skyline.azimuth_deg, skyline.elevation_deg, skyline.confidence):
        h.update(b"-" if a is None else np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()


def tile_first_pass(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams,
                    expect: tuple[int, float] | None) -> tuple[SkylineDatabase, SkylineGrid, FirstPass]:
    """The tile's database, grid and the skyline's first pass on it: made once per process and
    search, then kept (within FIRST_PASS_BYTES) for the next round of the same search."""
    tile_key = _tile_key(Path(folder) / tile.file)
    db, grid = open_tile(folder, tile, expect, key=tile_key)
    key = (tile_key, _skyline_digest(skyline), params)
    with _cache_lock:
        first = _first_passes.pop(key, None)
    if first is None or first.grid_id != id(grid.codes):  # the tile was mapped again since
        first = first_pass(grid, skyline.azimuth_deg, skyline.elevation_deg, params.sigma_deg,
                           params.heading_tolerance_deg, skyline.confidence, params.occlusion_weight,
                           params.map_sigma_m)
    with _cache_lock:
        _first_passes[key] = first
        held = sum(f.nbytes for f in _first_passes.values())
        while len(_first_passes) > 1 and held > FIRST_PASS_BYTES:
            held -= _first_passes.pop(next(iter(_first_passes))).nbytes
    return db, grid, first

