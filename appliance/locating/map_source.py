"""The map a photo is located on: a skyline database file, a tiled database folder, or a DEM whose
database is built for the search area and kept in a cache folder.

A DEM is read once to plan a grid over the search area (its georeferencing only, no heights), and
the database is built (:func:`appliance.terrain.database.build_database`, written atomically) only
when the cache holds none that will do: one of the same DEM content, CRS, camera height, azimuth
count and format version whose box contains the area's, at a spacing no coarser than twice the one
the area asks for.  So a second photo of the same area, or of a smaller one inside it, starts at
once.

Spacing of a built database: the DEM's own cell (the side of a square of a pixel's ground area),
times the smallest whole number that leaves at most ``max_nodes`` candidate nodes in the area's box
(clipped to the DEM); at one cell the DEM's own pixel lattice is kept.  Where that lattice leaves
fewer than ``min_nodes`` nodes in a search area (a coarse DEM), the nodes are set up to four times
finer than the DEM's posts, no finer than 5 m: the skyline a camera near the ground sees changes by
degrees within one coarse cell.  With no area the whole DEM is built if that takes at most four cells.

Example: a 4 m DSM (whose file carries no CRS), a photo taken within 600 m of a known point::

    area = SearchArea(circle=(60.5990, 7.5400, 600.0))  # lat, lon (deg), radius (m)
    opened = open_map("time_lapse_finse_DSM_midfilled.tif", area=area, crs="EPSG:32632")
    opened.spacing_m  # 8.0: two cells, 154 x 154 nodes over the 1.2 km box (at 4 m: 4 times as many)
    opened.built_s  # seconds of the build (about 5 on two cores); None the next time: from the cache
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.bodies import Body, body_named
from appliance.errors import DatabaseError, InputError
from appliance.inputs import check_nesting
from appliance.locating.tiled_index import TiledIndex, box_around, is_tiled, open_tiled, select_tiles
from appliance.terrain.database import (
    FORMAT_VERSION,
    MAGIC,
    SkylineDatabase,
    build_database,
    load_database,
)
from appliance.terrain.dem import DEMO_DEM
from appliance.terrain.elevation import Dem
from appliance.terrain.grid import NodeGrid, plan_grids
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
from appliance.terrain.mosaic import MapSource
from appliance.terrain.mosaic import open_map as open_dem_source
from appliance.terrain.verified import cache_root

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float]

#: Azimuths per skyline of a database built here (as ``viper precompute`` builds by default).
N_AZIMUTHS = 360
#: Candidate nodes of a database built for a search area.
DEFAULT_MAX_NODES = 40_000
#: A search area's database holds at least this many nodes: where the DEM's own posts give fewer,
#: the nodes are set finer than the posts (a camera near the ground sees the slopes beside it move by
#: degrees within one coarse cell), down to MAX_DENSIFY nodes per cell and MIN_SPACING_M.
DEFAULT_MIN_NODES = 12_000
MAX_DENSIFY = 4
MIN_SPACING_M = 5.0
#: With no search area, the whole DEM is built only at a spacing of at most this many of its cells.
WHOLE_MAP_MAX_CELLS = 4
#: A cached database is reused for an area whose own spacing is at least its spacing over this.
REUSE_COARSER = 2.0
#: Suffix of a database file in the cache folder.
SUFFIX = ".viperdb"
#: Folder of the built databases inside the appliance's cache folder.
CACHE_SUBDIR = "maps"


@dataclass(frozen=True)
class SearchArea:
    """A circle (lat, lon, radius_m) or a lon/lat box (west, south, east, north), degrees."""

    circle: tuple[float, float, float] | None = None
    box: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if (self.circle is None) == (self.box is None):
            raise InputError("a search area is a circle (--near) or a box (--search-bounds), one of the two")
        values = self.circle if self.circle is not None else self.box
        if not all(math.isfinite(v) for v in values or ()):
            raise InputError(f"{self.describe()}: every value must be a finite number")
        if self.circle is not None:
            lat, lon, radius_m = self.circle
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
                raise InputError(f"{self.describe()}: expected a latitude in [-90, 90] and a longitude in degrees")
            if not radius_m > 0.0:
                raise InputError(f"{self.describe()}: the radius must be positive (m)")
        if self.box is not None:
            w, s, e, n = self.box
            if not (w < e and s < n and -90.0 <= s and n <= 90.0):
                raise InputError(f"{self.describe()}: expected W,S,E,N with W < E, S < N, latitudes in [-90, 90]")

    def describe(self) -> str:
        """The area as the command line gives it."""
        if self.circle is not None:
            lat, lon, radius_m = self.circle
            return f"--near {lat:g},{lon:g},{radius_m:g}"
        w, s, e, n = self.box or (math.nan,) * 4
        return f"--search-bounds {w:g},{s:g},{e:g},{n:g}"

    def bounds_lonlat(self, body: Body) -> Box:
        """The lon/lat box (W, S, E, N, degrees) that holds the area."""
        if self.circle is not None:
            lat, lon, radius_m = self.circle
            return box_around(lat, lon, radius_m, body.name.value)
        assert self.box is not None
        return self.box

    def contains(self, lon: np.ndarray, lat: np.ndarray, body: Body) -> np.ndarray:
        """Whether each point (degrees) lies in the area: within the radius along the body's geodesic
        for a circle, inside the box (longitudes modulo 360) for a box; False where lon/lat is NaN."""
        lon = np.asarray(lon, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        finite = np.isfinite(lon) & np.isfinite(lat)
        if self.circle is not None:
            lat0, lon0, radius_m = self.circle
            lon_f, lat_f = np.where(finite, lon, lon0), np.where(finite, lat, lat0)
            _, _, d = body.geod.inv(np.full(lon.shape, lon0), np.full(lat.shape, lat0), lon_f, lat_f)
            return finite & (np.asarray(d) <= radius_m)
        assert self.box is not None
        w, s, e, n = self.box
        with np.errstate(invalid="ignore"):
            in_lon = (e - w >= 360.0) | (np.mod(lon - w, 360.0) <= e - w)
            return finite & in_lon & (lat >= s) & (lat <= n)


@dataclass(frozen=True)
class OpenedMap:
    """The map a photo is located on: one database or a tiled one, and how it was come by."""

    database: SkylineDatabase | None  # exactly one of database / tiled is set
    tiled: TiledIndex | None
    built_s: float | None  # seconds spent building the database now; None when opened or cached
    cache_path: Path | None  # the cached database file used or made (DEM input only)
    spacing_m: float | None  # the candidate nodes' spacing (the larger of the two directions)


def default_cache_dir() -> Path:
    """The folder of the databases built from DEMs: ``maps`` in the appliance's cache folder
    ($VIPER_CACHE_DIR, else the unit's $CACHE_DIRECTORY, else $XDG_CACHE_HOME/viper, else
    ~/.cache/viper)."""
    root = cache_root()
    if root is None:
        raise InputError("no cache folder can be named (no $VIPER_CACHE_DIR, $XDG_CACHE_HOME or home folder): "
                         "give --cache DIR")
    return root / CACHE_SUBDIR


def open_map(path: str | Path, *, area: SearchArea | None, crs: str | None = None, cache_dir: Path | None = None,
             height_m: float = DEFAULT_HEIGHT_M, max_nodes: int = DEFAULT_MAX_NODES,
             progress: Callable[[int, int, str], None] | None = None, min_nodes: int = DEFAULT_MIN_NODES) -> OpenedMap:
    """Open the map at ``path``: a skyline database file, a tiled database folder, or a DEM file.

    A database (file or folder) is opened as it is (``area`` is checked to meet it; ``crs``,
    ``height_m`` and ``max_nodes`` do not apply).  A DEM's database over ``area`` (the whole DEM when
    None) is taken from ``cache_dir`` (default :func:`default_cache_dir`) or built into it, at the
    spacing the module's docstring states, for a camera ``height_m`` above the ground; ``progress``
    receives the build's progress (done, total, what)."""
    p = Path(path)
    if is_tiled(p):
        index = open_tiled(p)
        if area is not None:
            select_tiles(index, area.bounds_lonlat(body_named(index.body)))  # one line when no tile meets it
        return OpenedMap(None, index, None, None, _tiled_spacing_m(index))
    if _is_database(p):
        db = load_database(p)
        if area is not None:
            area_log_prior(db, area)  # one line when the database does not cover the area
        return OpenedMap(db, None, None, None, _grid_spacing_m(db.grid))
    if not p.exists() and str(path) != DEMO_DEM:
        raise InputError(f"{p}: no such map (a skyline database file, a tiled database folder or a DEM file)")
    return _open_dem(str(path), area, crs, cache_dir, height_m, max_nodes, progress, min_nodes)


def area_log_prior(db: SkylineDatabase, area: SearchArea | None) -> np.ndarray | None:
    """Per node of ``db``: 0 inside ``area``, -inf outside (None for no area).  Refuses in one line
    an area that holds no valid node of the database, giving the database's lon/lat extent."""
    if area is None:
        return None
    body = body_named(str(db.header.get("body", "earth")))
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(np.arange(db.grid.n_nodes)))
    inside = area.contains(lon, lat, body)
    valid = db.valid_nodes
    if not (inside & valid).any():
        raise InputError(f"{db.path} does not cover {area.describe()}: {_extent_text(lon[valid], lat[valid])}")
    return np.where(inside, 0.0, -np.inf)


def _extent_text(lon: np.ndarray, lat: np.ndarray) -> str:
    if lon.size == 0:
        return "it has no valid node"
    return (f"its nodes span longitude {np.min(lon):.5f} to {np.max(lon):.5f}, latitude {np.min(lat):.5f} to "
            f"{np.max(lat):.5f}")


def _is_database(p: Path) -> bool:
    """Whether ``p`` is a file that starts as a skyline database does."""
    if not p.is_file():
        return False
    try:
        with p.open("rb") as fh:
            return fh.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _grid_spacing_m(grid: NodeGrid) -> float:
    return float(max(grid.dx_m, grid.dy_m))


def _tiled_spacing_m(index: TiledIndex) -> float | None:
    """The node spacing an index records (a regional lattice, or a whole body's facets), if any."""
    for key, fields in (("lattice", ("dx_m", "dy_m")), ("whole_body", ("spacing_m",))):
        rec = index.raw.get(key)
        if isinstance(rec, dict):
            vals = [rec.get(f) for f in fields]
            numbers = [float(v) for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)]
            if len(numbers) == len(vals) and all(math.isfinite(v) and v > 0 for v in numbers):
                return max(numbers)
    return None


# ---------------------------------------------------------------------------------------------
# A DEM: the planned grid, the cache and the build


@dataclass(frozen=True)
class _Plan:
    """The database an area of a DEM asks for: its box (clipped to the DEM), the spacing given to
    the grid planner (None: the DEM's own pixels), and the candidate grid that gives."""

    box: Box
    spacing_arg: float | None
    cand: NodeGrid

    @property
    def spacing_m(self) -> float:
        return _grid_spacing_m(self.cand)


def _open_dem(path: str, area: SearchArea | None, crs: str | None, cache_dir: Path | None, height_m: float,
              max_nodes: int, progress: Callable[[int, int, str], None] | None, min_nodes: int) -> OpenedMap:
    if max_nodes < 1:
        raise InputError(f"max_nodes {max_nodes}: at least 1")
    if not 0.0 <= height_m < 1000.0:
        raise InputError(f"camera height {height_m} m outside [0, 1000)")
    source = open_dem_source([path], None, crs)
    header = source.header()  # georeferencing only: the heights are read only for a build
    box = _clipped_box(header, area, path)
    plan = _plan(header, box, max_nodes, area, path, min_nodes)
    folder = cache_dir if cache_dir is not None else default_cache_dir()
    _make_folder(folder)
    for cached in _cached(folder, source, header, plan, height_m):
        try:
            db = load_database(cached)
        except DatabaseError as exc:
            log.warning("cached database left unused: %s", exc)
        else:
            log.info("%s: cached database %s (%s nodes at %.1f m)", path, cached, f"{db.grid.n_nodes:,}",
                     _grid_spacing_m(db.grid))
            return OpenedMap(db, None, None, cached, _grid_spacing_m(db.grid))
    out = folder / _file_name(source, header, plan, height_m)
    log.info("%s: building the skyline database of %s nodes at %.1f m into %s", path, f"{plan.cand.n_nodes:,}",
             plan.spacing_m, out)
    t0 = time.perf_counter()
    dem = source.load()
    build_database(dem, out, plan.box, plan.spacing_arg, height_m, N_AZIMUTHS, progress=progress)
    built_s = time.perf_counter() - t0
    db = load_database(out, dem)
    return OpenedMap(db, None, built_s, out, _grid_spacing_m(db.grid))


def _clipped_box(dem: Dem, area: SearchArea | None, path: str) -> Box:
    """The box of ``area`` clipped to the DEM (longitudes in the DEM's turn); the DEM's box for no
    area.  Refuses in one line an area that does not meet the DEM."""
    west, south, east, north = dem.bounds_lonlat()
    if area is None:
        return west, south, east, north
    w, s, e, n = area.bounds_lonlat(dem.body)
    extent = f"the DEM spans longitude {west:.5f} to {east:.5f}, latitude {south:.5f} to {north:.5f}"
    turn = next((k * 360.0 for k in (0, -1, 1, -2, 2) if w + k * 360.0 < east and e + k * 360.0 > west), None)
    if turn is None or n <= south or s >= north:
        raise InputError(f"{path} does not cover {area.describe()}: {extent}")
    w, e = w + turn, e + turn
    if area.circle is not None:
        # the point of the DEM's box nearest the centre (lon/lat clamped) must lie within the radius
        lat0, lon0, radius_m = area.circle
        lon0 += turn
        near = area.contains(np.array([min(max(lon0, west), east)]), np.array([min(max(lat0, south), north)]),
                             dem.body)
        if not bool(near[0]):
            raise InputError(f"{path} does not cover {area.describe()}: {extent}")
    return max(w, west), max(s, south), min(e, east), min(n, north)


def _densified(box: Box, cand: NodeGrid, grid_at: Callable[[float | None], NodeGrid], min_nodes: int,
               max_nodes: int) -> _Plan:
    """The DEM's own grid, or one k times finer (k = 2 .. MAX_DENSIFY, no finer than MIN_SPACING_M)
    where the own grid holds fewer than ``min_nodes`` nodes: the first k that reaches it, or the
    finest within ``max_nodes``."""
    best = _Plan(box, None, cand)
    cell_m = math.sqrt(cand.dx_m * cand.dy_m)
    for k in range(2, MAX_DENSIFY + 1):
        if best.cand.n_nodes >= min_nodes or cell_m / k < MIN_SPACING_M:
            break
        finer = grid_at(cell_m / k)
        if finer.n_nodes > max_nodes:
            break
        best = _Plan(box, cell_m / k, finer)
    return best


def _plan(dem: Dem, box: Box, max_nodes: int, area: SearchArea | None, path: str,
          min_nodes: int = DEFAULT_MIN_NODES) -> _Plan:
    """The coarsest spacing needed: the DEM's own pixels if they give at most ``max_nodes`` nodes in
    ``box`` (for a search area, finer where they give fewer than ``min_nodes``: :func:`_densified`),
    else k cells (k = 2, 3, ...) on a square grid; with no area, at most :data:`WHOLE_MAP_MAX_CELLS` cells."""

    def grid_at(spacing: float | None) -> NodeGrid:
        return plan_grids(dem, box, spacing, DEFAULT_MAX_RANGE_M)[0]

    cand = grid_at(None)
    if cand.n_nodes <= max_nodes:
        return _densified(box, cand, grid_at, min_nodes, max_nodes) if area is not None else _Plan(box, None, cand)
    cell_m = math.sqrt(cand.dx_m * cand.dy_m)  # the DEM's pixel, as the grid planner measures it
    k = max(2, math.floor(math.sqrt(cand.n_nodes / max_nodes)))
    while True:
        if area is None and k > WHOLE_MAP_MAX_CELLS:
            coarsest = grid_at(WHOLE_MAP_MAX_CELLS * cell_m)
            raise InputError(
                f"{path}: the whole DEM takes {coarsest.n_nodes:,} nodes even at {WHOLE_MAP_MAX_CELLS} cells "
                f"({WHOLE_MAP_MAX_CELLS * cell_m:.1f} m), more than {max_nodes:,}: give --near LAT,LON,RADIUS_M or "
                "--search-bounds W,S,E,N"
            )
        cand = grid_at(k * cell_m)
        if cand.n_nodes <= max_nodes:
            return _Plan(box, k * cell_m, cand)
        k += 1


def _make_folder(folder: Path) -> None:
    if folder.exists() and not folder.is_dir():
        raise InputError(f"cache folder {folder}: not a folder; give another with --cache DIR")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise InputError(f"cache folder {folder}: cannot be created ({why}); give another with --cache DIR") from None


def _key(source: MapSource, dem: Dem, box: Box, spacing_m: float, height_m: float) -> str:
    """SHA-256 (hex) of what makes a database: the DEM's content and CRS, the box, the spacing, the
    camera height, the azimuth count and the database format."""
    record = {"dem_sha256": source.sha256, "crs": dem.crs.to_wkt(), "box": [float(v) for v in box],
              "spacing_m": float(spacing_m), "height_m": float(height_m), "n_azimuths": N_AZIMUTHS,
              "format_version": FORMAT_VERSION}
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def _file_name(source: MapSource, dem: Dem, plan: _Plan, height_m: float) -> str:
    """``<DEM stem>-<W>_<S>_<E>_<N>-<spacing>m-<first 12 hex of the key>.viperdb``."""
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(source.path).stem)[:64] or "dem"
    box = "_".join(f"{v:.5f}" for v in plan.box)
    spacing = f"{round(plan.spacing_m, 1):g}"
    return f"{stem}-{box}-{spacing}m-{_key(source, dem, plan.box, plan.spacing_m, height_m)[:12]}{SUFFIX}"


def _cached(folder: Path, source: MapSource, dem: Dem, plan: _Plan, height_m: float) -> list[Path]:
    """The cached databases that will do for ``plan``, best first: same DEM content, CRS, height,
    azimuths, reach, refraction and format; a box containing the plan's; a spacing at most
    :data:`REUSE_COARSER` times the plan's.  Nearest the plan's spacing first, then fewest nodes."""
    crs_wkt = dem.crs.to_wkt()
    found: list[tuple[float, int, str]] = []
    for p in sorted(folder.glob("*" + SUFFIX)):
        h = _read_header(p)
        if h is None:
            continue
        try:
            same = (h.get("format_version") == FORMAT_VERSION and h.get("dem_sha256") == source.sha256
                    and h.get("dem_crs") == crs_wkt and float(h["height_m"]) == float(height_m)
                    and int(h["n_azimuths"]) == N_AZIMUTHS and float(h["max_range_m"]) == DEFAULT_MAX_RANGE_M
                    and float(h["refraction"]) == dem.body.refraction)
            if not same:
                continue
            w, s, e, n = (float(v) for v in h["search_bounds"])
            spacing_m = max(float(h["grid"]["dx_m"]), float(h["grid"]["dy_m"]))
            n_nodes = int(h["n_nodes"])
        except (KeyError, TypeError, ValueError):
            continue
        pw, ps, pe, pn = plan.box
        tol = 1e-9
        if not (w <= pw + tol and s <= ps + tol and e >= pe - tol and n >= pn - tol):
            continue
        if not 0.0 < spacing_m <= REUSE_COARSER * plan.spacing_m * (1 + 1e-9):
            continue
        found.append((abs(math.log(spacing_m / plan.spacing_m)), n_nodes, p.name))
    return [folder / name for _, _, name in sorted(found)]


def _read_header(p: Path) -> dict | None:
    """The JSON header of a database file, or None for anything else (no checksum checked: the
    database chosen is checked in full when it is loaded)."""
    try:
        if not p.is_file():
            return None
        with p.open("rb") as fh:
            if fh.read(len(MAGIC)) != MAGIC:
                return None
            hlen = int.from_bytes(fh.read(4), "little")
            if hlen > 1 << 24:
                return None
            raw = fh.read(hlen)
        check_nesting(raw)
        header = json.loads(raw.decode())
    except (OSError, ValueError):
        return None
    return header if isinstance(header, dict) else None
