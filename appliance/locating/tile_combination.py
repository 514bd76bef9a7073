"""The combination of a tiled search's tiles: their searches normalised over all of them as one grid would be.

Why the combination needs more than each tile's answer: every tile's posteriors are normalised
within the tile, so each tile, even one the skyline was never seen from, holds some node of
posterior near one.  Each tile therefore also reports its normalisers (the log of the summed
unnormalised lower, upper and midpoint posteriors, :class:`~appliance.estimator.EstimateResult`)
and its best candidate's unnormalised bounds; with them the best candidate's lower and upper
posterior are recomputed over all tiles exactly, and every other node's upper posterior is bounded
from above (:func:`appliance.estimator.likelihood.log_upper_with_others`).  The region is then
every node, in any tile, whose bound reaches the best's lower posterior; a node of it in another
tile, away from the best, is a rival the skyline does not rule out, and the answer is ambiguous.

The prior is uniform per unit area: a tile's evidence is weighed by its own cell area, which is the
same in every tile of one lattice and differs between the facets of a whole-body database
(:mod:`appliance.terrain.whole_body`), each on its own grid; every position (lon/lat) of the
region comes from its own tile's grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from appliance.bodies import body_named
from appliance.errors import EstimationError
from appliance.estimator.estimate import AMBIGUOUS_CELLS, SAME_ANSWER_CELLS
from appliance.estimator.likelihood import log_upper_with_others
from appliance.locating.position import Position, place_tiled
from appliance.locating.tiled_answer import RegionCell, TileCombination, TileOutcome


def _log_sum(values: Sequence[float]) -> float:
    v = [x for x in values if x > -math.inf]
    return float(np.logaddexp.reduce(np.asarray(v))) if v else -math.inf



def _placed(outcomes: Sequence[TileOutcome]) -> tuple[list[TileOutcome], list[TileOutcome]]:
    """Every outcome in tile order, and those that placed the skyline; EstimationError if none did."""
    outcomes = sorted(outcomes, key=lambda o: o.file)
    ok = [o for o in outcomes if o.error is None]
    if not ok:
        raise EstimationError(f"no searched tile can place the skyline ({outcomes[0].error})" if outcomes
                              else "no tile was searched")
    return outcomes, ok


def _global_bounds(ok: Sequence[TileOutcome]) -> tuple[list[float], list[float]]:
    """Each tile's best candidate's lower and upper log-posterior over all the tiles."""
    # unnormalised sums weighed by each tile's cell area: the prior is uniform per unit area
    ev_lo = [o.log_evidence_lower + o.log_cell_area for o in ok]
    ev_up = [o.log_evidence_upper + o.log_cell_area for o in ok]
    g_lower, g_upper = [], []
    for i, o in enumerate(ok):
        # within the tile, log_lower = lo - log(a + rest of the tiles' uppers): recover that
        # denominator, then add the other tiles' summed upper posteriors to it (and alike for upper)
        lo, up = o.lo_unnormalised + o.log_cell_area, o.up_unnormalised + o.log_cell_area
        den_lo = lo - o.log_lower
        den_up = up - o.log_upper
        g_lower.append(lo - float(np.logaddexp(den_lo, _others(ev_up, i))))
        g_upper.append(min(up - float(np.logaddexp(den_up, _others(ev_lo, i))), 0.0))
    return g_lower, g_upper


def _others(values: list[float], i: int) -> float:
    return _log_sum([v for j, v in enumerate(values) if j != i])


def best_tile(outcomes: Sequence[TileOutcome]) -> str:
    """The tile :func:`combine` finds the best candidate in, without combining the regions (which
    the outcomes may leave out)."""
    _, ok = _placed(outcomes)
    g_lower, _ = _global_bounds(ok)
    return ok[int(np.argmax(g_lower))].file


def combine(outcomes: Sequence[TileOutcome], body: str, *, elapsed_s: float = 0.0, source: str = "") -> Position:
    """The answer to the skyline ``source`` from the tiles' searches (:func:`combine_tiles`)."""
    return place_tiled(combine_tiles(outcomes, body, elapsed_s), source)


def combine_tiles(outcomes: Sequence[TileOutcome], body: str, elapsed_s: float = 0.0) -> TileCombination:
    """Normalise the tiles' searches over all of them: the best candidate, its posterior bounds, the
    region across tiles and whether the answer is ambiguous (module docstring).  The region's own
    cells come from the best tile's outcome only, which must carry them (``has_region``)."""
    outcomes, ok = _placed(outcomes)
    failed = tuple(o.file for o in outcomes if o.error is not None)
    ev_lo = [o.log_evidence_lower + o.log_cell_area for o in ok]
    ev_mid = [o.log_evidence_mid + o.log_cell_area for o in ok]
    g_lower, g_upper = _global_bounds(ok)
    b = int(np.argmax(g_lower))
    best = ok[b]
    if not best.has_region:
        raise ValueError(f"the best tile's outcome ({best.file}) was searched without its region")
    best_lower = g_lower[b]
    total_mid = _log_sum(ev_mid)
    share = {o.file: math.exp(ev_mid[i] - total_mid) for i, o in enumerate(ok)}

    region: list[RegionCell] = []
    rival = False
    overflowed: list[str] = []
    area = 0.0
    for i, o in enumerate(ok):
        cells, overflow = _tile_cells(o, o is best, best_lower, _others(ev_lo, i))
        if overflow:
            overflowed.append(o.file)
        region += cells
        area += math.exp(o.log_cell_area) * len(cells)
        if cells and o is not best and not rival:
            rival = _far_from(best, cells, body)
    notes = _notes(best, region, overflowed, rival, failed)
    ambiguous = bool(best.ambiguous or rival or overflowed or len(region) > AMBIGUOUS_CELLS)
    return TileCombination(best, tuple(o.file for o in outcomes), failed, best_lower, g_upper[b], tuple(region),
                           area, ambiguous, share, tuple(overflowed), notes, body, elapsed_s,
                           sum(o.candidates for o in ok), rival_tiles=rival)


def _tile_cells(o: TileOutcome, is_best: bool, best_lower: float, others_lower: float) -> tuple[list[RegionCell], bool]:
    """The tile's cells of the region: its sent nodes whose upper posterior over all tiles may reach
    the best's lower one (``others_lower``: the other tiles' summed lower posteriors), and the best
    tile's own region; and whether a node it did not send could reach it too."""
    bound = log_upper_with_others(o.top_log_upper, o.top_log_upper_unnormalised + o.log_cell_area, others_lower)
    keep = bound >= best_lower
    nodes = set(int(v) for v in o.top_nodes[keep])
    lonlat = {int(v): (float(p[0]), float(p[1])) for v, p in zip(o.top_nodes[keep], o.top_lonlat[keep])}
    upper = {int(v): float(u) + o.log_cell_area for v, u in zip(o.top_nodes[keep],
                                                                  o.top_log_upper_unnormalised[keep])}
    if is_best:
        for v, p in zip(o.region_nodes, o.region_lonlat):
            lonlat.setdefault(int(v), (float(p[0]), float(p[1])))
        nodes |= set(int(v) for v in o.region_nodes)
    left = log_upper_with_others(np.array([o.left_max_log_upper]),
                                  np.array([o.left_max_log_upper_unnormalised + o.log_cell_area]), others_lower)[0]
    overflow = bool(o.left_max_log_upper > -math.inf and left >= best_lower)
    return [RegionCell(o.file, v, *lonlat[v], upper.get(v, -math.inf)) for v in sorted(nodes)], overflow


def _far_from(best: TileOutcome, cells: list[RegionCell], body: str) -> bool:
    """Whether a cell lies more than SAME_ANSWER_CELLS of the best tile's cells from its best candidate."""
    reach_m = SAME_ANSWER_CELLS * max(best.cell_size_m)
    lon, lat = np.array([(c.lon, c.lat) for c in cells]).T
    _, _, dist = body_named(body).geod.inv(np.full(lon.size, best.lon), np.full(lat.size, best.lat), lon, lat)
    return bool(np.any(np.asarray(dist) > reach_m))


def _notes(best: TileOutcome, region: list[RegionCell], overflowed: list[str], rival: bool,
           failed: tuple[str, ...]) -> list[str]:
    """The combined answer's notes: the best tile's own (its 'ambiguous' ones only where it stays
    ambiguous), then why the combination is ambiguous and which tiles could not place the skyline."""
    notes = [n for n in best.record.get("notes", []) if not n.startswith("ambiguous")]
    if best.ambiguous:
        notes += [n for n in best.record.get("notes", []) if n.startswith("ambiguous")]
    if len(region) > AMBIGUOUS_CELLS or overflowed:
        notes.append(f"ambiguous: {len(region)}{'+' if overflowed else ''} cells across "
                     f"{len({c.tile for c in region})} tiles are as likely as the best; the skyline does not "
                     "single out one position")
    if rival:
        tiles = sorted({c.tile for c in region if c.tile != best.file})
        notes.append(f"ambiguous: tile {', '.join(tiles)} holds a place more than {SAME_ANSWER_CELLS:.0f} cells "
                     f"from the best (in {best.file}) whose upper posterior reaches the best's lower one")
    if failed:
        notes.append(f"{len(failed)} tile(s) could not place the skyline at all: {', '.join(failed)}")
    return notes
