"""A whole-body search's answer fitted on the map's own surface rather than on its facets' grid.

The facets resample the map (:mod:`appliance.terrain.whole_body`), and on their grid alone the
place a skyline was seen from can rank far down the region.  The region's contending places are
therefore screened and fitted on renders of the map itself (:mod:`appliance.locating.verification`),
and the best fit is the answer; the posterior bounds and the region stay the grid's.
"""

from __future__ import annotations

import dataclasses
import math

from appliance.bodies import body_named, geodesic_distance_m
from appliance.estimator import confidence
from appliance.estimator.estimate import AMBIGUOUS_CELLS, SAME_ANSWER_CELLS
from appliance.estimator.likelihood import sigma_midpoint
from appliance.estimator.noise import learned_noise, tempered_covariance
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
#: A place fitted on the map is a rival of the best fit when its likelihood at the learned noise,
#: tempered, is at least this share of the best's: what a 95 % statement leaves out.
RIVAL_SHARE = 0.05


def fit_on_surface(index: TiledIndex, est: TileCombination, surface: Dem, skyline: Skyline,
                   params: SearchParams, floor_deg: float = confidence.SIGMA_FLOOR_DEG) -> TileCombination | None:
    """``est`` (the facets' grid answer) with its answer fitted on the map's own surface: the
    contending places (the best, then the region's distinct places by upper posterior, at most
    SCREEN_PLACES) screened on renders of the map, the grid's best and the SURFACE_PLACES - 1 that
    screen best each fitted between nodes on renders of the map, the best fit kept
    (:mod:`appliance.locating.verification`) with the noise its residuals give (sigma at least
    ``floor_deg``) and its covariance at that noise.  The posterior bounds and the region stay the grid's; a fit
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
    w = min(fits, key=lambda f: f.cost)
    best = surface_fit(index, w, len(places), len(fits), len(candidates), floor_deg)
    return with_surface_fit(index, est, dataclasses.replace(best, rivals=_rival_fits(fits, w, best, spacing, surface)),
                            params.sigma_deg[1])


def _rival_fits(fits: list[PlaceFit], w: PlaceFit, best: SurfaceFit, spacing_m: float, surface: Dem) -> int:
    """How many of the places fitted, farther than SAME_ANSWER_CELLS from the best fit ``w``, fit
    nearly as well at the noise learned from it (``best``'s): their likelihood, tempered, at least
    RIVAL_SHARE of the best's."""
    if best.noise is None or w.exact is None:
        return 0
    lo, hi, temper = best.noise
    sig2 = sigma_midpoint(lo, hi) ** 2
    reach = -2.0 * math.log(RIVAL_SHARE)
    out = 0
    for f in fits:
        if f is w or f.exact is None:
            continue
        far = geodesic_distance_m(w.lat, w.lon, f.lat, f.lon, surface.body) > SAME_ANSWER_CELLS * spacing_m
        if far and temper * (f.exact.ssd - w.exact.ssd) / sig2 < reach:
            out += 1
    return out


def surface_fit(index: TiledIndex, w: PlaceFit, places: int, fits: int, candidates: int,
                floor_deg: float) -> SurfaceFit:
    """The fit ``w`` (the best of ``fits``) as the answer records it, with the noise its residuals
    give (sigma's interval at least ``floor_deg``, the tempering) and its covariance at that noise;
    its distance from the grid's best place is measured by :func:`with_surface_fit`."""
    tile = next(t for t in index.tiles if t.file == w.place.tile)
    db = open_tile(str(index.folder), tile, None)[0]
    x, y = db.grid.lonlat_to_xy(w.lon, w.lat)
    noise: tuple[float, float, float] | None = None
    cov_m2 = None
    if w.exact is not None and w.exact.residual_deg is not None:
        noise = learned_noise(w.exact.residual_deg, floor_deg, w.rms_deg)
        cov = tempered_covariance(w.exact, sigma_midpoint(noise[0], noise[1]), noise[2])
        if cov is not None:
            cov_m2 = confidence.grid_to_east_north(cov, w.cell_m, w.cell_m, w.grid_north_deg)
    return SurfaceFit(w.lat, w.lon, float(x), float(y), crs_name(db), w.place.tile, w.place.node,
                      w.heading_correction_deg, w.rms_deg, places, math.nan, candidates, cov_m2, noise, fits)


def with_surface_fit(index: TiledIndex, est: TileCombination, fit: SurfaceFit,
                     sigma_hi_deg: float) -> TileCombination:
    """``est`` answered by ``fit``, with a note of the fits.

    Where the fit learned the noise, the answer is ambiguous when the grid's region is (too many
    cells, a rival tile), when places fitted elsewhere on the map come near the fit
    (:func:`_rival_fits`), or when the fit's RMS exceeds ``sigma_hi_deg`` (the search's given
    interval's upper end: a skyline from no place on the map); the grid's own fit, worse than the
    map's by the facets' resampling, is no longer the measure of the match.  Without a noise learned,
    a fit farther than SAME_ANSWER_CELLS from ``est``'s best place on the grid is ambiguous."""
    spacing = max(est.best.cell_size_m)
    off = geodesic_distance_m(est.best.lat, est.best.lon, fit.lat, fit.lon, body_named(index.body))
    fit = dataclasses.replace(fit, grid_distance_m=off)
    notes = list(est.notes) + [f"fitted on the map's own surface: {fit.screened} contending place(s) screened, "
                               f"{fit.places} looked at, {fit.fits} fitted, the best {fit.rms_deg:.2f} deg RMS"]
    ambiguous = est.ambiguous
    if fit.noise is not None:
        ambiguous = est.rival_tiles or bool(est.overflowed) or len(est.region) > AMBIGUOUS_CELLS
        # the best tile's own verdicts on the grid (its fit's match, its rival fits) decide no more:
        # their notes go with them, the combination's own stay
        own = {n for n in est.best.record.get("notes", []) if n.startswith("ambiguous")}
        notes = [n for n in notes if n not in own]
        if fit.rms_deg > sigma_hi_deg:
            ambiguous = True
            notes.append(f"ambiguous: poor match: fitted on the map's own surface, residual {fit.rms_deg:.2f} deg "
                         f"RMS, more than the {sigma_hi_deg:.2f} deg the search allows")
    if fit.rivals:
        ambiguous = True
        notes.append(f"ambiguous: fitted on the map's own surface, {fit.rivals} place(s) more than "
                     f"{SAME_ANSWER_CELLS:.0f} cells away fit nearly as well (within a likelihood ratio of "
                     f"{1 / RIVAL_SHARE:.0f})")
    elif off > SAME_ANSWER_CELLS * spacing and fit.noise is None:
        ambiguous = True
        notes.append(f"ambiguous: fitted on the map's own surface, the skyline lies {off / 1000:.1f} km from the "
                     f"grid's best place (in {est.best.file})")
    return dataclasses.replace(est, fit=fit, ambiguous=ambiguous, notes=notes)
