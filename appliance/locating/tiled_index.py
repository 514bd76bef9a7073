"""A tiled skyline database's index: the folder, its tiles and the lon/lat area each covers.

A tiled database is a folder holding ``index.json`` and one format-3 database per tile, each a
window of one mosaic-wide candidate lattice (or, for a whole body, a facet on its own grid,
:mod:`appliance.terrain.whole_body`).  Opening one checks the index only; a search maps the tiles it
touches (:mod:`appliance.locating.tile_cache`).  A search box, or a position and radius, chooses the
tiles (longitudes compared modulo 360).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from appliance.bodies import body_named
from appliance.errors import DatabaseError, InputError
from appliance.inputs import MAX_INDEX_BYTES, read_json_bounded
from appliance.terrain.dem import Dem
from appliance.terrain.grid import lon_overlap
from appliance.terrain.mosaic import open_map

INDEX_NAME = "index.json"
INDEX_FORMAT = "viper-tiled-db"
INDEX_VERSION = 1

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
        index = read_json_bounded(p / INDEX_NAME, INDEX_NAME, MAX_INDEX_BYTES, DatabaseError)
    except FileNotFoundError:
        raise _bad(p, f"no {INDEX_NAME}") from None
    except DatabaseError:
        raise
    except OSError as exc:
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

