"""A whole-body tiled skyline database: facets, each an ordinary tile on its own metric grid.

One lon/lat lattice cannot serve a whole body (its metric spacing holds at one latitude only, and
it has no metric meaning at the poles), so a map that covers the body (it wraps around in
longitude and reaches both poles, :attr:`Dem.whole_body`) is cut into *facets*:

* latitude bands ``band_deg`` high between -``cap_deg`` and +``cap_deg``, each cut into longitude
  boxes whose ground width at the band's equator-ward edge is about the band's height (so boxes are
  roughly square and fewer near the poles).  Box k of a band of n is centred on longitude
  k * 360 / n, so the first box straddles the 0/360 seam;
* two polar caps, \\|lat\\| >= ``cap_deg``.

Each point of the body belongs to exactly one facet's box: a band holds latitudes [S, N) and
longitudes [W, E) (modulo 360); the north cap lat >= ``cap_deg``, the south cap lat < -``cap_deg``.

Each facet is an ordinary single-file database (format 3) on its own grid: a transverse Mercator
centred on a band's box, or a polar stereographic centred on a cap's pole (its scale set to one at
mid-cap, so within the cap it stays within a percent of true), at ``spacing_m``, by default half
the map's pixel size (DESIGN.md, "Decisions", says why).  Its candidate nodes are the grid's nodes
inside its box; the rectangle's other nodes are left out of the database like nodes on nodata
(:func:`build_on_grids` ``keep``).  Its terrain grid is the candidates' rectangle and the horizon's
reach all round, resampled bilinearly from the map, which reads across the 0/360 seam and across the
poles (:meth:`Dem.sample`), so a facet by the seam or a pole sees the terrain on the far side.

The horizon's reach defaults to the distance at which the map's highest point sinks below the
horizon of an eye at its lowest point, sqrt(2 R_eff (z_max - z_min)) (about 260 km on the Moon):
no terrain farther away can form a skyline.

Each facet is one Dask task.  A task loads the whole map (a whole-body map small enough for that,
the LOLA Moon at 4 px/deg is 2 MB; the windowed reads of a regional tiled build are not needed
here, :mod:`appliance.terrain.tiled`).  The folder's ``index.json`` is the tiled format
(:mod:`appliance.locating.tiled_index` reads it unchanged): each facet is a tile with row0 = col0 = 0, its
own grid's size and its box as ``bounds_lonlat``, whose W may be below 0 for a box across the seam
(the search compares longitudes modulo 360).  Since every facet has its own grid, the combination
over facets weighs each by its own cell area (:func:`appliance.locating.tile_combination.combine`).

The index also records where the map itself is, with its SHA-256 (``surface``): a search fits its
contending places on the map's own surface while the map is there and unchanged
(:func:`appliance.locating.surface_fit.fit_on_surface`).

A rerun into the same folder with the same parameters keeps the facets already built.
"""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from appliance.errors import InputError, OutputError
from appliance.terrain.database import build_on_grids
from appliance.terrain.dem import Dem
from appliance.terrain.grid import NodeGrid, _box_in_grid, _Lattice, _tmerc, lon_overlap
from appliance.terrain.horizon import DEFAULT_HEIGHT_M
from appliance.terrain.mosaic import MapSource
from appliance.terrain.tiled import (
    INDEX_FORMAT,
    INDEX_VERSION,
    TiledResult,
    TileJob,
    _lattice_entry,
    run_tile_jobs,
)

DEFAULT_BAND_DEG = 15.0
DEFAULT_CAP_DEG = 75.0
WHOLE_BODY_VERSION = 1


Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class Facet:
    """One facet: its file, its lon/lat box (W, S, E, N; a cap spans W = -180 to E = 180), its kind
    ("band", "north-cap" or "south-cap") and for a band, which of its band's ``n_boxes`` boxes it is
    (box k centred on lon k * 360 / n_boxes)."""

    file: str
    box: Box
    kind: str
    n_boxes: int = 1
    k: int = 0

    @property
    def centre(self) -> tuple[float, float]:
        """(lon, lat) the facet's grid is centred on."""
        if self.kind == "north-cap":
            return 0.0, 90.0
        if self.kind == "south-cap":
            return 0.0, -90.0
        w, s, e, n = self.box
        return (w + e) / 2.0, (s + n) / 2.0

    def contains(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Whether points belong to this facet (the half-open rule of the module docstring)."""
        lon = np.asarray(lon, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        w, s, e, n = self.box
        if self.kind == "north-cap":
            return lat >= s
        if self.kind == "south-cap":
            return lat < n
        # the box's index from the longitude, so that neighbouring boxes share their edges exactly
        width = 360.0 / self.n_boxes
        k = np.minimum(np.floor(np.mod(lon + width / 2.0, 360.0) / width), self.n_boxes - 1)
        return (lat >= s) & (lat < n) & (k == self.k)


def plan_facets(radius_m: float, band_deg: float = DEFAULT_BAND_DEG, cap_deg: float = DEFAULT_CAP_DEG
                ) -> tuple[Facet, ...]:
    """The facets of a body of mean radius ``radius_m``: south cap, bands south to north, north cap.
    File names follow the tiled build's: ``tile_rBBB_cKKK.viperdb``, band row BBB (0 the south cap),
    box KKK."""
    if not (0.0 < cap_deg < 90.0):
        raise InputError(f"polar cap edge {cap_deg} deg: expected between 0 and 90")
    if not (0.0 < band_deg <= 2.0 * cap_deg):
        raise InputError(f"band height {band_deg} deg: expected > 0 and at most {2.0 * cap_deg} (the bands' span)")
    n_bands = max(1, round(2.0 * cap_deg / band_deg))
    edges = np.linspace(-cap_deg, cap_deg, n_bands + 1)
    facets = [Facet("tile_r000_c000.viperdb", (-180.0, -90.0, 180.0, -cap_deg), "south-cap")]
    height_m = math.radians(2.0 * cap_deg / n_bands) * radius_m
    for b in range(n_bands):
        s, n = float(edges[b]), float(edges[b + 1])
        widest = 0.0 if s < 0.0 < n else min(abs(s), abs(n))
        around_m = 2.0 * math.pi * radius_m * math.cos(math.radians(widest))
        k = max(1, round(around_m / height_m))
        width = 360.0 / k
        for i in range(k):
            w = i * width - width / 2.0
            facets.append(Facet(f"tile_r{b + 1:03d}_c{i:03d}.viperdb", (w, s, w + width, n), "band", k, i))
    facets.append(Facet(f"tile_r{n_bands + 1:03d}_c000.viperdb", (-180.0, cap_deg, 180.0, 90.0), "north-cap"))
    return tuple(facets)


def facets_meeting(facets: tuple[Facet, ...], box: Box | None) -> tuple[Facet, ...]:
    """The facets whose box meets ``box`` (W, S, E, N degrees; None: all)."""
    if box is None:
        return facets
    w, s, e, n = box
    if not (w < e and s < n):
        raise InputError(f"search bounds {box}: expected W,S,E,N with W < E and S < N")
    out = tuple(f for f in facets if f.box[1] <= n and s <= f.box[3] and lon_overlap(f.box[0], f.box[2], w, e))
    if not out:
        raise InputError(f"search bounds {box} meet no facet")
    return out


def facet_crs(dem: Dem, facet: Facet) -> CRS:
    """A band's transverse Mercator, or a cap's polar stereographic of scale one at mid-cap."""
    lon_c, lat_c = facet.centre
    if facet.kind == "band":
        return _tmerc(dem, lon_c, lat_c)
    colat = math.radians(90.0 - (facet.box[1] if facet.kind == "north-cap" else -facet.box[3]))
    k0 = math.cos(colat / 4.0) ** 2  # the stereographic's scale is k0 / cos^2(c / 2): one at c = colat / 2
    ell = dem.crs.ellipsoid
    a = ell.semi_major_metre if ell is not None else dem.body.semi_major_m
    b = ell.semi_minor_metre if ell is not None else dem.body.semi_major_m
    return CRS.from_proj4(f"+proj=stere +lat_0={lat_c!r} +lon_0=0 +k_0={k0!r} +x_0=0 +y_0=0 +a={a!r} +b={b!r} "
                          "+units=m +no_defs")


def facet_grids(dem: Dem, facet: Facet, spacing_m: float, max_range_m: float
                ) -> tuple[NodeGrid, NodeGrid, tuple[int, int]]:
    """A facet's candidate grid (the nodes' rectangle around its box), terrain grid (plus the
    horizon's reach all round) and the candidates' (row, col) in the terrain grid."""
    crs = facet_crs(dem, facet)
    lattice = _Lattice(crs, 0.0, 0.0, spacing_m, spacing_m, spacing_m, spacing_m)
    if facet.kind == "band":
        to_grid = Transformer.from_crs(dem.crs.geodetic_crs, crs, always_xy=True)
        cx0, cy0, cx1, cy1 = _box_in_grid(to_grid, facet.box)
    else:
        edge = facet.box[1] if facet.kind == "north-cap" else facet.box[3]
        _, y = Transformer.from_crs(dem.crs.geodetic_crs, crs, always_xy=True).transform(0.0, edge)
        r = abs(float(y))
        cx0, cy0, cx1, cy1 = -r, -r, r, r
    c0, c1 = lattice.indices(cx0, cx1, 0)
    r0, r1 = lattice.indices(cy0, cy1, 1)
    tc0, tc1 = lattice.indices(cx0 - max_range_m, cx1 + max_range_m, 0)
    tr0, tr1 = lattice.indices(cy0 - max_range_m, cy1 + max_range_m, 1)
    cand = lattice.window(r0, r1, c0, c1)
    terr = lattice.window(tr0, tr1, tc0, tc1)
    return cand, terr, (tr1 - r1, c0 - tc0)


def facet_keep(cand: NodeGrid, facet: Facet) -> np.ndarray:
    """Which of the candidate rectangle's nodes (row-major) lie in the facet's box."""
    lon, lat = cand.xy_to_lonlat(*cand.node_xy(np.arange(cand.n_nodes)))
    return np.asarray(facet.contains(lon, lat), dtype=bool)


def default_spacing_m(dem: Dem) -> float:
    """Half the map's pixel size (module docstring): a grid at the pixel size itself, off the
    pixel centres, smooths the map's surface under the eye and so the near horizon."""
    return float(min(dem.resolution_m())) / 2.0


def default_max_range_m(dem: Dem, refraction: float | None = None) -> float:
    """The reach beyond which no terrain of the map can rise above the horizon of an eye at the
    map's lowest point: sqrt(2 R_eff (z_max - z_min)), rounded up to 10 km."""
    z = dem.elevation_m[np.isfinite(dem.elevation_m)]
    relief = float(z.max() - z.min()) if z.size else 0.0
    reach = math.sqrt(2.0 * dem.body.effective_radius_m(refraction) * max(relief, 1.0))
    return math.ceil(reach / 10_000.0) * 10_000.0


def build_facet(source: MapSource, out_dir: str, facet: Facet, spacing_m: float, params: dict) -> dict:
    """One task: load the map, build the facet's database, write it atomically.  Returns the
    file's name, its candidate count, the seconds taken and this process's peak resident memory."""
    t0 = time.perf_counter()
    dem = source.load()
    cand, terr, offset = facet_grids(dem, facet, spacing_m, params["max_range_m"])
    keep = facet_keep(cand, facet)
    build_on_grids(dem, Path(out_dir) / facet.file, cand, terr, offset, (0, 0), (terr.n_rows, terr.n_cols),
                   facet.box, params["height_m"], params["n_azimuths"], params["refraction"],
                   params["max_range_m"], None, workers=1, keep=keep)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kilobytes on Linux
    return {"file": facet.file, "nodes": int(keep.sum()), "seconds": time.perf_counter() - t0,
            "peak_rss_bytes": int(peak)}


def build_whole_body(
    source: MapSource,
    out_dir: str | Path,
    facet_box: Box | None = None,
    spacing_m: float | None = None,
    height_m: float = DEFAULT_HEIGHT_M,
    n_azimuths: int = 360,
    refraction: float | None = None,
    max_range_m: float | None = None,
    band_deg: float = DEFAULT_BAND_DEG,
    cap_deg: float = DEFAULT_CAP_DEG,
    client: Any = None,
    force: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
) -> TiledResult:
    """Build (or complete) the whole-body tiled database of ``source`` in ``out_dir`` on the Dask
    ``client``: every facet, or with ``facet_box`` (W, S, E, N) only the facets meeting it.

    Facets already there with the same parameters are kept; one built with other parameters is an
    error unless ``force``."""
    t_start = time.perf_counter()
    out = Path(out_dir)
    if not out.is_dir():
        raise OutputError(f"{out}: output folder does not exist")
    dem = source.load()
    if not dem.whole_body:
        raise InputError(f"{dem.source}: not a map of the whole body (it must wrap around in longitude and reach "
                         "both poles); build it with --search-bounds instead")
    spacing = default_spacing_m(dem) if spacing_m is None else float(spacing_m)
    if not (math.isfinite(spacing) and spacing > 0.0):
        raise InputError(f"--spacing {spacing_m} m must be positive")
    reach = default_max_range_m(dem, refraction) if max_range_m is None else float(max_range_m)
    facets = facets_meeting(plan_facets(dem.body.radius_m, band_deg, cap_deg), facet_box)
    refr = dem.body.refraction if refraction is None else refraction
    params = {"height_m": height_m, "n_azimuths": n_azimuths, "refraction": refr, "max_range_m": reach}
    grids = {f.file: facet_grids(dem, f, spacing, reach)[0] for f in facets}
    index = {
        "format": INDEX_FORMAT,
        "format_version": INDEX_VERSION,
        "whole_body": {"version": WHOLE_BODY_VERSION, "band_deg": band_deg, "cap_deg": cap_deg,
                       "spacing_m": spacing, "facet_box": list(facet_box) if facet_box is not None else None},
        "tiles": [{"file": f.file, "kind": f.kind, "row0": 0, "col0": 0, "n_rows": grids[f.file].n_rows,
                   "n_cols": grids[f.file].n_cols, "bounds_lonlat": list(f.box)} for f in facets],
        "n_azimuths": n_azimuths,
        "height_m": height_m,
        "max_range_m": reach,
        "refraction": refr,
        "body": dem.body.name.value,
        "sources": [{"name": n, "sha256": s} for n, s in source.sources],
        # where the map itself stays, for the search's fits on its own surface (appliance.locating.surface_fit)
        "surface": {"path": str(Path(source.path).resolve()), "crs": source.crs, "sha256": source.sha256},
    }
    jobs = [TileJob(f.file, _lattice_entry(grids[f.file]), build_facet,
                    (source, str(out.resolve()), f, spacing, params)) for f in facets]
    keys = ("format", "format_version", "whole_body", "n_azimuths", "height_m", "max_range_m", "refraction",
            "body", "sources")
    return run_tile_jobs(source, out, index, keys, params, jobs, client, force, progress, "facets", t_start)
