"""One tile's part of a tiled search: its first pass's floor, and its search reduced to what travels back.

Each runs where the tile is mapped: in the searching process, or as a Dask task on a worker
(:mod:`appliance.locating.tiled_search`).  What a tile's search sends back (:class:`TileOutcome`)
holds no per-node maps: the tile's own record, its best candidate's bounds and normalisers, and
its TOP_NODES most likely nodes.
"""

from __future__ import annotations

import math
import time

import numpy as np

from appliance.errors import EstimationError
from appliance.estimator import EstimateResult
from appliance.locating.position import locate
from appliance.locating.tile_cache import SearchParams, tile_first_pass
from appliance.locating.tiled_answer import TileOutcome
from appliance.locating.tiled_index import TileEntry
from appliance.skyline import Skyline
from appliance.terrain.grid import NodeGrid

#: How many of a tile's nodes (highest upper posterior first) travel back from its search: enough
#: that, when a node left behind could still join the region, the region is already wider than
#: AMBIGUOUS_CELLS and the answer ambiguous whatever the rest holds.
TOP_NODES = 4096


def tile_floor(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams,
               expect: tuple[int, float] | None = None) -> float:
    """The tile's best first-pass lower log-posterior (:attr:`appliance.estimator.FirstPass.best_lower`);
    -inf where the skyline cannot be placed on it."""
    try:
        return tile_first_pass(folder, tile, skyline, params, expect)[2].best_lower
    except EstimationError:
        return -math.inf


def search_tile(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams, *, source: str = "",
                refine: bool = True, expect: tuple[int, float] | None = None, rescore_floor: float | None = None,
                region: bool = True, learn_noise: bool = False) -> TileOutcome:
    """The ordinary estimate on one tile, with the exact refinement or without (``refine``), its
    rescoring pruned against ``rescore_floor`` (the best first-pass lower bound over every tile
    searched, :func:`tile_floor`).  A tile where the skyline cannot be placed at all (no terrain
    along its azimuths) is reported as such; the other tiles may still place it.

    ``region`` False leaves the tile's own region (its nodes and their lon/lat) out of the outcome:
    the combination reads it from the best tile only, and a round that only picks the best tile
    (:func:`appliance.locating.tile_combination.best_tile`) needs none.  A tile the skyline does not
    single a place out on (sea, a plain) holds a region of most of its nodes, whose projection to
    lon/lat costs more than the tile's search on the grid.

    ``learn_noise`` (the best tile's refinement in a search's first round) learns the noise from the
    tile's best fit (:func:`appliance.estimator.estimate`) and sends it back: the tile's posteriors are
    then on another scale than the others', and only the noise is read from it."""
    t0 = time.perf_counter()
    try:
        db, grid, first = tile_first_pass(folder, tile, skyline, params, expect)
        pos = locate(db, skyline, params.sigma_deg, params.heading_tolerance_deg, source=source, grid=grid,
                     height_m=params.height_m, occlusion_weight=params.occlusion_weight,
                     map_sigma_m=params.map_sigma_m, refine=refine, rescore_floor=rescore_floor, first=first,
                     learn_noise=learn_noise, temper=params.temper, allowed_sigma_deg=params.allowed_sigma_deg,
                     polish=params.polish)
    except EstimationError as exc:
        return TileOutcome(tile.file, str(exc), elapsed_s=time.perf_counter() - t0)
    r = pos.result
    top, up, up_un, left_max, left_max_un = _top_nodes(r)
    nodes = np.asarray(r.region_nodes, dtype=np.int64) if region else np.zeros(0, np.int64)
    g = db.grid
    return TileOutcome(
        tile.file, None, pos.to_json(db, max_cells=0), r.node, pos.lat, pos.lon, r.log_lower,
        math.log(r.upper) if r.upper > 0 else -math.inf, r.log_lower_unnormalised, r.log_upper_unnormalised,
        r.log_evidence_lower, r.log_evidence_upper, r.log_evidence_mid, math.log(g.dx_m * g.dy_m),
        (g.dx_m, g.dy_m), r.ambiguous, nodes, _lonlat(g, nodes), top.astype(np.int64), up[top], up_un[top],
        _lonlat(g, top), left_max, left_max_un, r.candidates, time.perf_counter() - t0, region,
        pos.x, pos.y, pos.crs, (*r.sigma_deg, r.temper) if r.sigma_learned else None)


def _top_nodes(r: EstimateResult) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The TOP_NODES nodes of highest unnormalised upper posterior, in that order (the order every
    tile's nodes keep over all tiles); the per-node upper posteriors, normalised and not; and the
    largest of each among the nodes not sent (-inf where all are sent)."""
    up = np.asarray(r.log_upper_map, dtype=np.float64)
    assert r.log_upper_unnormalised_map is not None
    up_un = np.asarray(r.log_upper_unnormalised_map, dtype=np.float64)
    k = min(TOP_NODES, up.size)
    top = np.argpartition(-up_un, k - 1)[:k] if k < up.size else np.arange(up.size)
    top = top[np.argsort(-up_un[top], kind="stable")]
    left = np.ones(up.size, dtype=bool)
    left[top] = False
    # the largest of the nodes not sent, read in place (no copy of the tile's other nodes)
    left_max = float(np.max(up, where=left, initial=-math.inf)) if k < up.size else -math.inf
    left_max_un = float(np.max(up_un, where=left, initial=-math.inf)) if k < up.size else -math.inf
    return top, up, up_un, left_max, left_max_un


def _lonlat(grid: NodeGrid, nodes: np.ndarray) -> np.ndarray:
    """The nodes' (lon, lat), one row each."""
    if nodes.size == 0:
        return np.zeros((0, 2))
    lon, lat = grid.xy_to_lonlat(*grid.node_xy(nodes))
    return np.column_stack([np.atleast_1d(lon), np.atleast_1d(lat)]).astype(np.float64)
