"""Position from a skyline against a tiled skyline database: a folder of ordinary databases.

A tiled database is a folder holding ``index.json`` and one format-3 database per tile, each a
window of one mosaic-wide candidate lattice.  A search runs the ordinary estimator on every tile
that the search area touches (in process, or one Dask task per tile on a cluster) and then combines
the tiles as one grid would have been combined.

Why the combination needs more than each tile's answer: every tile's posteriors are normalised
within the tile, so each tile, even one the skyline was never seen from, holds some node of
posterior near one.  Each tile therefore also reports its normalisers (the log of the summed
unnormalised lower, upper and midpoint posteriors, :class:`~appliance.estimator.EstimateResult`)
and its best candidate's unnormalised bounds; with them the best candidate's lower and upper
posterior are recomputed over all tiles exactly, and every other node's upper posterior is bounded
from above (:func:`global_log_upper_bound`).  The region is then every node, in any tile, whose
bound reaches the best's lower posterior; a node of it in another tile, away from the best, is a
rival the skyline does not rule out, and the answer is ambiguous.

The prior is uniform per unit area: a tile's evidence is weighed by its own cell area, which is the
same in every tile of one lattice and differs between the facets of a whole-body database
(:mod:`appliance.terrain.whole_body`), each on its own grid; every position (lon/lat) of the
region comes from its own tile's grid.  A search box or a position and radius choose the tiles
(longitudes compared modulo 360); within them the prior stays uniform.

Nothing here touches devices or logs: the module maps a folder and skylines to numbers.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from appliance.bodies import body_named, geodesic_distance_m
from appliance.errors import DatabaseError, EstimationError, InputError
from appliance.estimator.estimate import (
    AMBIGUOUS_CELLS,
    OCCLUSION_WEIGHT,
    SAME_ANSWER_CELLS,
    FirstPass,
    SkylineGrid,
    first_pass,
)
from appliance.locate.position import MAX_REGION_CELLS_IN_JSON, crs_name, locate, skyline_grid
from appliance.locate.verification import FitSettings, Place, distinct_places, fit_places, screen_places
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase, load_database
from appliance.terrain.dem import Dem
from appliance.terrain.grid import lon_overlap
from appliance.terrain.mosaic import open_map

INDEX_NAME = "index.json"
INDEX_FORMAT = "viper-tiled-db"
INDEX_VERSION = 1
#: How many of a tile's nodes (highest upper posterior first) travel back from its search: enough
#: that, when a node left behind could still join the region, the region is already wider than
#: AMBIGUOUS_CELLS and the answer ambiguous whatever the rest holds.
TOP_NODES = 4096

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class TileEntry:
    """One tile of the index: its file, its window of the mosaic lattice (bookkeeping only: the
    tile's own header grid is authoritative) and its candidate area in lon/lat (W, S, E, N)."""

    file: str
    row0: int
    col0: int
    n_rows: int
    n_cols: int
    bounds_lonlat: Box


@dataclass(frozen=True)
class TiledIndex:
    """A checked ``index.json`` and the folder it lies in."""

    folder: Path
    tiles: tuple[TileEntry, ...]
    n_azimuths: int
    height_m: float
    max_range_m: float
    body: str
    raw: dict

    def path(self, tile: TileEntry) -> Path:
        return self.folder / tile.file


def is_tiled(path: str | Path) -> bool:
    """Whether ``path`` names a tiled database (a folder) rather than a single database file."""
    return Path(path).is_dir()


def _bad(folder: Path, why: str) -> DatabaseError:
    return DatabaseError(f"{folder}: not a usable tiled skyline database: {why}")


def _number(d: dict, key: str, folder: Path, kind: Callable[[Any], Any] = float) -> Any:
    try:
        v = d[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError
        if isinstance(v, float) and not math.isfinite(v):
            raise _bad(folder, f"{INDEX_NAME} has a non-finite {key!r}")
        out = kind(v)
    except (KeyError, TypeError, ValueError):
        raise _bad(folder, f"{INDEX_NAME} lacks a numeric {key!r}") from None
    if out != v:
        raise _bad(folder, f"{INDEX_NAME} has a non-integral {key!r}: {v}")
    return out


def _tile_entry(t: Any, folder: Path, k: int) -> TileEntry:
    if not isinstance(t, dict):
        raise _bad(folder, f"tile {k} of {INDEX_NAME} is not an object")
    name = t.get("file")
    if not isinstance(name, str) or not name or Path(name).name != name:
        raise _bad(folder, f"tile {k} of {INDEX_NAME} has no plain file name")
    b = t.get("bounds_lonlat")
    if not (isinstance(b, list) and len(b) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                        for v in b)):
        raise _bad(folder, f"tile {name}: bounds_lonlat must be [W, S, E, N]")
    w, s, e, n = (float(v) for v in b)
    if not (w < e and s < n):
        raise _bad(folder, f"tile {name}: bounds_lonlat {b} must have W < E and S < N")
    dims = [_number(t, key, folder, int) for key in ("row0", "col0", "n_rows", "n_cols")]
    if dims[0] < 0 or dims[1] < 0 or dims[2] < 1 or dims[3] < 1:
        raise _bad(folder, f"tile {name}: row0, col0 must be >= 0 and n_rows, n_cols >= 1")
    return TileEntry(name, dims[0], dims[1], dims[2], dims[3], (w, s, e, n))


def open_tiled(folder: str | Path) -> TiledIndex:
    """Read and check a tiled database's index: its format and version, each tile's entry, and that
    every tile's file is present.  No tile is opened here: a search maps only the tiles it touches."""
    p = Path(folder)
    if not p.is_dir():
        raise DatabaseError(f"{p}: no such tiled database folder")
    try:
        index = json.loads((p / INDEX_NAME).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _bad(p, f"no {INDEX_NAME}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _bad(p, f"unreadable {INDEX_NAME} ({first})") from None
    if not isinstance(index, dict) or index.get("format") != INDEX_FORMAT:
        raise _bad(p, f"{INDEX_NAME} is not of format {INDEX_FORMAT!r}")
    if index.get("format_version") != INDEX_VERSION:
        raise _bad(p, f"{INDEX_NAME} format version {index.get('format_version')}, this viper reads "
                      f"version {INDEX_VERSION}")
    tiles_raw = index.get("tiles")
    if not isinstance(tiles_raw, list) or not tiles_raw:
        raise _bad(p, f"{INDEX_NAME} lists no tiles")
    tiles = tuple(_tile_entry(t, p, k) for k, t in enumerate(tiles_raw))
    names = [t.file for t in tiles]
    if len(set(names)) != len(names):
        raise _bad(p, f"{INDEX_NAME} lists a tile twice")
    missing = [n for n in names if not (p / n).is_file()]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise _bad(p, f"tile {missing[0]}{more} listed in {INDEX_NAME} is missing")
    body = index.get("body")
    if not isinstance(body, str):
        raise _bad(p, f"{INDEX_NAME} lacks the body")
    try:
        body_named(body)
    except (KeyError, ValueError):
        raise _bad(p, f"{INDEX_NAME} names an unknown body {body!r}") from None
    return TiledIndex(p, tiles, _number(index, "n_azimuths", p, int), _number(index, "height_m", p),
                      _number(index, "max_range_m", p), body, index)


def box_around(lat: float, lon: float, radius_m: float, body: str) -> Box:
    """The lon/lat box (W, S, E, N) holding every point within ``radius_m`` of (lat, lon)."""
    if not (math.isfinite(radius_m) and radius_m > 0.0):
        raise InputError(f"search radius {radius_m} m: expected > 0")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise InputError(f"position {lat}, {lon}: expected a latitude and longitude in degrees")
    dlat = math.degrees(radius_m / body_named(body).radius_m)
    cos_lat = math.cos(math.radians(min(abs(lat) + dlat, 90.0)))
    dlon = 180.0 if cos_lat < 1e-9 else min(math.degrees(radius_m / (body_named(body).radius_m * cos_lat)), 180.0)
    return lon - dlon, max(lat - dlat, -90.0), lon + dlon, min(lat + dlat, 90.0)


def select_tiles(index: TiledIndex, box: Box | None = None) -> list[TileEntry]:
    """The tiles whose candidate area meets ``box`` (W, S, E, N; None: every tile)."""
    if box is None:
        return list(index.tiles)
    w, s, e, n = box
    if not (w < e and s < n):
        raise InputError(f"search bounds {box}: expected W,S,E,N with W < E and S < N")
    out = [t for t in index.tiles
           if lon_overlap(t.bounds_lonlat[0], t.bounds_lonlat[2], w, e) and t.bounds_lonlat[1] <= n
           and s <= t.bounds_lonlat[3]]
    if not out:
        raise InputError(f"search bounds {tuple(round(v, 6) for v in box)} meet no tile of {index.folder}")
    return out


@dataclass(frozen=True)
class SearchParams:
    """What every tile's search shares (the arguments of :func:`appliance.locate.position.locate`)."""

    sigma_deg: tuple[float, float]
    heading_tolerance_deg: float | None
    height_m: float | None = None
    occlusion_weight: float = OCCLUSION_WEIGHT
    map_sigma_m: float = 0.0


@dataclass(frozen=True)
class TileOutcome:
    """One tile's search, reduced to what the combination and the outputs need (small enough to
    travel back from a Dask worker: no per-node maps, only the TOP_NODES most likely nodes)."""

    file: str
    error: str | None
    record: dict = field(default_factory=dict)  # the tile's own JSON record (locate.position), no region cells
    node: int = -1
    lat: float = math.nan
    lon: float = math.nan
    log_lower: float = -math.inf  # the best candidate's lower and upper posterior within the tile
    log_upper: float = -math.inf
    lo_unnormalised: float = -math.inf  # and unnormalised
    up_unnormalised: float = -math.inf
    log_evidence_lower: float = -math.inf
    log_evidence_upper: float = -math.inf
    log_evidence_mid: float = -math.inf
    log_cell_area: float = 0.0  # log of a cell's area (m^2): the uniform prior per unit area
    cell_size_m: tuple[float, float] = (math.nan, math.nan)
    ambiguous: bool = False
    region_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    region_lonlat: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    top_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    top_log_upper: np.ndarray = field(default_factory=lambda: np.zeros(0))
    top_log_upper_unnormalised: np.ndarray = field(default_factory=lambda: np.zeros(0))
    top_lonlat: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    left_max_log_upper: float = -math.inf  # the highest upper posterior of the nodes not sent
    left_max_log_upper_unnormalised: float = -math.inf  # and the highest unnormalised one
    candidates: int = 0
    elapsed_s: float = 0.0
    has_region: bool = True  # False: the search left the region out (search_tile's ``region``)


#: Candidate nodes of the tiles a process keeps mapped between searches (checksums verified once,
#: at the first load): a whole-body database or a few 1-degree tiles at 90 m, a few hundred MB of
#: per-node arrays besides the mapped files.
OPEN_TILE_NODES = 16_000_000
_open_tiles: dict[tuple[str, int, int], tuple[SkylineDatabase, SkylineGrid]] = {}
#: Guards the per-process caches (_open_tiles, _first_passes): the tiles of an in-process search
#: run on several threads at once.  Held only to look up, insert and evict, never while a tile
#: is loaded or scored.
_cache_lock = threading.Lock()


def _open_tile(folder: str, tile: TileEntry, expect: tuple[int, float] | None,
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


def _tile_first_pass(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams,
                     expect: tuple[int, float] | None) -> tuple[SkylineDatabase, SkylineGrid, FirstPass]:
    """The tile's database, grid and the skyline's first pass on it: made once per process and
    search, then kept (within FIRST_PASS_BYTES) for the next round of the same search."""
    tile_key = _tile_key(Path(folder) / tile.file)
    db, grid = _open_tile(folder, tile, expect, key=tile_key)
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


def tile_floor(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams,
               expect: tuple[int, float] | None = None) -> float:
    """The tile's best first-pass lower log-posterior (:attr:`appliance.estimator.FirstPass.best_lower`);
    -inf where the skyline cannot be placed on it."""
    try:
        return _tile_first_pass(folder, tile, skyline, params, expect)[2].best_lower
    except EstimationError:
        return -math.inf


def search_tile(folder: str, tile: TileEntry, skyline: Skyline, params: SearchParams,
                source: str = "", refine: bool = True, expect: tuple[int, float] | None = None,
                rescore_floor: float | None = None, region: bool = True) -> TileOutcome:
    """The ordinary estimate on one tile, with the exact refinement or without (``refine``), its
    rescoring pruned against ``rescore_floor`` (the best first-pass lower bound over every tile
    searched, :func:`tile_floor`).  A tile where the skyline cannot be placed at all (no terrain
    along its azimuths) is reported as such; the other tiles may still place it.

    ``region`` False leaves the tile's own region (its nodes and their lon/lat) out of the outcome:
    the combination reads it from the best tile only, and a round that only picks the best tile
    (:func:`best_tile`) needs none.  A tile the skyline does not single a place out on (sea, a
    plain) holds a region of most of its nodes, whose projection to lon/lat costs more than the
    tile's search on the grid."""
    t0 = time.perf_counter()
    try:
        db, grid, first = _tile_first_pass(folder, tile, skyline, params, expect)
        pos = locate(db, skyline, params.sigma_deg, params.heading_tolerance_deg, source=source, grid=grid,
                     height_m=params.height_m, occlusion_weight=params.occlusion_weight,
                     map_sigma_m=params.map_sigma_m, refine=refine, rescore_floor=rescore_floor, first=first,
                     learn_noise=False)
    except EstimationError as exc:
        return TileOutcome(tile.file, str(exc), elapsed_s=time.perf_counter() - t0)
    r = pos.result
    up = np.asarray(r.log_upper_map, dtype=np.float64)
    assert r.log_upper_unnormalised_map is not None
    up_un = np.asarray(r.log_upper_unnormalised_map, dtype=np.float64)
    # ranked by the unnormalised upper posterior: the order every tile's nodes keep over all tiles
    k = min(TOP_NODES, up.size)
    top = np.argpartition(-up_un, k - 1)[:k] if k < up.size else np.arange(up.size)
    top = top[np.argsort(-up_un[top], kind="stable")]
    left = np.ones(up.size, dtype=bool)
    left[top] = False
    # the largest of the nodes not sent, read in place (no copy of the tile's other nodes)
    left_max = float(np.max(up, where=left, initial=-math.inf)) if k < up.size else -math.inf
    left_max_un = float(np.max(up_un, where=left, initial=-math.inf)) if k < up.size else -math.inf

    def lonlat(nodes: np.ndarray) -> np.ndarray:
        if nodes.size == 0:
            return np.zeros((0, 2))
        lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(nodes))
        return np.column_stack([np.atleast_1d(lon), np.atleast_1d(lat)]).astype(np.float64)

    nodes = np.asarray(r.region_nodes, dtype=np.int64) if region else np.zeros(0, np.int64)
    g = db.grid
    return TileOutcome(
        tile.file, None, pos.to_json(db, max_cells=0), r.node, pos.lat, pos.lon, r.log_lower,
        math.log(r.upper) if r.upper > 0 else -math.inf, r.log_lower_unnormalised, r.log_upper_unnormalised,
        r.log_evidence_lower, r.log_evidence_upper, r.log_evidence_mid, math.log(g.dx_m * g.dy_m),
        (g.dx_m, g.dy_m), r.ambiguous, nodes, lonlat(nodes), top.astype(np.int64), up[top], up_un[top],
        lonlat(top), left_max, left_max_un, r.candidates, time.perf_counter() - t0, region)


def _log_sum(values: Sequence[float]) -> float:
    v = [x for x in values if x > -math.inf]
    return float(np.logaddexp.reduce(np.asarray(v))) if v else -math.inf


def global_log_upper_bound(log_upper: np.ndarray, log_upper_unnormalised: np.ndarray,
                           log_others_lower: float) -> np.ndarray:
    """An upper bound on nodes' upper posterior over all tiles, from their upper posterior within
    their own tile and their unnormalised one (nats, on the scale of ``log_others_lower``).

    Within a tile a candidate's upper posterior is u = b / (b + S - a), with b and a its own
    unnormalised upper and lower posterior and S the tile's summed lower ones; over all tiles the
    others' summed lower posteriors O (``log_others_lower``) join the denominator, so
    1 / g = 1 / u + O / b exactly.  A node holds the largest u and the largest b of its headings,
    which bounds every heading's g from above; for one tile (O = 0) g is u.
    """
    lu = np.minimum(np.asarray(log_upper, dtype=np.float64), 0.0)
    if log_others_lower == -math.inf:
        return lu
    lb = np.asarray(log_upper_unnormalised, dtype=np.float64)
    return -np.logaddexp(-lu, log_others_lower - lb)


@dataclass(frozen=True)
class RegionCell:
    """A node of the combined region: its tile, its node there, and where it lies."""

    tile: str
    node: int
    lon: float
    lat: float
    #: its unnormalised upper posterior times its cell's area, what ranks the contending places (the
    #: best tile's region nodes beyond its TOP_NODES: -inf)
    log_upper_unnormalised: float = -math.inf


@dataclass(frozen=True)
class SurfaceFit:
    """The answer fitted on the map's own surface (:mod:`appliance.locate.verification`): where, in which
    tile's grid coordinates, the compass's error, the fit's RMS residual and how many contending
    places were looked at."""

    lat: float
    lon: float
    x: float
    y: float
    crs: str
    tile: str
    node: int  # the node of that tile the fit started from
    heading_correction_deg: float
    rms_deg: float
    places: int
    grid_distance_m: float  # from the grid's best place
    screened: int = 0  # contending places screened before choosing those looked at


@dataclass(frozen=True)
class TiledEstimate:
    """The combined estimate over the searched tiles."""

    best: TileOutcome
    tiles_searched: tuple[str, ...]
    tiles_failed: tuple[str, ...]
    log_lower: float  # the best candidate's posterior bounds over all searched tiles
    log_upper: float
    region: tuple[RegionCell, ...]
    region_area_m2: float
    ambiguous: bool
    tile_share: dict[str, float]  # each tile's share of the midpoint posterior
    overflowed: tuple[str, ...]  # tiles whose nodes left behind could still join the region
    notes: list[str]
    body: str
    elapsed_s: float
    candidates: int
    fit: SurfaceFit | None = None  # the answer fitted on the map's own surface, where the map was at hand

    @property
    def tile(self) -> str:
        return self.best.file if self.fit is None else self.fit.tile

    @property
    def lat(self) -> float:
        return self.best.lat if self.fit is None else self.fit.lat

    @property
    def lon(self) -> float:
        return self.best.lon if self.fit is None else self.fit.lon

    @property
    def heading_correction_deg(self) -> float:
        if self.fit is not None:
            return self.fit.heading_correction_deg
        return float(self.best.record["heading_correction_deg"])

    def truth_error_m(self, truth: tuple[float, float]) -> float:
        return geodesic_distance_m(self.lat, self.lon, truth[0], truth[1], body_named(self.body))

    def status(self, index: TiledIndex | None = None, truth: tuple[float, float] | None = None) -> str:
        """'ambiguous' when the combination is, or when the truth (where known) lies outside the
        region; else 'ok'."""
        if self.ambiguous:
            return "ambiguous"
        if truth is not None and (index is None or not self.truth_in_region(index, truth)):
            return "ambiguous"
        return "ok"

    def truth_in_region(self, index: TiledIndex, truth: tuple[float, float]) -> bool:
        """Whether the node nearest the true (lat, lon), in a searched tile holding it or within half a
        degree of it, belongs to the region (a facet of a whole-body database keeps only the nodes
        inside its box, so the nearest node may belong to its neighbour)."""
        lat, lon = truth
        cells = {(c.tile, c.node) for c in self.region}
        m = 0.5
        m_lon = min(180.0, m / max(math.cos(math.radians(min(abs(lat) + m, 90.0))), 1e-9))
        for t in index.tiles:
            w, s, e, n = t.bounds_lonlat
            if t.file not in self.tiles_searched or not (lon_overlap(lon, lon, w - m_lon, e + m_lon)
                                                         and s - m <= lat <= n + m):
                continue
            grid = _open_tile(str(index.folder), t, None)[0].grid
            fr, fc = grid.xy_to_rc(*grid.lonlat_to_xy(lon, lat))
            r, c = int(round(float(fr))), int(round(float(fc)))
            if 0 <= r < grid.n_rows and 0 <= c < grid.n_cols and (t.file, r * grid.n_cols + c) in cells:
                return True
        return False

    def to_json(self, index: TiledIndex | None = None, truth: tuple[float, float] | None = None) -> dict:
        """The single-file record (:meth:`appliance.locate.position.Position.to_json`) of the best tile, its
        bounds, region and status replaced by the combined ones, and which tiles were searched."""
        out = dict(self.best.record)
        cells = [[round(c.lat, 7), round(c.lon, 7)] for c in self.region]
        out.update({
            "lower": math.exp(self.log_lower),
            "upper": math.exp(self.log_upper),
            "log10_lower": round(self.log_lower / math.log(10.0), 4),
            "region": {
                "area_m2": round(self.region_area_m2, 1),
                "cell_size_m": [round(v, 3) for v in self.best.cell_size_m],
                "n_cells": len(self.region),
                "cells": cells[:MAX_REGION_CELLS_IN_JSON],
                "cells_truncated": len(cells) > MAX_REGION_CELLS_IN_JSON,
                "tiles": sorted({c.tile for c in self.region}),
            },
            "ambiguous": self.ambiguous,
            "status": self.status(index, truth),
            "tile": self.tile,
            "tile_node": self.best.node if self.fit is None else self.fit.node,
            "tiles_searched": list(self.tiles_searched),
            "tile_share": {k: round(v, 6) for k, v in self.tile_share.items()},
            "candidates": self.candidates,
            "elapsed_ms": round(self.elapsed_s * 1e3, 2),
            "notes": list(self.notes),
        })
        if self.fit is not None:
            f = self.fit
            out.update({"lat": round(f.lat, 8), "lon": round(f.lon, 8), "x": round(f.x, 3), "y": round(f.y, 3),
                        "crs": f.crs, "heading_correction_deg": round(f.heading_correction_deg, 3),
                        "rms_residual_deg": round(f.rms_deg, 4),
                        "surface_fit": {"places": f.places, "screened": f.screened,
                                        "grid_distance_m": round(f.grid_distance_m, 1)}})
        if truth is not None:
            out["truth"] = {"lat": truth[0], "lon": truth[1], "error_m": round(self.truth_error_m(truth), 2)}
        return out


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


def combine(outcomes: Sequence[TileOutcome], body: str, elapsed_s: float = 0.0) -> TiledEstimate:
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
    notes: list[str] = []
    rival = False
    overflowed: list[str] = []
    area = 0.0
    reach_m = SAME_ANSWER_CELLS * max(best.cell_size_m)
    b_body = body_named(body)
    for i, o in enumerate(ok):
        bound = global_log_upper_bound(o.top_log_upper, o.top_log_upper_unnormalised + o.log_cell_area,
                                       _others(ev_lo, i))
        keep = bound >= best_lower
        nodes = set(int(v) for v in o.top_nodes[keep])
        lonlat = {int(v): (float(p[0]), float(p[1])) for v, p in zip(o.top_nodes[keep], o.top_lonlat[keep])}
        upper = {int(v): float(u) + o.log_cell_area for v, u in zip(o.top_nodes[keep],
                                                                      o.top_log_upper_unnormalised[keep])}
        if o is best:
            for v, p in zip(o.region_nodes, o.region_lonlat):
                lonlat.setdefault(int(v), (float(p[0]), float(p[1])))
            nodes |= set(int(v) for v in o.region_nodes)
        left = global_log_upper_bound(np.array([o.left_max_log_upper]),
                                      np.array([o.left_max_log_upper_unnormalised + o.log_cell_area]),
                                      _others(ev_lo, i))[0]
        if o.left_max_log_upper > -math.inf and left >= best_lower:
            overflowed.append(o.file)
        cells = [RegionCell(o.file, v, *lonlat[v], upper.get(v, -math.inf)) for v in sorted(nodes)]
        region += cells
        area += math.exp(o.log_cell_area) * len(cells)
        if cells and o is not best and not rival:
            lon, lat = np.array([(c.lon, c.lat) for c in cells]).T
            _, _, dist = b_body.geod.inv(np.full(lon.size, best.lon), np.full(lat.size, best.lat), lon, lat)
            rival = bool(np.any(np.asarray(dist) > reach_m))
    notes += [n for n in best.record.get("notes", []) if not n.startswith("ambiguous")]
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
    ambiguous = bool(best.ambiguous or rival or overflowed or len(region) > AMBIGUOUS_CELLS)
    return TiledEstimate(best, tuple(o.file for o in outcomes), failed, best_lower, g_upper[b], tuple(region),
                         area, ambiguous, share, tuple(overflowed), notes, body, elapsed_s,
                         sum(o.candidates for o in ok))


#: Contending places of a whole-body search looked at on the map's own surface
#: (:func:`fit_on_surface`): the region's SCREEN_PLACES most likely distinct places (by upper
#: posterior on the facets' grid) are screened on the map (:func:`appliance.locate.verification.screen_places`),
#: and the grid's best place and the SURFACE_PLACES - 1 that screen best are fitted.  On the facets'
#: grid alone the place a skyline was seen from ranked 112th-364th among the region's distinct
#: places at four of twenty positions of bench/moon_whole_body.py; screened on the map,
#: first to sixth of 400.
SCREEN_PLACES = 400
SURFACE_PLACES = 24


def open_surface(index: TiledIndex) -> tuple[Dem | None, str | None]:
    """The map a whole-body database was built from (its index's ``surface``), if it is still where
    it was and unchanged: (map, None), else (None, why not).  (None, None) for a database that
    records no map: a regional one, whose tiles lie on the map's own lattice."""
    rec = index.raw.get("surface")
    if rec is None:
        return None, None
    if not (isinstance(rec, dict) and isinstance(rec.get("path"), str) and isinstance(rec.get("sha256"), str)
            and (rec.get("crs") is None or isinstance(rec.get("crs"), str))):
        raise _bad(index.folder, f"{INDEX_NAME} has a malformed 'surface'")
    path = Path(rec["path"])
    if not path.is_file():
        return None, f"its map {path} is not there"
    try:
        source = open_map([str(path)], None, rec.get("crs"))
        if source.sha256 != rec["sha256"]:
            return None, f"its map {path} has changed since the build"
        return source.load(), None
    except OSError as exc:  # DemError too
        return None, f"its map {path} cannot be read ({exc.strerror or exc})"


def fit_on_surface(index: TiledIndex, est: TiledEstimate, surface: Dem, skyline: Skyline,
                   params: SearchParams) -> TiledEstimate | None:
    """``est`` (the facets' grid answer) with its answer fitted on the map's own surface: the
    contending places (the best, then the region's distinct places by upper posterior, at most
    SCREEN_PLACES) screened on renders of the map, the grid's best and the SURFACE_PLACES - 1 that
    screen best each fitted between nodes on renders of the map, the best fit kept
    (:mod:`appliance.locate.verification`).  The posterior bounds and the region stay the grid's; a fit
    farther than SAME_ANSWER_CELLS from the grid's best makes the answer ambiguous.  None where no
    place can be fitted."""
    spacing = max(est.best.cell_size_m)
    ranked = [Place(est.best.file, est.best.node, est.best.lat, est.best.lon)]
    ranked += [Place(c.tile, c.node, c.lat, c.lon) for c in sorted(est.region, key=lambda c: -c.log_upper_unnormalised)]
    candidates = distinct_places(ranked, SCREEN_PLACES, SAME_ANSWER_CELLS * spacing, surface)
    settings = FitSettings(index.height_m if params.height_m is None else params.height_m, index.n_azimuths,
                           index.max_range_m, index.raw.get("refraction"), spacing, params.sigma_deg,
                           params.heading_tolerance_deg, params.occlusion_weight, params.map_sigma_m)
    places = candidates
    if len(candidates) > SURFACE_PLACES:
        # the grid's best place always, then those that screen best on the map
        screened = screen_places(surface, skyline, candidates[1:], settings)
        places = candidates[:1] + [p for _, p in screened[:SURFACE_PLACES - 1]]
    fits = fit_places(surface, skyline, places, settings)
    if not fits:
        return None
    w = min(fits, key=lambda f: f.cost)
    tile = next(t for t in index.tiles if t.file == w.place.tile)
    db = _open_tile(str(index.folder), tile, None)[0]
    x, y = db.grid.lonlat_to_xy(w.lon, w.lat)
    off = geodesic_distance_m(est.best.lat, est.best.lon, w.lat, w.lon, body_named(index.body))
    notes = list(est.notes) + [f"fitted on the map's own surface: {len(candidates)} contending place(s) screened, "
                               f"{len(places)} looked at, {len(fits)} fitted, the best {w.rms_deg:.2f} deg RMS"]
    ambiguous = est.ambiguous
    if off > SAME_ANSWER_CELLS * spacing:
        ambiguous = True
        notes.append(f"ambiguous: fitted on the map's own surface, the skyline lies {off / 1000:.1f} km from the "
                     f"grid's best place (in {est.best.file})")
    fit = SurfaceFit(w.lat, w.lon, float(x), float(y), crs_name(db), w.place.tile, w.place.node,
                     w.heading_correction_deg, w.rms_deg, len(places), off, len(candidates))
    return dataclasses.replace(est, fit=fit, ambiguous=ambiguous, notes=notes)


def locate_tiled(index: TiledIndex, skyline: Skyline, params: SearchParams, box: Box | None = None,
                 client: Any = None, source: str = "", surface: Dem | None = None) -> TiledEstimate:
    """Search the tiles that ``box`` meets (every tile with None) and combine them.

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

    With the ``surface`` a whole-body database was built from (:func:`open_surface`), the answer is
    fitted on that map itself (:func:`fit_on_surface`) instead of refined on the facets' resampled
    grid."""
    t0 = time.perf_counter()
    tiles = select_tiles(index, box)
    placed: dict[str, str] = {}
    floors = _run(index, tile_floor, tiles, client, skyline, params, placed=placed)
    floor = max(floors, default=-math.inf)
    first = _run(index, search_tile, tiles, client, skyline, params, source, False, rescore_floor=floor,
                 region=False, placed=placed)
    best = best_tile(first)
    best_tiles = [t for t in tiles if t.file == best]
    if surface is not None:
        # the best tile's region without its refinement: the fits on the map replace that
        grid = _run(index, search_tile, best_tiles, client, skyline, params, source, False, rescore_floor=floor,
                    placed=placed)
        fitted = fit_on_surface(index, combine(grid + [o for o in first if o.file != best], index.body), surface,
                                skyline, params)
        if fitted is not None:
            return dataclasses.replace(fitted, elapsed_s=time.perf_counter() - t0)
    refined = _run(index, search_tile, best_tiles, client, skyline, params, source, True, rescore_floor=floor,
                   placed=placed)
    outcomes = refined + [o for o in first if o.file != best]
    return combine(outcomes, index.body, time.perf_counter() - t0)


def _run(index: TiledIndex, task: Callable[..., Any], tiles: Sequence[TileEntry], client: Any, skyline: Skyline,
         params: SearchParams, *args: Any, placed: dict[str, str] | None = None, **kwargs: Any) -> list[Any]:
    """``task(folder, tile, skyline, params, *args, expect=..., **kwargs)`` for every tile, in
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
            return [task(folder, t, skyline, params, *args, **kwargs) for t in tiles]
        return list(_tile_pool(threads).map(lambda t: task(folder, t, skyline, params, *args, **kwargs), tiles))
    placed = {} if placed is None else placed
    futures = []
    for t in tiles:
        where = {"workers": [placed[t.file]], "allow_other_workers": True} if t.file in placed else {}
        futures.append(client.submit(task, folder, t, skyline, params, *args, pure=False, **where, **kwargs))
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
