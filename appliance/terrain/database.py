"""The skyline database: the skyline of every node of a candidate grid, compact and memory-mapped.

File layout (little-endian)::

    8 bytes   magic b"VIPERDB\\0"
    4 bytes   uint32 header length H
    H bytes   JSON header (format version, DEM identity, grid, camera height, body, refraction,
              azimuth sampling, array offsets), padded with spaces to a multiple of 64
    arrays    codes uint8[n_nodes, n_azimuths]  (255 = no terrain along that azimuth)
              distance uint8[n_nodes, n_azimuths]  (log-quantised range of the horizon; 255 = none)
              offset_deg float32[n_nodes]       (NaN = node on nodata)
              step_deg float32[n_nodes]
              ground_m float32[n_nodes]
              convergence_deg float32[n_nodes]  (true azimuth of grid north)
              terrain_m float32[terrain rows, terrain cols]  (the heights the skylines were built on)
              coarse_codes uint8[n_nodes, n_azimuths / 4]  (the estimator's first pass: codes averaged
                                                 over runs of four azimuths)
              coarse_partial bool[n_nodes]      (the node lacks terrain somewhere, or is nodata)
              coarse_tau2 uint8[n_nodes, n_azimuths / 4]  (the parallax variance of each run, log codes)
    checksums uint32[1 + blocks]                (CRC32 of bytes 0..end of the header, then of each
                                                 CHECKSUM_BLOCK bytes of the arrays; the header's
                                                 "checksum" entry gives its offset and block size)

The codes and ranges are quantised as :mod:`appliance.terrain.quantize` says, on the node grid of
:mod:`appliance.terrain.grid`.  The range says how fast the skyline moves with position (parallax),
and the terrain grid lets the estimator render exact skylines between nodes; candidate node (0, 0)
is terrain node (row0, col0), same spacing.

The checksums (:mod:`appliance.terrain.storage`) are verified when the database is loaded: a flipped
bit is a one-line error naming the block.  A file that passed is recorded
(:mod:`appliance.terrain.verified`) and, unchanged since, is not read through again on later loads;
its header is checked every time.  The first-pass arrays are made at build time so that no
estimate has to make them.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from appliance.atomic import atomic_output, scratch_file
from appliance.bodies import body_named
from appliance.errors import DatabaseError, InputError, NodataCandidatesError
from appliance.estimator import COARSE_STRIDE, SkylineGrid, first_pass_ahead
from appliance.inputs import check_nesting, open_regular
from appliance.terrain.dem import Dem
from appliance.terrain.grid import NodeGrid, grid_convergence_deg, lattice_of, plan_grids, terrain_on_grid
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
from appliance.terrain.quantize import (
    DISTANCE_LOG_STEP,
    DISTANCE_MIN_M,
    MISSING_CDEG,
    MISSING_CODE,
    decode_distance,
    store_centidegrees,
    turn_and_quantize,
)
from appliance.terrain.storage import (
    CHECKSUM_BLOCK,
    file_block_checksums,
    pread_into,
    pwrite_all,
    run_threads,
    verify_checksums,
)
from appliance.terrain.sweep import HorizonSweeper
from appliance.terrain.verified import FileIdentity

MAGIC = b"VIPERDB\0"
FORMAT_VERSION = 3
ALIGN = 64


@dataclass(frozen=True, eq=False)
class SkylineDatabase:
    """A loaded (memory-mapped) skyline database."""

    path: str
    header: dict
    grid: NodeGrid
    codes: np.ndarray
    offset_deg: np.ndarray
    step_deg: np.ndarray
    ground_m: np.ndarray
    distance_codes: np.ndarray
    convergence_deg: np.ndarray
    terrain_m: np.ndarray
    terrain_origin: tuple[int, int]
    #: the estimator's first pass, made at build: box-averaged codes, the nodes lacking terrain
    #: somewhere, and the parallax variance of each run of azimuths
    coarse_codes: np.ndarray
    coarse_partial: np.ndarray
    coarse_tau2: np.ndarray

    @property
    def n_azimuths(self) -> int:
        return int(self.codes.shape[1])

    @property
    def azimuths_deg(self) -> np.ndarray:
        return np.arange(self.n_azimuths) * (360.0 / self.n_azimuths)

    @property
    def height_m(self) -> float:
        return float(self.header["height_m"])

    @property
    def valid_nodes(self) -> np.ndarray:
        return np.isfinite(self.offset_deg)

    def skylines_deg(self, index: np.ndarray | slice | int) -> np.ndarray:
        """Decoded skylines (deg, NaN = no terrain) of the given nodes, shape (k, n_azimuths)."""
        codes = np.asarray(self.codes[index])
        off = np.asarray(self.offset_deg[index], dtype=np.float64)
        step = np.asarray(self.step_deg[index], dtype=np.float64)
        el = off[..., None] + step[..., None] * codes
        return np.where(codes == MISSING_CODE, np.nan, el)

    def distances_m(self, index: np.ndarray | slice | int) -> np.ndarray:
        """Range (m) of the terrain forming each azimuth's horizon (NaN = no terrain)."""
        return decode_distance(np.asarray(self.distance_codes[index]))

    @property
    def r_eff_m(self) -> float:
        return body_named(self.header["body"]).effective_radius_m(self.header["refraction"])


def build_database(
    dem: Dem,
    out_path: str | Path,
    search_bounds: tuple[float, float, float, float] | None = None,
    spacing_m: float | None = None,
    height_m: float = DEFAULT_HEIGHT_M,
    n_azimuths: int = 360,
    refraction: float | None = None,
    max_range_m: float = DEFAULT_MAX_RANGE_M,
    progress: Callable[[int, int, str], None] | None = None,
    workers: int | None = None,
) -> dict:
    """Render every candidate node's skyline and write the database atomically; returns its header.

    Azimuths are swept in parallel on ``workers`` threads (default: one per core), each running
    single-threaded kernels that release the GIL (DESIGN.md, "Decisions").  A node's horizon comes
    from the terrain within ``max_range_m`` of it and nothing beyond (an exact cut-off, see
    HorizonSweeper), so a build in tiles, each with a halo of that range, equals a build of the
    whole map node for node.

    Memory: each azimuth's skylines go to an unnamed scratch file beside the output as they are
    swept (3 bytes per node and azimuth on disk, besides the output), and are read back a chunk of
    nodes at a time to be turned, quantised and written, so that the build holds the terrain, the
    sweep's work arrays and one chunk, not every skyline."""
    _check_sampling(n_azimuths, height_m)
    cand, terr, offset = plan_grids(dem, search_bounds, spacing_m, max_range_m)
    origin, shape = lattice_of(dem, terr)
    bounds = search_bounds if search_bounds is not None else dem.bounds_lonlat()
    return build_on_grids(dem, out_path, cand, terr, offset, origin, shape, bounds, height_m, n_azimuths,
                          refraction, max_range_m, progress, workers)


def _check_sampling(n_azimuths: int, height_m: float) -> None:
    """Refuse an azimuth count or camera height no database can be built with."""
    if not 8 <= n_azimuths <= 3600:
        raise InputError(f"azimuth count {n_azimuths} outside [8, 3600]")
    if not 0.0 <= height_m < 1000.0:
        raise InputError(f"camera height {height_m} m outside [0, 1000)")


def build_on_grids(
    dem: Dem,
    out_path: str | Path,
    cand: NodeGrid,
    terr: NodeGrid,
    offset: tuple[int, int],
    lattice_origin: tuple[int, int],
    lattice_shape: tuple[int, int],
    search_bounds: tuple[float, float, float, float],
    height_m: float = DEFAULT_HEIGHT_M,
    n_azimuths: int = 360,
    refraction: float | None = None,
    max_range_m: float = DEFAULT_MAX_RANGE_M,
    progress: Callable[[int, int, str], None] | None = None,
    workers: int | None = None,
    keep: np.ndarray | None = None,
) -> dict:
    """The database of a candidate grid already planned: ``cand`` lies at ``offset`` (row, col) in the
    terrain grid ``terr``, and ``terr`` at ``lattice_origin`` in a lattice of ``lattice_shape`` nodes.

    A tiled build passes windows of one mosaic-wide lattice here, so that every tile's sweep lines,
    metric spacing and node placement are those of the whole map, not re-planned from its bounds.
    ``keep`` (bool per candidate node, row-major) leaves the other nodes out of the database as
    nodes on nodata are (no skyline, NaN offset): a facet of a whole-body build keeps only the
    nodes inside its own lon/lat box."""
    _check_sampling(n_azimuths, height_m)
    if keep is not None and np.shape(keep) != (cand.n_nodes,):
        raise InputError(f"keep mask of shape {np.shape(keep)} for {cand.n_nodes} candidate nodes")
    ro, co = offset
    Z = terrain_on_grid(dem, terr)
    if not np.isfinite(Z[ro : ro + cand.n_rows, co : co + cand.n_cols]).any():
        raise NodataCandidatesError(f"{dem.source}: every candidate node inside the search bounds is nodata")
    r_eff = dem.body.effective_radius_m(refraction)
    gamma = grid_convergence_deg(cand, dem.crs.geodetic_crs or dem.crs)
    step_az = 360.0 / n_azimuths
    n = cand.n_nodes
    sweeper = HorizonSweeper(Z, terr.dx_m, terr.dy_m, height_m, r_eff, (ro, co, cand.n_rows, cand.n_cols),
                             lattice_origin, lattice_shape, max_range_m)
    left_out = None if keep is None else ~np.asarray(keep, dtype=bool)
    header = _header(dem, cand, terr, offset, search_bounds, height_m, n_azimuths, refraction, max_range_m)
    ground = Z[ro : ro + cand.n_rows, co : co + cand.n_cols].ravel().astype(np.float32)
    if left_out is not None:
        ground[left_out] = np.nan
    plan = _FilePlan.of(header, n, n_azimuths, Z.size)
    # the output and the spill are both allocated on disk before the sweep: a full disk fails now
    with atomic_output(out_path, preallocate=plan.file_bytes) as tmp, \
            scratch_file(out_path, preallocate=3 * n_azimuths * n) as spill:

        def one_azimuth(j: int) -> None:
            tan, far = sweeper.horizons(j * step_az)
            cdeg = np.empty(n, dtype=np.int16)  # centidegrees at grid azimuth j
            dgrid = np.empty(n, dtype=np.uint8)  # ranges at grid azimuth j
            store_centidegrees(tan, far, cdeg, dgrid)
            if left_out is not None:
                cdeg[left_out] = MISSING_CDEG
                dgrid[left_out] = MISSING_CODE
            pwrite_all(spill, cdeg, 2 * n * j)
            pwrite_all(spill, dgrid, 2 * n * n_azimuths + n * j)

        done = 0
        for _ in run_threads(one_azimuth, range(n_azimuths), workers):
            done += 1
            if progress is not None:
                progress(done, n_azimuths, "skylines")
        fd = os.open(tmp, os.O_RDWR | os.O_CLOEXEC)
        try:
            _write(fd, plan, spill, gamma.ravel(), step_az, ground, Z.astype(np.float32), cand, workers)
        finally:
            os.close(fd)
    return header


def _header(dem: Dem, cand: NodeGrid, terr: NodeGrid, offset: tuple[int, int],
            search_bounds: tuple[float, float, float, float], height_m: float, n_azimuths: int,
            refraction: float | None, max_range_m: float) -> dict:
    """The JSON header of a database (before its array layout and checksum entry)."""
    ro, co = offset
    return {
        "format": "viper-skyline-db",
        "format_version": FORMAT_VERSION,
        "dem_sha256": dem.sha256,
        "dem_source": Path(dem.source).name,
        "dem_crs": dem.crs.to_wkt(),
        "body": dem.body.name.value,
        "refraction": dem.body.refraction if refraction is None else refraction,
        "height_m": height_m,
        "max_range_m": max_range_m,
        "n_azimuths": n_azimuths,
        "grid": {
            "crs_wkt": cand.crs_wkt, "x0": cand.x0, "y0": cand.y0, "dx": cand.dx, "dy": cand.dy,
            "n_rows": cand.n_rows, "n_cols": cand.n_cols, "dx_m": cand.dx_m, "dy_m": cand.dy_m,
        },
        "search_bounds": list(search_bounds),
        "distance_code": {"min_m": DISTANCE_MIN_M, "log_step": DISTANCE_LOG_STEP},
        "terrain": {"n_rows": terr.n_rows, "n_cols": terr.n_cols, "row0": ro, "col0": co},
    }


#: Nodes turned, quantised and written together (their arrays are held in memory at once, two
#: chunks at most), and nodes per thread within them (their skylines read back from the spill with
#: one read per azimuth).
CHUNK_NODES = 1 << 15
THREAD_NODES = 8192


@dataclass(frozen=True)
class _FilePlan:
    """Where everything goes in a database file: its header bytes, where the arrays start, each
    array's offset from there, the checksum table's offset and block count, and the file's size."""

    n_az: int
    head: bytes
    data_start: int
    layout: dict[str, int]
    table: int
    n_blocks: int

    @property
    def file_bytes(self) -> int:
        return self.data_start + self.table + 4 * (1 + self.n_blocks)

    @classmethod
    def of(cls, header: dict, n: int, n_az: int, terrain_size: int) -> _FilePlan:
        n_coarse = n_az // COARSE_STRIDE
        layout = {}
        pos = 0
        sizes = (("codes", n * n_az), ("distance", n * n_az), ("offset_deg", 4 * n), ("step_deg", 4 * n),
                 ("ground_m", 4 * n), ("convergence_deg", 4 * n), ("terrain_m", 4 * terrain_size),
                 ("coarse_codes", n * n_coarse), ("coarse_partial", n), ("coarse_tau2", n * n_coarse))
        for name, nbytes in sizes:
            layout[name] = pos
            pos += -(-nbytes // ALIGN) * ALIGN
        n_blocks = -(-pos // CHECKSUM_BLOCK)
        checksum = {"algorithm": "crc32", "block_bytes": CHECKSUM_BLOCK, "offset": pos, "blocks": n_blocks}
        header = dict(header, arrays=layout, n_nodes=n, checksum=checksum)
        raw = json.dumps(header).encode()
        hlen = -(-(len(raw) + 12) // ALIGN) * ALIGN - 12
        head = MAGIC + np.uint32(hlen).tobytes() + raw.ljust(hlen, b" ")
        return cls(n_az, head, 12 + hlen, layout, pos, n_blocks)

    def at(self, name: str, byte: int = 0) -> int:
        """The file offset of byte ``byte`` of array ``name``."""
        return self.data_start + self.layout[name] + byte


def _write(fd: int, plan: _FilePlan, spill: int, gamma_deg: np.ndarray, step_az: float, ground: np.ndarray,
           terrain: np.ndarray, cand: NodeGrid, workers: int | None) -> None:
    """Write the database into the preallocated file ``fd`` from the skylines at grid azimuths in
    ``spill`` (int16 centidegrees of every node, azimuth after azimuth, then the uint8 ranges likewise),
    a chunk of nodes at a time: each chunk's columns are read back, turned to true azimuths and
    quantised, its first-pass arrays made, and its rows written; two chunks at most are in memory."""
    n, n_az = ground.size, plan.n_az
    n_coarse = n_az // COARSE_STRIDE
    offs = np.empty(n, np.float32)
    steps = np.empty(n, np.float32)
    shift = np.asarray(gamma_deg, dtype=np.float64) / step_az
    # the per-node inputs of the estimator's first pass (ground gradient, offset variance, range
    # table), as the estimator makes them, from a grid with no skylines
    per_node = SkylineGrid(np.empty((n, 0), np.uint8), offs, steps, n_rows=cand.n_rows, n_cols=cand.n_cols,
                           dx_m=cand.dx_m, dy_m=cand.dy_m, ground_m=ground, distance_min_m=DISTANCE_MIN_M,
                           distance_log_step=DISTANCE_LOG_STEP)

    def write_chunk(lo: int, codes: np.ndarray, dist: np.ndarray, coarse: np.ndarray, partial: np.ndarray,
                    tau2: np.ndarray) -> None:
        pwrite_all(fd, codes, plan.at("codes", lo * n_az))
        pwrite_all(fd, dist, plan.at("distance", lo * n_az))
        pwrite_all(fd, coarse, plan.at("coarse_codes", lo * n_coarse))
        pwrite_all(fd, partial.view(np.uint8), plan.at("coarse_partial", lo))
        pwrite_all(fd, tau2, plan.at("coarse_tau2", lo * n_coarse))

    # a chunk is written on a thread of its own while the next one is made: two chunks at most in memory
    with ThreadPoolExecutor(max_workers=1) as writer:
        written: Future[None] | None = None
        for lo in range(0, n, CHUNK_NODES):
            hi = min(lo + CHUNK_NODES, n)
            codes = np.empty((hi - lo, n_az), np.uint8)
            dist = np.empty((hi - lo, n_az), np.uint8)

            def quantize_part(a: int, lo: int = lo, hi: int = hi, codes: np.ndarray = codes,
                              dist: np.ndarray = dist) -> None:
                b = min(a + THREAD_NODES, hi)
                cdeg = np.empty((n_az, b - a), np.int16)
                dgrid = np.empty((n_az, b - a), np.uint8)
                for j in range(n_az):  # this part's column of every azimuth's row
                    pread_into(spill, cdeg[j], 2 * (n * j + a))
                    pread_into(spill, dgrid[j], 2 * n * n_az + n * j + a)
                turn_and_quantize(cdeg, dgrid, shift[a:b], codes[a - lo : b - lo], dist[a - lo : b - lo], offs[a:b],
                                  steps[a:b], 0, b - a)

            for _ in run_threads(quantize_part, range(lo, hi, THREAD_NODES), workers):
                pass
            # the estimator's first pass, exactly as it would make it from the arrays above (per node)
            coarse, partial, tau2 = first_pass_ahead(per_node, codes, dist, slice(lo, hi))
            if written is not None:
                written.result()
            written = writer.submit(write_chunk, lo, codes, dist, coarse, partial, tau2)
            del codes, dist, coarse, partial, tau2
        if written is not None:
            written.result()
    for name, arr in (("offset_deg", offs), ("step_deg", steps), ("ground_m", ground),
                      ("convergence_deg", np.asarray(gamma_deg, dtype=np.float32)),
                      ("terrain_m", np.ascontiguousarray(terrain, dtype=np.float32))):
        pwrite_all(fd, arr, plan.at(name))
    crcs = [zlib.crc32(plan.head)] + file_block_checksums(fd, plan.data_start, plan.table, workers)
    pwrite_all(fd, np.asarray(crcs, dtype="<u4"), plan.data_start + plan.table)
    pwrite_all(fd, np.frombuffer(plan.head, np.uint8), 0)


def load_database(path: str | Path, dem: Dem | None = None, full_check: bool = False) -> SkylineDatabase:
    """Memory-map a database; refuses a foreign format or version, or one from another DEM, and a
    damaged file (see :func:`appliance.terrain.storage.verify_checksums`; ``full_check``: every
    block even if this file was verified before and has not changed since)."""
    p = Path(path)
    try:
        fh = open_regular(p, "database", DatabaseError)
    except DatabaseError:
        raise
    except FileNotFoundError:
        raise DatabaseError(f"{p}: database not found") from None
    except IsADirectoryError:
        raise DatabaseError(f"{p}: is a folder, not a database") from None
    except OSError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatabaseError(f"{p}: unreadable database header ({first})") from None
    # the header, the file's identity and the memory map all come from this one open file
    with fh:
        return _load_open(p, fh, dem, full_check)


def _load_open(p: Path, fh: BinaryIO, dem: Dem | None, full_check: bool) -> SkylineDatabase:
    try:
        magic = fh.read(8)
        if magic != MAGIC:
            raise DatabaseError(f"{p}: not a Viper skyline database")
        hlen_raw = fh.read(4)
        hlen = int(np.frombuffer(hlen_raw, np.uint32)[0])
        if hlen > 1 << 24:
            raise ValueError(f"header length {hlen}")
        raw = fh.read(hlen)
        check_nesting(raw)
        header = json.loads(raw.decode())
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
    except IsADirectoryError:
        raise DatabaseError(f"{p}: is a folder, not a database") from None
    except (OSError, ValueError, IndexError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatabaseError(f"{p}: unreadable database header ({first})") from None
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise DatabaseError(
            f"{p}: database format version {version}, this viper reads version {FORMAT_VERSION}; rebuild it with "
            f"`viper precompute {header.get('dem_source', 'DEM')} --out {p.name}` (same --search-bounds, --spacing, "
            "--height)"
        )
    if dem is not None and header.get("dem_sha256") != dem.sha256:
        raise DatabaseError(
            f"{p}: built from DEM {header.get('dem_source')} ({str(header.get('dem_sha256'))[:12]}), "
            f"not from {Path(dem.source).name} ({dem.sha256[:12]})"
        )
    start = 12 + hlen
    try:
        n = int(header["n_nodes"])
        n_az = int(header["n_azimuths"])
        lay = header["arrays"]
        identity = FileIdentity.of_fd(fh.fileno())
        mm = np.memmap(fh, mode="r", dtype=np.uint8, offset=start)
        verify_checksums(p, header, magic + hlen_raw + raw, mm, identity, full_check)
        codes = mm[lay["codes"] : lay["codes"] + n * n_az].reshape(n, n_az)
        dist = mm[lay["distance"] : lay["distance"] + n * n_az].reshape(n, n_az)
        f32 = {k: mm[lay[k] : lay[k] + 4 * n].view(np.float32)
               for k in ("offset_deg", "step_deg", "ground_m", "convergence_deg")}
        th = header["terrain"]
        n_t = int(th["n_rows"]) * int(th["n_cols"])
        terrain = mm[lay["terrain_m"] : lay["terrain_m"] + 4 * n_t].view(np.float32).reshape(th["n_rows"], th["n_cols"])
        n_c = n * (n_az // COARSE_STRIDE)
        coarse = mm[lay["coarse_codes"] : lay["coarse_codes"] + n_c].reshape(n, n_az // COARSE_STRIDE)
        partial = mm[lay["coarse_partial"] : lay["coarse_partial"] + n].view(np.bool_)
        coarse_tau2 = mm[lay["coarse_tau2"] : lay["coarse_tau2"] + n_c].reshape(n, n_az // COARSE_STRIDE)
    except DatabaseError:
        raise
    except (ValueError, OSError, KeyError, TypeError, IndexError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatabaseError(f"{p}: truncated or corrupt database ({first})") from None
    try:
        g = header["grid"]
        grid = NodeGrid(
            g["crs_wkt"], g["x0"], g["y0"], g["dx"], g["dy"], g["n_rows"], g["n_cols"], g["dx_m"], g["dy_m"]
        )
        row0, col0 = int(th["row0"]), int(th["col0"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DatabaseError(f"{p}: corrupt database header ({type(exc).__name__}: {exc})") from None
    if grid.n_nodes != n:
        raise DatabaseError(f"{p}: grid of {grid.n_nodes} nodes but {n} skylines")
    return SkylineDatabase(str(p), header, grid, codes, f32["offset_deg"], f32["step_deg"], f32["ground_m"], dist,
                           f32["convergence_deg"], terrain, (row0, col0), coarse, partial, coarse_tau2)
