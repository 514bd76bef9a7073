"""A whole-body search's answer fitted on the map's own surface rather than on its facets' grid.

The facets resample the map (:mod:`appliance.terrain.whole_body`), and on their grid alone the
place a skyline was seen from can rank far down the region.  The region's contending places are
therefore screened and fitted on renders of the map itself (:mod:`appliance.locating.verification`),
and the best fit is the answer; the posterior bounds and the region stay the grid's.
"""

from __future__ import annotations

import dataclasses

from appliance.bodies import body_named, geodesic_distance_m
from appliance.estimator.estimate import SAME_ANSWER_CELLS
from appliance.locating.search_grid import crs_name
from appliance.locating.tile_cache import SearchParams, open_tile
from appliance.locating.tiled_answer import SurfaceFit, TileCombination
from appliance.locating.tiled_index import TiledIndex
from appliance.locating.verification import FitSettings, Place, PlaceFit, distinct_places, fit_places, screen_places
from appliance.skyline import Skyline
from appliance.terrain.dem import Dem

#: At most this many of the region's distinct places (by upper posterior on the facets' grid) are
#: screened on the map (:func:`appliance.locating.verification.screen_places`).
SCREEN_PLACES = 400
#: Places fitted on the map: the grid's best place and the SURFACE_PLACES - 1 that screen best.
SURFACE_PLACES = 24


def fit_on_surface(index: TiledIndex, est: TileCombination, surface: Dem, skyline: Skyline,
                   params: SearchParams) -> TileCombination | None:
    """``est`` (the facets' grid answer) with its answer fitted on the map's own surface: the
    contending places (the best, then the region's distinct places by upper posterior, at most
    SCREEN_PLACES) screened on renders of the map, the grid's best and the SURFACE_PLACES - 1 that
    screen best each fitted between nodes on renders of the map, the best fit kept
    (:mod:`appliance.locating.verification`).  The posterior bounds and the region stay the grid's; a fit
    farther than SAME_ANSWER_CELLS from the grid's best makes the answer ambiguous.  None where no
    place can be fitted."""
    spacing = max(est.best.cell_size_m)
    ranked = [Place(est.best.file, est.best.node, est.best.lat, est.best.lon)]
    ranked += [Place(c.tile, c.node, c.lat, c.lon) for c in sorted(est.region, key=lambda c: -c.log_upper_unnormalised)]
    candidates = distinct_places(ranked, SCREEN_PLACES, SAME_ANSWER_CELLS * spacing, surface)
    settings = FitSettings(
        height_m=index.height_m if params.height_m is None else params.height_m, n_azimuths=index.n_azimuths,
        reach_m=index.max_range_m, refraction=index.raw.get("refraction"), node_spacing_m=spacing,
        sigma_deg=params.sigma_deg, heading_tolerance_deg=params.heading_tolerance_deg,
        occlusion_weight=params.occlusion_weight, map_sigma_m=params.map_sigma_m)
    places = candidates
    if len(candidates) > SURFACE_PLACES:
        # the grid's best place always, then those that screen best on the map
        screened = screen_places(surface, skyline, candidates[1:], settings)
        places = candidates[:1] + [p for _, p in screened[:SURFACE_PLACES - 1]]
    fits = fit_places(surface, skyline, places, settings)
    if not fits:
        return None
    return _with_fit(index, est, min(fits, key=lambda f: f.cost), len(places), len(fits), len(candidates))


def _with_fit(index: TiledIndex, est: TileCombination, w: PlaceFit, places: int, fits: int,
              candidates: int) -> TileCombination:
    """``est`` answered by the fit ``w``, with a note of the fits and, where the fit lies farther
    than SAME_ANSWER_CELLS from the grid's best place, ambiguous."""
    spacing = max(est.best.cell_size_m)
    tile = next(t for t in index.tiles if t.file == w.place.tile)
    db = open_tile(str(index.folder), tile, None)[0]
    x, y = db.grid.lonlat_to_xy(w.lon, w.lat)
    off = geodesic_distance_m(est.best.lat, est.best.lon, w.lat, w.lon, body_named(index.body))
    notes = list(est.notes) + [f"fitted on the map's own surface: {candidates} contending place(s) screened, "
                               f"{places} looked at, {fits} fitted, the best {w.rms_deg:.2f} deg RMS"]
    ambiguous = est.ambiguous
    if off > SAME_ANSWER_CELLS * spacing:
        ambiguous = True
        notes.append(f"ambiguous: fitted on the map's own surface, the skyline lies {off / 1000:.1f} km from the "
                     f"grid's best place (in {est.best.file})")
    fit = SurfaceFit(w.lat, w.lon, float(x), float(y), crs_name(db), w.place.tile, w.place.node,
                     w.heading_correction_deg, w.rms_deg, places, off, candidates)
    return dataclasses.replace(est, fit=fit, ambiguous=ambiguous, notes=notes)
