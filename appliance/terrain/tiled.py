"""A tiled skyline database, built tile by tile as Dask tasks.

One candidate lattice covers the whole map: the very grid a single-process build of the map would
use (same CRS, origin, spacing and metric spacing, the latter taken at the whole map's centre), cut
into tiles of ``tile_nodes`` nodes.  Each tile is one task that reads only its own window of the map
(the tile plus the horizon's reach, clipped to the map), sweeps the tile's skylines with the sweep
lines of the whole lattice, and writes ``tile_rRRR_cCCC.viperdb``: an ordinary single-file database
whose grid is that window of the lattice.  ``index.json``, written last, says where every tile lies.

A rerun into the same folder with the same parameters keeps every tile that exists and loads
(checksums verified) and builds only the others, so an interrupted build resumes where it stopped.
"""

from __future__ import annotations

import json
import logging
import math
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from appliance.atomic import atomic_output, remove_stale_temporaries
from appliance.errors import DatabaseError, DemError, InputError, NodataCandidatesError, OutputError
from appliance.terrain.database import build_on_grids, load_database
from appliance.terrain.dem import Dem
from appliance.terrain.grid import NodeGrid, _dem_pixel_origin, lattice_of, plan_grids
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
from appliance.terrain.mosaic import MapSource

INDEX = "index.json"
INDEX_FORMAT = "viper-tiled-db"
INDEX_VERSION = 1
#: Candidate nodes per tile: an SRTM 3-arc-second tile's worth (DESIGN.md, "Decisions", says why).
DEFAULT_TILE_NODES = (1201, 1201)

log = logging.getLogger("appliance.terrain.tiled")


@dataclass(frozen=True)
class Tile:
    """One tile: candidate rows row0.. and columns col0.. of the lattice, the terrain window around
    it (rows, cols in the whole terrain grid) and the map pixels to read for it."""

    file: str
    row0: int
    col0: int
    n_rows: int
    n_cols: int
    terrain: tuple[int, int, int, int]
    pixels: tuple[int, int, int, int]


@dataclass(frozen=True)
class TiledPlan:
    """The whole map's candidate and terrain grids, where the terrain grid lies in the sweep
    lattice, and the tiles."""

    cand: NodeGrid
    terr: NodeGrid
    offset: tuple[int, int]
    lattice_origin: tuple[int, int]
    lattice_shape: tuple[int, int]
    tiles: tuple[Tile, ...]


@dataclass(frozen=True)
class TiledResult:
    index: dict
    built: tuple[str, ...]
    kept: tuple[str, ...]
    #: the largest peak resident memory (bytes) of a worker process that built a tile
    peak_rss_bytes: int
    seconds: float
    #: the tiles wholly on nodata, left out of the index
    void: tuple[str, ...] = ()


def _window(grid: NodeGrid, r0: int, c0: int, n_rows: int, n_cols: int) -> NodeGrid:
    """Rows r0.. and columns c0.. of ``grid``, with its spacings (metric ones included) unchanged."""
    x0, y0 = grid.rc_to_xy(r0, c0)
    return NodeGrid(grid.crs_wkt, float(x0), float(y0), grid.dx, grid.dy, n_rows, n_cols, grid.dx_m, grid.dy_m)


def plan_tiles(dem: Dem, search_bounds: tuple[float, float, float, float] | None, spacing_m: float | None,
               max_range_m: float, tile_nodes: tuple[int, int] = DEFAULT_TILE_NODES) -> TiledPlan:
    """Cut the single-process build's candidate grid into tiles; ``dem`` may be a map's header alone
    (:meth:`MapSource.header`), since only its georeferencing is used."""
    tr, tc = tile_nodes
    if tr < 1 or tc < 1:
        raise InputError(f"--tile-nodes {tr},{tc}: both counts must be positive")
    cand, terr, (ro, co) = plan_grids(dem, search_bounds, spacing_m, max_range_m)
    origin, shape = lattice_of(dem, terr)
    # the horizon's reach in lattice steps, as plan_grids measures it
    reach = max_range_m if not terr.crs.is_geographic else max_range_m / min(terr.dx_m / terr.dx,
                                                                              terr.dy_m / terr.dy)
    # plus two: the row beside a sweep line that its interpolation reads, and a node's offset from
    # its line, so a tile holds every terrain point its nodes' horizons may use
    halo_r, halo_c = math.floor(reach / terr.dy + 1e-9) + 2, math.floor(reach / terr.dx + 1e-9) + 2
    native = _dem_pixel_origin(dem, terr) is not None
    tiles = []
    for r0 in range(0, cand.n_rows, tr):
        for c0 in range(0, cand.n_cols, tc):
            nr, nc = min(tr, cand.n_rows - r0), min(tc, cand.n_cols - c0)
            t_r0 = max(ro + r0 - halo_r, 0)
            t_c0 = max(co + c0 - halo_c, 0)
            t_r1 = min(ro + r0 + nr + halo_r, terr.n_rows)
            t_c1 = min(co + c0 + nc + halo_c, terr.n_cols)
            terrain = (t_r0, t_c0, t_r1 - t_r0, t_c1 - t_c0)
            pixels = (_native_pixels(origin, terrain, dem.shape) if native
                      else _pixels_under(dem, _window(terr, *terrain)))
            tiles.append(Tile(f"tile_r{r0 // tr:03d}_c{c0 // tc:03d}.viperdb", r0, c0, nr, nc, terrain, pixels))
    return TiledPlan(cand, terr, (ro, co), origin, shape, tuple(tiles))


def _native_pixels(origin: tuple[int, int], terrain: tuple[int, int, int, int],
                   shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The map pixels under a terrain window of a grid made of the map's own pixels."""
    r0, c0 = max(origin[0] + terrain[0], 0), max(origin[1] + terrain[1], 0)
    r1 = min(origin[0] + terrain[0] + terrain[2], shape[0])
    c1 = min(origin[1] + terrain[1] + terrain[3], shape[1])
    return r0, c0, r1 - r0, c1 - c0


def _pixels_under(dem: Dem, grid: NodeGrid) -> tuple[int, int, int, int]:
    """The map pixels a resampled grid's bilinear heights use: the box of its edges in pixel
    coordinates, two pixels wider, clipped to the map."""
    from pyproj import Transformer

    t = np.linspace(0.0, 1.0, 41)
    rows = np.concatenate([np.zeros_like(t), t, np.ones_like(t), t]) * (grid.n_rows - 1)
    cols = np.concatenate([t, np.ones_like(t), t, np.zeros_like(t)]) * (grid.n_cols - 1)
    x, y = grid.rc_to_xy(rows, cols)
    dx, dy = Transformer.from_crs(grid.crs, dem.crs, always_xy=True).transform(x, y)
    pc, pr = dem.xy_to_pixel(np.asarray(dx), np.asarray(dy))
    r0 = max(int(math.floor(float(np.nanmin(pr)))) - 2, 0)
    c0 = max(int(math.floor(float(np.nanmin(pc)))) - 2, 0)
    r1 = min(int(math.ceil(float(np.nanmax(pr)))) + 3, dem.shape[0])
    c1 = min(int(math.ceil(float(np.nanmax(pc)))) + 3, dem.shape[1])
    return r0, c0, max(r1 - r0, 1), max(c1 - c0, 1)


def _bounds_lonlat(grid: NodeGrid) -> tuple[float, float, float, float]:
    """(W, S, E, N) degrees of the cells centred on a grid's nodes, from points along their edges."""
    t = np.linspace(0.0, 1.0, 21)
    rows = np.concatenate([np.zeros_like(t), t, np.ones_like(t), t]) * grid.n_rows - 0.5
    cols = np.concatenate([t, np.ones_like(t), t, np.zeros_like(t)]) * grid.n_cols - 0.5
    lon, lat = grid.xy_to_lonlat(*grid.rc_to_xy(rows, cols))
    return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))


def _lattice_entry(g: NodeGrid) -> dict:
    return {"crs_wkt": g.crs_wkt, "x0": g.x0, "y0": g.y0, "dx": g.dx, "dy": g.dy, "n_rows": g.n_rows,
            "n_cols": g.n_cols, "dx_m": g.dx_m, "dy_m": g.dy_m}


def build_tile(source: MapSource, out_dir: str, plan: TiledPlan, tile: Tile, params: dict) -> dict:
    """One task: read the tile's window of the map, build its database, write it atomically.
    Returns the file's name, the seconds taken and this process's peak resident memory."""
    t0 = time.perf_counter()
    dem = source.window(*tile.pixels)
    t_r0, t_c0, t_nr, t_nc = tile.terrain
    terr = _window(plan.terr, t_r0, t_c0, t_nr, t_nc)
    ro, co = plan.offset
    cand = _window(plan.cand, tile.row0, tile.col0, tile.n_rows, tile.n_cols)
    offset = (ro + tile.row0 - t_r0, co + tile.col0 - t_c0)
    origin = (plan.lattice_origin[0] + t_r0, plan.lattice_origin[1] + t_c0)
    build_on_grids(dem, Path(out_dir) / tile.file, cand, terr, offset, origin, plan.lattice_shape,
                   _bounds_lonlat(cand), params["height_m"], params["n_azimuths"], params["refraction"],
                   params["max_range_m"], None, workers=1)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kilobytes on Linux
    return {"file": tile.file, "seconds": time.perf_counter() - t0, "peak_rss_bytes": int(peak)}


def _tile_state(path: Path, expect: dict) -> str:
    """"missing", "kept" (exists, loads, same parameters) or "differs"."""
    if not path.exists():
        return "missing"
    try:
        db = load_database(path)
    except DatabaseError:
        return "missing"  # damaged: built again
    h = db.header
    same = all(h.get(k) == v for k, v in expect.items())
    return "kept" if same else "differs"


def remove_tile_temporaries(out_dir: str | Path) -> list[Path]:
    """Remove the temporary tile files of writers no longer alive (a worker killed mid-write, a local
    cluster closed on an interrupt); a live writer's are left alone."""
    names = {p.name.split(".")[1] + ".viperdb" for p in Path(out_dir).glob(".tile_r*_c*.viperdb.*")}
    removed: list[Path] = []
    for name in sorted(names):
        removed += remove_stale_temporaries(out_dir, name)
    return removed


def build_tiled(
    source: MapSource,
    out_dir: str | Path,
    search_bounds: tuple[float, float, float, float] | None = None,
    spacing_m: float | None = None,
    height_m: float = DEFAULT_HEIGHT_M,
    n_azimuths: int = 360,
    refraction: float | None = None,
    max_range_m: float = DEFAULT_MAX_RANGE_M,
    tile_nodes: tuple[int, int] = DEFAULT_TILE_NODES,
    client: Any = None,
    force: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
) -> TiledResult:
    """Build (or complete) the tiled database of ``source`` in ``out_dir`` on the Dask ``client``.

    Tiles already there with the same parameters are kept; one built with other parameters is an
    error unless ``force`` (then it is built again)."""
    t_start = time.perf_counter()
    out = Path(out_dir)
    if not out.is_dir():
        raise OutputError(f"{out}: output folder does not exist")
    dem = source.header()
    plan = plan_tiles(dem, search_bounds, spacing_m, max_range_m, tile_nodes)
    refr = dem.body.refraction if refraction is None else refraction
    params = {"height_m": height_m, "n_azimuths": n_azimuths, "refraction": refr, "max_range_m": max_range_m}
    index = {
        "format": INDEX_FORMAT,
        "format_version": INDEX_VERSION,
        "lattice": _lattice_entry(plan.cand),
        "tile_nodes": [int(tile_nodes[0]), int(tile_nodes[1])],
        "tiles": [{"file": t.file, "row0": t.row0, "col0": t.col0, "n_rows": t.n_rows, "n_cols": t.n_cols,
                   "bounds_lonlat": list(_bounds_lonlat(_window(plan.cand, t.row0, t.col0, t.n_rows, t.n_cols)))}
                  for t in plan.tiles],
        "n_azimuths": n_azimuths,
        "height_m": height_m,
        "max_range_m": max_range_m,
        "refraction": refr,
        "body": dem.body.name.value,
        "sources": [{"name": n, "sha256": s} for n, s in source.sources],
    }
    jobs = [TileJob(t.file, _lattice_entry(_window(plan.cand, t.row0, t.col0, t.n_rows, t.n_cols)), build_tile,
                    (source, str(out.resolve()), plan, t, params)) for t in plan.tiles]
    keys = ("format", "format_version", "lattice", "tile_nodes", "n_azimuths", "height_m", "max_range_m",
            "refraction", "body", "sources")
    return run_tile_jobs(source, out, index, keys, params, jobs, client, force, progress, "tiles", t_start)


@dataclass(frozen=True)
class TileJob:
    """One file of a tiled database: its name, its candidate grid (:func:`_lattice_entry`) and the
    Dask task that builds it, ``task(*args)``, returning its file, seconds and peak memory."""

    file: str
    grid: dict
    task: Callable[..., dict]
    args: tuple


def run_tile_jobs(source: MapSource, out: Path, index: dict, keys: tuple[str, ...], params: dict,
                  jobs: list[TileJob], client: Any, force: bool,
                  progress: Callable[[int, int, str], None] | None, unit: str, t_start: float) -> TiledResult:
    """Build the jobs' files missing from ``out`` on the Dask ``client`` and write ``index`` last.

    An index already there whose ``keys`` differ, or a file built with other ``params`` (or from
    another map), is an error unless ``force`` (then it is built again); a file with the same ones
    is kept, so an interrupted build resumes where it stopped."""
    old_path = out / INDEX
    if old_path.exists() and not force:
        try:
            old = json.loads(old_path.read_text())
        except (OSError, ValueError):
            old = None
        differ = [k for k in keys if not isinstance(old, dict) or old.get(k) != index[k]]
        if differ:
            raise OutputError(f"{out}: holds a tiled database built with other parameters ({', '.join(differ)}); "
                              "pass --force to build it again")
    todo: list[TileJob] = []
    kept: list[TileJob] = []
    for job in jobs:
        state = _tile_state(out / job.file, dict(params, dem_sha256=source.sha256, grid=job.grid))
        if state == "differs" and not force:
            raise OutputError(f"{out / job.file}: built with other parameters; pass --force to build it again")
        (kept if state == "kept" else todo).append(job)
    built: list[str] = []
    void: set[str] = set()
    peak = 0
    if todo:
        from distributed import as_completed

        if client is None:
            raise InputError("a tiled build needs a Dask client")
        futures = {client.submit(job.task, *job.args, pure=False): job.file for job in todo}
        done = len(kept)
        if progress is not None:
            progress(done, len(jobs), unit)
        try:
            for fut in as_completed(futures):
                try:
                    res = fut.result()
                except NodataCandidatesError:
                    # a tile wholly on nodata (off the map's edge, in a void) holds no candidate:
                    # it has no file and the index leaves it out (a rerun finds it void again)
                    void.add(futures[fut])
                    res = None
                if res is not None:
                    built.append(res["file"])
                    peak = max(peak, int(res["peak_rss_bytes"]))
                    log.debug("%s built in %.1f s", res["file"], res["seconds"])
                done += 1
                if progress is not None:
                    progress(done, len(jobs), unit)
        finally:
            client.cancel(list(futures))
    remove_tile_temporaries(out)
    if void:
        index = dict(index, tiles=[t for t in index["tiles"] if t["file"] not in void])
        if not index["tiles"]:
            raise DemError(f"{source.name}: every candidate node is nodata; no {unit[:-1]} to build")
    with atomic_output(old_path) as tmp:
        tmp.write_text(json.dumps(index, indent=1) + "\n")
    return TiledResult(index, tuple(built), tuple(job.file for job in kept), peak, time.perf_counter() - t_start,
                       tuple(sorted(void)))
