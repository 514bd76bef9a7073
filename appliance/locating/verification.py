"""Exact fits of a whole-body search's contending places on the source map's own surface.

A whole-body database's facets resample the map onto their own grids
(:mod:`appliance.terrain.whole_body`).  A camera 1.5 m above a map of 7.6 km pixels sees mostly the
slopes under it, and the resampled surface's slopes differ from the map's: the facets' skylines
stand 0.1-0.6 deg RMS off the map's own, and between nodes 3.8 km apart the skyline changes by more
than the measurement's noise.  The grid search can then rank a place hundreds of km away above the
place the skyline was seen from, both inside its region (neither ruled out).

Each contending place is therefore fitted between nodes on renders of the map itself: a local
grid around it in an azimuthal equidistant frame, a few cells per node spacing and per map pixel
(:func:`local_cell_m`), whose bilinear surface follows the map's; a few looks around the node (one
render each, every heading the compass allows) at every place, more at the places whose first looks
come lowest, then the exact refinement (:func:`appliance.estimator.exact.refine`) from the best of
them.  The place whose fit explains the skyline best is the answer.  Where more places contend
than can be fitted, each is first screened (:func:`screen_places`): a few quick looks on a coarser
local grid, one render each, which rank the places on the map itself rather than on the facets'
skylines.  The fits only choose among places the database could not rule out; the posterior
bounds, the region and whether the answer is ambiguous stay the grid's.

Nothing here touches devices or logs: a map, places and a skyline in, fits out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pyproj import Transformer

from appliance.estimator.estimate import OCCLUSION_WEIGHT, measured_on_grid
from appliance.estimator.exact import SCREEN_SCAN_DEG, START_SPREAD_CELLS, Fit, Model, Terrain, refine, render, screen
from appliance.estimator.likelihood import occlusion_cap_deg2, sigma_midpoint
from appliance.skyline import Skyline
from appliance.terrain.dem import Dem
from appliance.terrain.horizon import local_aeqd

#: The local grid's cell: a quarter of the node spacing, and a quarter of the map's pixel where
#: that is smaller (near the poles a longitude pixel narrows: 1.3 km at 80 deg on the LOLA map),
#: but not below a sixteenth of the node spacing.  Sampled so, the map's bilinear surface read
#: bilinearly again gives skylines within 0.01-0.1 deg of the map's own at most places (0.2-0.4
#: deg where the eye's near slopes are steep; 0.15-0.2 deg at 80 deg with the node's quarter).
FINE_PER_NODE = 4
FINE_PER_PIXEL = 4
MAX_FINE_PER_NODE = 16
#: Where the pixel asks for a finer cell than the node's quarter, that cell holds out to NEAR_NODES
#: node spacings from the eye and the node's quarter beyond (the heights' detail matters near at
#: hand); each grid reaches MARGIN_NODES farther, for eyes off the place's node.
NEAR_NODES = 10
MARGIN_NODES = 2
#: Looks around a place's node, in node spacings: a lattice LOOK_STEP_NODES apart out to
#: LOOK_REACH_NODES along each axis (the place stands for every region cell within two spacings of
#: it), then half that step around the best FITS_PER_PLACE of them.  From a start half a spacing
#: off, a fit on a skyline seen 1.5 m above the ground can stall a kilometre short.
LOOK_STEP_NODES = 0.5
LOOK_REACH_NODES = 1.0
#: Every contending place first gets the lattice's looks within FIRST_LOOK_REACH_NODES of its node;
#: the FULL_PLACES whose first looks come lowest get the rest of the looks and the fits.
FIRST_LOOK_REACH_NODES = 0.5
FULL_PLACES = 6
#: Full fits per place, from its best-looking starts.
FITS_PER_PLACE = 2
#: How far (node spacings) a fit may wander from the place's node.
MAX_OFFSET_NODES = 1.5
#: The screening of many places before the fits (:func:`screen_places`): each place's terrain has
#: the node's quarter out to NEAR_NODES (not finer where the map's pixel is narrower) and one node
#: spacing beyond (a sixteenth of the samples: the map's pixel is coarser than that below 60 deg of
#: latitude), and gets one quick look (:meth:`PlaceSearch.quick_look`) at each of SCREEN_LOOKS
#: (node spacings south and east of its node).
SCREEN_OUTER_PER_NODE = 1.0
SCREEN_LOOKS = ((0.0, 0.0), (-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5))
#: A quick look turns its one render across the heading bounds in whole azimuth steps, then in
#: steps of 1 / SCREEN_TURN_SPLIT of one around the best.
SCREEN_TURN_SPLIT = 4


@dataclass(frozen=True)
class Place:
    """A contending place of a search: its tile, node there and position."""

    tile: str
    node: int
    lat: float
    lon: float


@dataclass(frozen=True)
class PlaceFit:
    """The exact fit of a skyline near ``place`` on the map's surface: where it ended, the heading
    correction (deg, the compass's error), its cost (the residual sum at sigma's midpoint,
    chi-square units) and RMS residual (deg); the exact fit itself (its residuals and curvature, in
    cells of ``cell_m`` of a local grid whose north stands ``grid_north_deg`` from true north at the fit)."""

    place: Place
    lat: float
    lon: float
    heading_correction_deg: float
    cost: float
    rms_deg: float
    exact: Fit | None = None
    cell_m: float = math.nan
    grid_north_deg: float = 0.0


@dataclass(frozen=True)
class FitSettings:
    """What every place's fit shares: the database's camera height, azimuths, reach and refraction,
    and the search's sigma interval, heading tolerance, occlusion weight and map error."""

    height_m: float
    n_azimuths: int
    reach_m: float
    refraction: float | None
    node_spacing_m: float
    sigma_deg: tuple[float, float]
    heading_tolerance_deg: float | None
    occlusion_weight: float = OCCLUSION_WEIGHT
    map_sigma_m: float = 0.0


class LocalFrame:
    """The azimuthal equidistant frame centred on (lat, lon) on the map's body: metres east (x) and
    north (y) of the centre to lon/lat.  On a sphere in closed form; on an ellipsoid through PROJ."""

    def __init__(self, dem: Dem, lat: float, lon: float) -> None:
        self.lat0, self.lon0 = math.radians(lat), lon
        ell = dem.crs.ellipsoid
        a = ell.semi_major_metre if ell is not None else dem.body.semi_major_m
        b = ell.semi_minor_metre if ell is not None else a
        self.radius_m = a if a == b else None
        self._proj = None if a == b else Transformer.from_crs(local_aeqd(dem, lat, lon), dem.crs.geodetic_crs,
                                                              always_xy=True)

    def lonlat(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._proj is not None:
            lon, lat = self._proj.transform(x, y)
            return np.asarray(lon), np.asarray(lat)
        assert self.radius_m is not None
        x, y = np.asarray(x, float), np.asarray(y, float)
        rho = np.hypot(x, y)
        c = rho / self.radius_m
        sin_c, cos_c = np.sin(c), np.cos(c)
        s0, c0 = math.sin(self.lat0), math.cos(self.lat0)
        ratio = np.divide(y * sin_c, rho, out=np.zeros_like(rho), where=rho > 0)
        lat = np.arcsin(np.clip(cos_c * s0 + ratio * c0, -1.0, 1.0))
        lon = self.lon0 + np.degrees(np.arctan2(x * sin_c, rho * c0 * cos_c - y * s0 * sin_c))
        return (lon + 180.0) % 360.0 - 180.0, np.degrees(lat)


def quick_render(terrain: Terrain, cell_m: float, row: float, col: float, azimuth_deg: np.ndarray,
                 height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Elevation (deg) and range (m) per grid azimuth from fractional (row, col) of a local grid
    (:func:`local_terrain`), as :func:`appliance.estimator.exact.render` renders them with the looks'
    schedule of ray samples, its outer grid too (two per cent of the distance, an outer cell at most)
    rather than the fits' finer one."""
    el, far, _ = render(terrain, cell_m, cell_m, row, col, azimuth_deg,
                        terrain.look_distances(cell_m), height_m, outer_looks=True)
    return el, far


def _grid_heights(dem: Dem, frame: LocalFrame, cell_m: float, half: int) -> np.ndarray:
    """The map's heights at the frame's nodes (i - half, half - j) * cell_m east and north."""
    n = 2 * half + 1
    k = (np.arange(n) - half) * cell_m
    lon, lat = frame.lonlat(np.broadcast_to(k[None, :], (n, n)), np.broadcast_to(-k[:, None], (n, n)))
    return dem.sample_lonlat(lon, lat)


def local_terrain(dem: Dem, lat: float, lon: float, cell_m: float, *, reach_m: float, height_m: float,
                  r_eff_m: float, margin_m: float, outer_cell_m: float | None = None,
                  near_reach_m: float = math.inf) -> tuple[Terrain, LocalFrame]:
    """The map's heights on a square grid of ``cell_m`` around (lat, lon), in the azimuthal
    equidistant frame centred there (grid north is true north at the centre), out to ``reach_m``
    and ``margin_m`` beyond (for eyes that far from the centre); the centre is node (n // 2, n // 2),
    rows run south.  With ``outer_cell_m`` (coarser), the fine grid reaches ``near_reach_m`` only,
    and an outer grid of that cell the rest (:class:`~appliance.estimator.exact.Terrain`).
    Returns the terrain and its frame."""
    frame = LocalFrame(dem, lat, lon)
    if outer_cell_m is None or outer_cell_m <= cell_m or near_reach_m >= reach_m:
        half = int(math.ceil((reach_m + margin_m) / cell_m))
        heights = _grid_heights(dem, frame, cell_m, half)
        return Terrain(heights, 0, 0, np.zeros(heights.size), height_m, r_eff_m, reach_m), frame
    half_out = int(math.ceil((reach_m + margin_m) / outer_cell_m))
    outer = Terrain(_grid_heights(dem, frame, outer_cell_m, half_out), 0, 0, np.zeros(1), height_m, r_eff_m,
                    reach_m)
    half = int(math.ceil((near_reach_m + margin_m) / cell_m))
    heights = _grid_heights(dem, frame, cell_m, half)
    return Terrain(heights, 0, 0, np.zeros(heights.size), height_m, r_eff_m, reach_m, outer, outer_cell_m / cell_m,
                   near_reach_m), frame


def local_cell_m(dem: Dem, lat: float, lon: float, node_spacing_m: float) -> float:
    """The local grid's cell at (lat, lon) (FINE_PER_NODE, FINE_PER_PIXEL, MAX_FINE_PER_NODE)."""
    fine = min(node_spacing_m / FINE_PER_NODE, min(dem.resolution_m((lon, lat))) / FINE_PER_PIXEL)
    return max(fine, node_spacing_m / MAX_FINE_PER_NODE)


def _look_heading(terrain: Terrain, cell_m: float, m: np.ndarray, row: float, col: float, *, height_m: float,
                  bounds: tuple[float, float]) -> float | None:
    """The heading (deg, a whole azimuth step) within ``bounds`` whose shift of one render at
    (row, col) fits ``m`` best; None where the render sees too little."""
    n = m.size
    step = 360.0 / n
    s, _, _ = render(terrain, cell_m, cell_m, row, col, np.arange(n) * step, terrain.look_distances(cell_m), height_m)
    if np.isfinite(s).sum() < 0.9 * n:
        return None
    lo, hi = bounds
    shifts = np.arange(math.ceil(lo / step), math.floor(hi / step) + 1) if hi - lo < 360.0 else np.arange(n)
    shifts = shifts if shifts.size else np.array([0])
    idx = (np.arange(n)[None, :] + shifts[:, None]) % n
    d = m[None, :] - s[idx]
    ssd = np.nansum(d * d, axis=1)
    return float(shifts[int(np.argmin(ssd))] * step)


class PlaceSearch:
    """The search for a skyline's fit near one place on the map's own surface: its local terrain,
    the looks made so far (cost, row and column offsets in node spacings, heading) and the fit."""

    def __init__(self, dem: Dem, skyline: Skyline, place: Place, settings: FitSettings,
                 screening: bool = False) -> None:
        """``screening``: terrain for quick looks only (:func:`screen_places`): the node's quarter
        out to NEAR_NODES whatever the map's pixel, one node spacing beyond (SCREEN_OUTER_PER_NODE)."""
        self.dem, self.place, self.settings = dem, place, settings
        self.m, w = measured_on_grid(skyline.azimuth_deg, skyline.elevation_deg, skyline.confidence,
                                     settings.n_azimuths)
        node = settings.node_spacing_m
        self.cell = node / FINE_PER_NODE if screening else local_cell_m(dem, place.lat, place.lon, node)
        self.per_node = node / self.cell
        r_eff = dem.body.effective_radius_m(settings.refraction)
        outer = node / (SCREEN_OUTER_PER_NODE if screening else FINE_PER_NODE)
        self.terrain, self.frame = local_terrain(dem, place.lat, place.lon, self.cell, reach_m=settings.reach_m,
                                                 height_m=settings.height_m, r_eff_m=r_eff,
                                                 margin_m=MARGIN_NODES * node, outer_cell_m=outer,
                                                 near_reach_m=NEAR_NODES * node)
        self.centre = self.terrain.heights_m.shape[1] // 2
        self.sig_ref = sigma_midpoint(*settings.sigma_deg)
        self.model = Model(w, occlusion_cap_deg2(settings.occlusion_weight, self.sig_ref), settings.map_sigma_m)
        tol = settings.heading_tolerance_deg
        step = 360.0 / settings.n_azimuths
        self.bounds = (-180.0, 180.0) if tol is None else (-tol - step, tol + step)
        self.looks: list[tuple[float, float, float, float]] = []

    @property
    def best_look(self) -> float:
        """The lowest cost of the looks made so far (inf before any)."""
        return min((v[0] for v in self.looks), default=math.inf)

    def look(self, dr: float, dc: float) -> None:
        """One look from ``dr``, ``dc`` node spacings south and east of the place's node: one render,
        every heading the bounds allow (:func:`appliance.estimator.exact.screen`)."""
        if not np.isfinite(self.m).any():
            return
        row, col = self.centre + dr * self.per_node, self.centre + dc * self.per_node
        lo, hi = self.bounds
        # a look scans SCREEN_SCAN_DEG either side of its start: a compass's window needs no first guess
        heading = 0.5 * (lo + hi) if hi - lo <= 2.0 * SCREEN_SCAN_DEG else _look_heading(
            self.terrain, self.cell, self.m, row, col, height_m=self.settings.height_m, bounds=self.bounds)
        if heading is not None:
            cost, heading = screen(self.terrain, self.cell, self.cell, self.m, row, col, 0.0, heading, self.bounds,
                                   self.settings.height_m, self.sig_ref, self.model)
            if math.isfinite(cost):
                self.looks.append((cost, dr, dc, heading))

    def quick_look(self, dr: float, dc: float) -> float:
        """The cost (chi-square units at sigma's midpoint, as :meth:`look`'s) of one render from
        ``dr``, ``dc`` node spacings south and east of the place's node, turned to its best heading
        within the bounds: whole azimuth steps, then 1 / SCREEN_TURN_SPLIT of one around the best
        (no eye-height fit, no heading scan between renders: a ranking, cheaper than a look).  inf
        where the render sees too little."""
        m = self.m
        n = m.size
        valid = np.isfinite(m)
        if not valid.any():
            return math.inf
        step = 360.0 / n
        az = np.arange(n) * step
        row, col = self.centre + dr * self.per_node, self.centre + dc * self.per_node
        s, d = quick_render(self.terrain, self.cell, row, col, az, self.settings.height_m)
        ok = np.isfinite(s) & np.isfinite(d)
        if ok.sum() < 0.9 * n:
            return math.inf
        if not ok.all():
            s = np.interp(az, az[ok], s[ok], period=360.0)
            d = np.interp(az, az[ok], d[ok], period=360.0)
        u = self.model.weights(valid, d, self.sig_ref)
        mz = np.where(valid, m, 0.0)
        lo, hi = self.bounds
        whole = np.arange(math.ceil(lo / step), math.floor(hi / step) + 1) if hi - lo < 360.0 else np.arange(n)
        if whole.size == 0:
            whole = np.array([0])
        idx = (np.arange(n)[None, :] + whole[:, None]) % n
        k = int(np.argmin(self.model.cost(np.where(valid, mz - s[idx], 0.0), u)))
        split = SCREEN_TURN_SPLIT
        turns = (whole[k] + np.arange(-split, split + 1) / split) * step
        turns = turns[(turns >= lo) & (turns <= hi)] if hi - lo < 360.0 else turns
        sky = np.interp(((az[None, :] + turns[:, None]) % 360.0).ravel(), az, s, period=360.0).reshape(turns.size, n)
        return float(np.min(self.model.cost(np.where(valid, mz - sky, 0.0), u))) / self.sig_ref**2

    def look_around(self, reach_nodes: float, step_nodes: float) -> None:
        """Looks on a lattice ``step_nodes`` apart out to ``reach_nodes`` along each axis (those not
        made yet)."""
        k = int(round(reach_nodes / step_nodes))
        done = {(dr, dc) for _, dr, dc, _ in self.looks}
        for dr in np.arange(-k, k + 1) * step_nodes:
            for dc in np.arange(-k, k + 1) * step_nodes:
                if (float(dr), float(dc)) not in done:
                    self.look(float(dr), float(dc))

    def fit(self) -> PlaceFit | None:
        """The full search: the look lattice (LOOK_STEP_NODES out to LOOK_REACH_NODES), half that
        step around the best FITS_PER_PLACE looks, then the exact refinement from the best of all.
        None where the map around the place cannot be rendered or the skyline fits nowhere near."""
        self.look_around(LOOK_REACH_NODES, LOOK_STEP_NODES)
        half = 0.5 * LOOK_STEP_NODES
        for _, dr0, dc0, _ in sorted(self.looks)[:FITS_PER_PLACE]:
            for dr in (-half, 0.0, half):
                for dc in (-half, 0.0, half):
                    if dr or dc:
                        self.look(dr0 + dr, dc0 + dc)
        c, n, cell = self.centre, self.terrain.heights_m.shape[1], self.cell
        best = None
        for _, dr, dc, heading in sorted(self.looks)[:FITS_PER_PLACE]:
            start = (c + dr * self.per_node, c + dc * self.per_node)
            fit = refine(self.terrain, cell, cell, self.m, c, c, n, heading, self.settings.height_m, start,
                         self.sig_ref, self.bounds, self.model, max_offset_cells=MAX_OFFSET_NODES * self.per_node,
                         start_spread_cells=START_SPREAD_CELLS * self.per_node)
            if fit is not None and (best is None or fit.ssd < best.ssd):
                best = fit
        if best is None:
            return None
        x, y = (best.col - c) * cell, (c - best.row) * cell
        lon, lat = self.frame.lonlat(np.array([x, x]), np.array([y, y + cell]))
        # the fit's heading is against the frame's grid north; the true azimuth of grid north there
        gamma, _, _ = self.dem.body.geod.inv(lon[0], lat[0], lon[1], lat[1])
        heading = (best.heading_deg + float(gamma) + 180.0) % 360.0 - 180.0
        return PlaceFit(self.place, float(lat[0]), float(lon[0]), heading, best.ssd / self.sig_ref**2, best.rms_deg,
                        best, cell, float(gamma))


def fit_places(dem: Dem, skyline: Skyline, places: list[Place], settings: FitSettings) -> list[PlaceFit]:
    """The fits of ``skyline`` near the ``places`` on the map's own surface: a first look at each
    (FIRST_LOOK_STEP_NODES lattice within half a node spacing), then the full search
    (:meth:`PlaceSearch.fit`) at the FULL_PLACES whose first looks come lowest."""
    searches = [PlaceSearch(dem, skyline, p, settings) for p in places]
    for s in searches:
        s.look_around(FIRST_LOOK_REACH_NODES, LOOK_STEP_NODES)
    ranked = sorted((s for s in searches if math.isfinite(s.best_look)), key=lambda s: s.best_look)
    return [f for f in (s.fit() for s in ranked[:FULL_PLACES]) if f is not None]


def screen_places(dem: Dem, skyline: Skyline, places: list[Place], settings: FitSettings) -> list[tuple[float, Place]]:
    """Each place's best quick look (:meth:`PlaceSearch.quick_look` at SCREEN_LOOKS, on screening
    terrain: :class:`PlaceSearch`'s ``screening``), lowest first: which places deserve the fits.
    Places that cannot be rendered come last (inf)."""
    out = []
    for p in places:
        search = PlaceSearch(dem, skyline, p, settings, screening=True)
        out.append((min(search.quick_look(dr, dc) for dr, dc in SCREEN_LOOKS), p))
    return sorted(out, key=lambda v: v[0])


def fit_place(dem: Dem, skyline: Skyline, place: Place, settings: FitSettings) -> PlaceFit | None:
    """The full search for the fit of ``skyline`` near one ``place`` (:meth:`PlaceSearch.fit`)."""
    return PlaceSearch(dem, skyline, place, settings).fit()


def distinct_places(ranked: list[Place], count: int, apart_m: float, dem: Dem) -> list[Place]:
    """The first ``count`` places of ``ranked`` (most likely first) each more than ``apart_m`` from
    every place kept before it (geodesic distance on the map's body).  The places near each kept
    one are found on the sphere first, with a margin, and only those measured on the body."""
    if not ranked:
        return []
    lat = np.array([p.lat for p in ranked])
    lon = np.array([p.lon for p in ranked])
    la, lo = np.radians(lat), np.radians(lon)
    xyz = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=1)
    # within apart_m on the body, within this angle between the normals: no radius of curvature of
    # an ellipsoid is shorter than b^2 / a
    geod = dem.body.geod
    cos_reach = math.cos(min(1.01 * apart_m * geod.a / (geod.b * geod.b) + 1e-9, math.pi))
    # the places kept from a prefix of ``ranked`` are those kept from the whole list, as long as
    # the prefix yields ``count`` of them: try a short prefix first
    size = min(lat.size, max(64 * count, 4096))
    while True:
        alive = np.ones(size, dtype=bool)
        kept: list[Place] = []
        while len(kept) < count and alive.any():
            k = int(np.argmax(alive))
            kept.append(ranked[k])
            near = np.nonzero(alive & (xyz[:size] @ xyz[k] >= cos_reach))[0]
            _, _, d = dem.body.geod.inv(np.full(near.size, lon[k]), np.full(near.size, lat[k]), lon[near], lat[near])
            alive[near[np.asarray(d) <= apart_m]] = False
        if len(kept) >= count or size == lat.size:
            return kept
        size = min(lat.size, 4 * size)
