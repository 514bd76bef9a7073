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

Elevation (deg) = offset + step * code.  The step is 0.1 degree (quantisation error at most 0.05
degree) unless a node's skyline spans more than 25.4 degrees, where it grows to span/254.
Azimuth j is ``j * 360 / n_azimuths`` degrees clockwise from true north.  Range (m) =
DISTANCE_MIN_M * exp(DISTANCE_LOG_STEP * code): 5 % steps from 1 m to 300 km.  The range says how
fast the skyline moves with position (parallax), and the terrain grid lets the estimator render
exact skylines between nodes; candidate node (0, 0) is terrain node (row0, col0), same spacing.

The checksums are verified when the database is loaded: a flipped bit is a one-line error naming the
block.  The first-pass arrays are made at build time so that no estimate has to make them.

Nodes form a regular grid in a metric CRS: the DEM's own when it is a projected CRS with scale
close to 1, else a transverse Mercator centred on the search area.  Node (row, col) lies at
x = x0 + col * dx, y = y0 - row * dy; node index = row * n_cols + col.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numba
import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from appliance.atomic import atomic_output
from appliance.errors import DatabaseError, DemError, InputError
from appliance.estimator.estimate import COARSE_STRIDE, SkylineGrid
from appliance.numerics import FAST_FINITE
from appliance.terrain.dem import Dem
from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
from appliance.terrain.sweep import HorizonSweeper

MAGIC = b"VIPERDB\0"
FORMAT_VERSION = 3
DISTANCE_MIN_M = 1.0
DISTANCE_LOG_STEP = 0.05
MISSING_CODE = 255
BASE_STEP_DEG = 0.1
MAX_SPAN_DEG = 25.0
ALIGN = 64
CHECKSUM_BLOCK = 1 << 20  # bytes of the array section per CRC32
MISSING_CDEG = np.iinfo(np.int16).min


@dataclass(frozen=True)
class NodeGrid:
    """A regular grid of candidate nodes: in a metric CRS, or the lon/lat grid of a geographic DEM.

    ``dx``/``dy`` are in the CRS's units; ``dx_m``/``dy_m`` the ground spacing in metres (for a
    geographic grid, at the grid's centre latitude).
    """

    crs_wkt: str
    x0: float
    y0: float
    dx: float
    dy: float
    n_rows: int
    n_cols: int
    dx_m: float
    dy_m: float

    @property
    def n_nodes(self) -> int:
        return self.n_rows * self.n_cols

    @cached_property
    def crs(self) -> CRS:
        return CRS.from_wkt(self.crs_wkt)

    @cached_property
    def to_lonlat(self) -> Transformer:
        return Transformer.from_crs(self.crs, self.crs.geodetic_crs, always_xy=True)

    @cached_property
    def from_lonlat(self) -> Transformer:
        return Transformer.from_crs(self.crs.geodetic_crs, self.crs, always_xy=True)

    def node_xy(self, index: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        row, col = np.divmod(np.asarray(index), self.n_cols)
        return self.x0 + col * self.dx, self.y0 - row * self.dy

    def rc_to_xy(self, row: np.ndarray | float, col: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        return self.x0 + np.asarray(col) * self.dx, self.y0 - np.asarray(row) * self.dy

    def xy_to_rc(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        return (self.y0 - np.asarray(y)) / self.dy, (np.asarray(x) - self.x0) / self.dx

    def xy_to_lonlat(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        lon, lat = self.to_lonlat.transform(np.asarray(x, float), np.asarray(y, float))
        return np.asarray(lon), np.asarray(lat)

    def lonlat_to_xy(self, lon: np.ndarray | float, lat: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        x, y = self.from_lonlat.transform(np.asarray(lon, float), np.asarray(lat, float))
        return np.asarray(x), np.asarray(y)

    @property
    def transform(self) -> Affine:
        """Affine of the node grid seen as pixels centred on the nodes (for GeoTIFF output)."""
        return Affine(self.dx, 0.0, self.x0 - self.dx / 2, 0.0, -self.dy, self.y0 + self.dy / 2)


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
        from appliance.bodies import body_named

        return body_named(self.header["body"]).effective_radius_m(self.header["refraction"])


def encode_distance(distance_m: np.ndarray) -> np.ndarray:
    """uint8 log-quantised ranges (255 where NaN)."""
    d = np.asarray(distance_m, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.rint(np.log(np.maximum(d, DISTANCE_MIN_M) / DISTANCE_MIN_M) / DISTANCE_LOG_STEP)
    return np.where(np.isfinite(d), np.clip(c, 0, MISSING_CODE - 1), MISSING_CODE).astype(np.uint8)


def decode_distance(codes: np.ndarray) -> np.ndarray:
    c = np.asarray(codes)
    return np.where(c == MISSING_CODE, np.nan, DISTANCE_MIN_M * np.exp(DISTANCE_LOG_STEP * c.astype(np.float64)))


def _metric_grid_crs(dem: Dem, lon_c: float, lat_c: float) -> tuple[CRS, bool]:
    """The CRS of the node grid, and True if it is the DEM's own (no resampling).

    A geographic DEM keeps its own lon/lat grid, treated as locally metric with the spacing at the
    search area's centre latitude; a projected DEM keeps its grid where the projection's scale is
    within 0.2 % of 1; any other map is resampled onto a transverse Mercator grid.
    """
    if dem.crs.is_geographic:
        return dem.crs, True
    if dem.crs.is_projected:
        try:
            from pyproj import Proj

            factors = Proj(dem.crs).get_factors(lon_c, lat_c)
            scale = math.sqrt(factors.areal_scale)
        except Exception:  # pyproj raises plain errors for CRSs without factors
            scale = float("nan")
        unit = dem.crs.axis_info[0].unit_conversion_factor if dem.crs.axis_info else 1.0
        if abs(scale - 1.0) < 0.002 and abs(unit - 1.0) < 1e-9:
            return dem.crs, True
    return _tmerc(dem, lon_c, lat_c), False


def _tmerc(dem: Dem, lon_c: float, lat_c: float) -> CRS:
    ell = dem.crs.ellipsoid
    a = ell.semi_major_metre if ell is not None else dem.body.semi_major_m
    b = ell.semi_minor_metre if ell is not None else dem.body.semi_major_m
    proj = f"+proj=tmerc +lat_0={lat_c!r} +lon_0={lon_c!r} +k=1 +x_0=0 +y_0=0 +a={a!r} +b={b!r} +units=m"
    return CRS.from_proj4(proj + " +no_defs")


def plan_grids(
    dem: Dem,
    search_bounds: tuple[float, float, float, float] | None,
    spacing_m: float | None,
    max_range_m: float,
) -> tuple[NodeGrid, NodeGrid, tuple[int, int]]:
    """Candidate grid, terrain grid (candidates plus the horizon's reach) and the candidates' offset
    (row, col) inside the terrain grid."""
    west, south, east, north = dem.bounds_lonlat()
    if search_bounds is None:
        search_bounds = (west, south, east, north)
    sw, ss, se, sn = search_bounds
    if not (sw < se and ss < sn):
        raise InputError(f"search bounds {search_bounds}: expected W,S,E,N with W < E and S < N")
    if se <= west or sw >= east or sn <= south or ss >= north:
        raise InputError(
            f"search bounds {search_bounds} lie outside the DEM {dem.source} "
            f"({west:.5f}, {south:.5f}, {east:.5f}, {north:.5f})"
        )
    sw, ss, se, sn = max(sw, west), max(ss, south), min(se, east), min(sn, north)
    if se - sw > 30.0 or sn - ss > 30.0:
        raise InputError(
            f"search area {se - sw:.1f} x {sn - ss:.1f} degrees is too large for one metric grid: "
            "give --search-bounds W,S,E,N spanning at most 30 degrees"
        )
    lon_c, lat_c = (sw + se) / 2.0, (ss + sn) / 2.0
    crs, native = _metric_grid_crs(dem, lon_c, lat_c)
    to_grid = Transformer.from_crs(dem.crs.geodetic_crs, crs, always_xy=True)
    if native and spacing_m is None:
        dx, dy = abs(dem.transform.a), abs(dem.transform.e)
        ox, oy = dem.pixel_to_xy(np.array(0.0), np.array(0.0))
        origin = (float(ox), float(oy))
        if crs.is_geographic:
            geod = dem.geod
            _, _, dx_m = geod.inv(lon_c, lat_c, lon_c + dx, lat_c)
            _, _, dy_m = geod.inv(lon_c, lat_c - dy / 2, lon_c, lat_c + dy / 2)
        else:
            dx_m, dy_m = dx, dy
    else:
        if crs.is_geographic:
            crs, native = _tmerc(dem, lon_c, lat_c), False
            to_grid = Transformer.from_crs(dem.crs.geodetic_crs, crs, always_xy=True)
        rx, ry = dem.resolution_m()
        dx, dy = (rx, ry) if spacing_m is None else (float(spacing_m), float(spacing_m))
        origin = (0.0, 0.0)
        dx_m, dy_m = dx, dy
    reach = max_range_m if not crs.is_geographic else max_range_m / min(dx_m / dx, dy_m / dy)
    if not (dx > 0 and dy > 0):
        raise InputError(f"grid spacing must be positive, got {dx} x {dy} m")

    def box(lo_lon: float, lo_lat: float, hi_lon: float, hi_lat: float) -> tuple[float, ...]:
        t = np.linspace(0, 1, 41)
        lons = np.concatenate([lo_lon + (hi_lon - lo_lon) * t, np.full_like(t, hi_lon),
                               lo_lon + (hi_lon - lo_lon) * t, np.full_like(t, lo_lon)])
        lats = np.concatenate([np.full_like(t, lo_lat), lo_lat + (hi_lat - lo_lat) * t,
                               np.full_like(t, hi_lat), lo_lat + (hi_lat - lo_lat) * t])
        x, y = to_grid.transform(lons, lats)
        return float(np.min(x)), float(np.min(y)), float(np.max(x)), float(np.max(y))

    cx0, cy0, cx1, cy1 = box(sw, ss, se, sn)
    tx0, ty0, tx1, ty1 = box(west, south, east, north)
    if not np.all(np.isfinite([tx0, ty0, tx1, ty1])):
        tx0, ty0, tx1, ty1 = -np.inf, -np.inf, np.inf, np.inf
    # the terrain grid holds the candidates and the horizon's reach around them, within the map
    tx0, ty0 = min(max(tx0, cx0 - reach), cx0), min(max(ty0, cy0 - reach), cy0)
    tx1, ty1 = max(min(tx1, cx1 + reach), cx1), max(min(ty1, cy1 + reach), cy1)

    def cols(lo: float, hi: float, o: float, d: float) -> tuple[int, int]:
        return math.ceil((lo - o) / d - 1e-9), math.floor((hi - o) / d + 1e-9)

    c0, c1 = cols(cx0, cx1, origin[0], dx)
    r0, r1 = cols(cy0, cy1, origin[1], dy)
    tc0, tc1 = cols(tx0, tx1, origin[0], dx)
    tr0, tr1 = cols(ty0, ty1, origin[1], dy)
    if c1 < c0 or r1 < r0:
        raise InputError(f"search bounds {search_bounds} contain no grid node at {dx:.1f} x {dy:.1f} m")
    wkt = crs.to_wkt()
    cand = NodeGrid(wkt, origin[0] + c0 * dx, origin[1] + r1 * dy, dx, dy, r1 - r0 + 1, c1 - c0 + 1, dx_m, dy_m)
    terr = NodeGrid(
        wkt, origin[0] + tc0 * dx, origin[1] + tr1 * dy, dx, dy, tr1 - tr0 + 1, tc1 - tc0 + 1, dx_m, dy_m
    )
    return cand, terr, (tr1 - r1, c0 - tc0)


def _dem_pixel_origin(dem: Dem, grid: NodeGrid) -> tuple[int, int] | None:
    """(row, col) of the DEM pixel at the grid's node (0, 0) when the grid is a window of the DEM's
    own pixels (same CRS, spacing and orientation), else None."""
    if grid.crs == dem.crs and abs(grid.dx - abs(dem.transform.a)) < 1e-12 and dem.transform.b == 0:
        col0, row0 = dem.xy_to_pixel(np.array(grid.x0), np.array(grid.y0))
        r, c = int(round(float(row0))), int(round(float(col0)))
        if abs(r - row0) < 1e-6 and abs(c - col0) < 1e-6:
            return r, c
    return None


def lattice_of(dem: Dem, grid: NodeGrid) -> tuple[tuple[int, int], tuple[int, int]]:
    """Where ``grid`` lies in the lattice its nodes belong to: (row, col) of its node (0, 0) and
    the lattice's shape.  A grid at the DEM's own spacing is a window of the DEM's pixels; any other
    is its own lattice."""
    origin = _dem_pixel_origin(dem, grid)
    if origin is not None:
        return origin, dem.shape
    return (0, 0), (grid.n_rows, grid.n_cols)


def run_threads(fn: Callable[[int], None], items: Iterable[int], workers: int | None = None) -> Iterator[int]:
    """Call ``fn`` on every item from a pool of threads (default: one per core); yields each item as
    it completes.  ``fn`` is expected to spend its time in kernels that release the GIL."""
    n = workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=max(int(n), 1)) as pool:
        futures = {pool.submit(fn, i): i for i in items}
        for fut in as_completed(futures):
            fut.result()
            yield futures[fut]


def terrain_on_grid(dem: Dem, grid: NodeGrid) -> np.ndarray:
    """DEM heights (m, NaN = nodata) at the grid's nodes, bilinear."""
    origin = _dem_pixel_origin(dem, grid)
    if origin is not None and min(origin) >= 0:
        r, c = origin
        sub = dem.elevation_m[r : r + grid.n_rows, c : c + grid.n_cols]
        if sub.shape == (grid.n_rows, grid.n_cols):
            return np.array(sub, dtype=np.float64)
    to_dem = Transformer.from_crs(grid.crs, dem.crs, always_xy=True)
    out = np.empty((grid.n_rows, grid.n_cols))
    cols = grid.x0 + np.arange(grid.n_cols) * grid.dx
    for r in range(grid.n_rows):
        x, y = to_dem.transform(cols, np.full(grid.n_cols, grid.y0 - r * grid.dy))
        out[r] = dem.sample(np.asarray(x), np.asarray(y))
    return out


def grid_convergence_deg(grid: NodeGrid, geod_crs: CRS) -> np.ndarray:
    """True azimuth (deg) of grid north at every node, interpolated from a coarse lattice."""
    from pyproj import Geod
    from scipy.interpolate import RegularGridInterpolator

    ell = geod_crs.ellipsoid
    geod = Geod(a=ell.semi_major_metre, b=ell.semi_minor_metre) if ell is not None else Geod(ellps="WGS84")
    rs = np.linspace(0, grid.n_rows - 1, min(grid.n_rows, 24))
    cs = np.linspace(0, grid.n_cols - 1, min(grid.n_cols, 24))
    rr, cc = np.meshgrid(rs, cs, indexing="ij")
    x, y = grid.rc_to_xy(rr.ravel(), cc.ravel())
    lon0, lat0 = grid.xy_to_lonlat(x, y)
    lon1, lat1 = grid.xy_to_lonlat(x, y + grid.dy * min(1.0, 10.0 / grid.dy_m))
    az, _, _ = geod.inv(lon0, lat0, lon1, lat1)
    az = ((np.asarray(az) + 180.0) % 360.0) - 180.0
    table = az.reshape(rr.shape)
    if len(rs) < 2 or len(cs) < 2:
        return np.full((grid.n_rows, grid.n_cols), float(np.mean(table)))
    interp = RegularGridInterpolator((rs, cs), table)
    R, C = np.meshgrid(np.arange(grid.n_rows), np.arange(grid.n_cols), indexing="ij")
    return interp(np.stack([R.ravel(), C.ravel()], axis=1)).reshape(grid.n_rows, grid.n_cols)


@numba.njit(cache=True, inline="always")
def _atan(x: float) -> float:
    """Arctangent to 1e-5 rad (0.0006 deg), branch-light so that loops over it vectorise."""
    ax = abs(x)
    inv = ax > 1.0
    t = 1.0 / ax if inv else ax
    t2 = t * t
    # minimax polynomial for atan(t), 0 <= t <= 1
    p = t * (0.99997726 + t2 * (-0.33262347 + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332
                                                                                         + t2 * -0.01172120)))))
    r = 0.5 * math.pi - p if inv else p
    return -r if x < 0 else r


@numba.njit(cache=True, nogil=True, fastmath=FAST_FINITE)
def _store_centidegrees(tan: np.ndarray, far: np.ndarray, out: np.ndarray, dist: np.ndarray) -> None:
    """One azimuth of every node (row-major over the window): out[node] = elevation in hundredths
    of a degree (int16; MISSING_CDEG where NaN); dist[node] = the horizon's log-quantised range."""
    rows, cols = tan.shape
    scale = 100.0 * 180.0 / math.pi
    inv_log = 1.0 / DISTANCE_LOG_STEP
    for r in range(rows):
        line = tan[r]
        fline = far[r]
        base = r * cols
        for c in range(cols):
            t = line[c]
            if t != t:
                out[base + c] = MISSING_CDEG
                dist[base + c] = MISSING_CODE
            else:
                out[base + c] = np.int16(round(_atan(t) * scale))
                f = fline[c]
                if f != f:
                    dist[base + c] = MISSING_CODE
                else:
                    code = round(math.log(max(f, DISTANCE_MIN_M) / DISTANCE_MIN_M) * inv_log)
                    dist[base + c] = min(max(code, 0), MISSING_CODE - 1)


@numba.njit(cache=True)
def _quantize_row(row: np.ndarray, codes: np.ndarray, offs: np.ndarray, steps: np.ndarray, i: int) -> None:
    """Offset, step and uint8 codes of one skyline (deg, NaN = missing) into row i."""
    lo = np.inf
    hi = -np.inf
    for e in row:
        if not math.isnan(e):
            lo = min(lo, e)
            hi = max(hi, e)
    if lo > hi:
        offs[i] = np.nan
        steps[i] = BASE_STEP_DEG
        codes[i, :] = MISSING_CODE
        return
    o = np.float32(lo)
    st = np.float32(max(BASE_STEP_DEG, (hi - lo) / (MISSING_CODE - 1)))
    offs[i] = o
    steps[i] = st
    for j in range(row.size):
        e = row[j]
        if math.isnan(e):
            codes[i, j] = MISSING_CODE
        else:
            codes[i, j] = min(max(round((e - o) / st), 0), MISSING_CODE - 1)


@numba.njit(cache=True, nogil=True)
def _turn_and_quantize(cdeg: np.ndarray, dgrid: np.ndarray, shift: np.ndarray, codes: np.ndarray,
                       dist: np.ndarray, offs: np.ndarray, steps: np.ndarray, lo: int, hi: int) -> None:
    """Nodes lo..hi-1: resample each node's skyline (cdeg[azimuth, node], azimuth-major) from grid
    to true azimuths (true = grid + shift steps, linear on the circle; ranges from the nearer
    azimuth), then quantise it into codes[node]."""
    n_az = cdeg.shape[0]
    block = 256
    src = np.empty((block, n_az), dtype=np.int16)
    dsrc = np.empty((block, n_az), dtype=np.uint8)
    row = np.empty(n_az)
    for b0 in range(lo, hi, block):
        b1 = min(b0 + block, hi)
        for j in range(n_az):  # a block of nodes gathered azimuth by azimuth: contiguous reads
            for i in range(b0, b1):
                src[i - b0, j] = cdeg[j, i]
                dsrc[i - b0, j] = dgrid[j, i]
        for i in range(b0, b1):
            s = src[i - b0]
            ds = dsrc[i - b0]
            sh = shift[i]
            whole = int(math.floor(sh))
            w = sh - whole
            if w == 0.0 and whole == 0:
                for j in range(n_az):
                    c = s[j]
                    row[j] = np.nan if c == MISSING_CDEG else c / 100.0
                    dist[i, j] = ds[j]
            else:
                # value at grid azimuth j - shift: between j - whole - 1 (weight w) and j - whole (1 - w)
                for j in range(n_az):
                    i1 = (j - whole) % n_az
                    i0 = (i1 - 1) % n_az
                    a = s[i0]
                    bb = s[i1]
                    if a == MISSING_CDEG or bb == MISSING_CDEG:
                        row[j] = np.nan
                        dist[i, j] = MISSING_CODE
                    else:
                        row[j] = (a * w + bb * (1.0 - w)) / 100.0
                        dist[i, j] = ds[i0] if w >= 0.5 else ds[i1]
            _quantize_row(row, codes, offs, steps, i)


@numba.njit(cache=True, parallel=True)
def _quantize_rows(elev: np.ndarray, codes: np.ndarray, offs: np.ndarray, steps: np.ndarray) -> None:
    for i in numba.prange(elev.shape[0]):
        _quantize_row(elev[i], codes, offs, steps, i)


def quantize(elev_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-node offset and step, and uint8 codes, of skylines ``elev_deg[n, n_az]`` (NaN = missing).

    The step is 0.1 degree (error at most 0.05) unless the skyline spans more than 25.4 degrees."""
    e = np.ascontiguousarray(elev_deg, dtype=np.float64)
    codes = np.empty(e.shape, dtype=np.uint8)
    offs = np.empty(e.shape[0], dtype=np.float32)
    steps = np.empty(e.shape[0], dtype=np.float32)
    _quantize_rows(e, codes, offs, steps)
    return codes, offs, steps


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
    single-threaded kernels that release the GIL: a busy machine slows the build in proportion,
    with no threads spinning at barriers."""
    if not 8 <= n_azimuths <= 3600:
        raise InputError(f"azimuth count {n_azimuths} outside [8, 3600]")
    if not 0.0 <= height_m < 1000.0:
        raise InputError(f"camera height {height_m} m outside [0, 1000)")
    cand, terr, (ro, co) = plan_grids(dem, search_bounds, spacing_m, max_range_m)
    Z = terrain_on_grid(dem, terr)
    if not np.isfinite(Z[ro : ro + cand.n_rows, co : co + cand.n_cols]).any():
        raise DemError(f"{dem.source}: every candidate node inside the search bounds is nodata")
    r_eff = dem.body.effective_radius_m(refraction)
    gamma = grid_convergence_deg(cand, dem.crs.geodetic_crs or dem.crs)
    step_az = 360.0 / n_azimuths
    n = cand.n_nodes
    cdeg = np.empty((n_azimuths, n), dtype=np.int16)  # centidegrees at grid azimuths, one row per azimuth
    dgrid = np.empty((n_azimuths, n), dtype=np.uint8)  # ranges at grid azimuths
    origin, shape = lattice_of(dem, terr)
    sweeper = HorizonSweeper(Z, terr.dx_m, terr.dy_m, height_m, r_eff, (ro, co, cand.n_rows, cand.n_cols),
                             origin, shape)

    def one_azimuth(j: int) -> None:
        tan, far = sweeper.horizons(j * step_az)
        _store_centidegrees(tan, far, cdeg[j], dgrid[j])

    done = 0
    for _ in run_threads(one_azimuth, range(n_azimuths), workers):
        done += 1
        if progress is not None:
            progress(done, n_azimuths, "skylines")

    header = {
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
        "search_bounds": list(search_bounds) if search_bounds else list(dem.bounds_lonlat()),
        "distance_code": {"min_m": DISTANCE_MIN_M, "log_step": DISTANCE_LOG_STEP},
        "terrain": {"n_rows": terr.n_rows, "n_cols": terr.n_cols, "row0": ro, "col0": co},
    }
    ground = Z[ro : ro + cand.n_rows, co : co + cand.n_cols].ravel().astype(np.float32)
    _write(out_path, header, cdeg, dgrid, gamma.ravel(), step_az, ground, Z.astype(np.float32), cand, workers)
    return header


def _write(out_path: str | Path, header: dict, cdeg: np.ndarray, dgrid: np.ndarray, gamma_deg: np.ndarray,
           step_az: float, ground: np.ndarray, terrain: np.ndarray, cand: NodeGrid, workers: int | None) -> None:
    n_az, n = cdeg.shape
    n_coarse = n_az // COARSE_STRIDE
    layout = {}
    pos = 0
    sizes = (("codes", n * n_az), ("distance", n * n_az), ("offset_deg", 4 * n), ("step_deg", 4 * n),
             ("ground_m", 4 * n), ("convergence_deg", 4 * n), ("terrain_m", 4 * terrain.size),
             ("coarse_codes", n * n_coarse), ("coarse_partial", n), ("coarse_tau2", n * n_coarse))
    for name, nbytes in sizes:
        layout[name] = pos
        pos += -(-nbytes // ALIGN) * ALIGN
    n_blocks = -(-pos // CHECKSUM_BLOCK)
    checksum = {"algorithm": "crc32", "block_bytes": CHECKSUM_BLOCK, "offset": pos, "blocks": n_blocks}
    header = dict(header, arrays=layout, n_nodes=n, checksum=checksum)
    raw = json.dumps(header).encode()
    hlen = -(-(len(raw) + 12) // ALIGN) * ALIGN - 12
    data_start = 12 + hlen
    head = MAGIC + np.uint32(hlen).tobytes() + raw.ljust(hlen, b" ")
    # allocated in full before the memory map touches it: a full disk is a one-line error, not SIGBUS
    with atomic_output(out_path, preallocate=data_start + pos + 4 * (1 + n_blocks)) as tmp:
        with tmp.open("r+b") as fh:
            fh.write(head)
        mm = np.memmap(tmp, mode="r+", dtype=np.uint8, offset=data_start, shape=(pos,))
        codes = mm[layout["codes"] : layout["codes"] + n * n_az].reshape(n, n_az)
        dist = mm[layout["distance"] : layout["distance"] + n * n_az].reshape(n, n_az)
        offs = np.empty(n, np.float32)
        steps = np.empty(n, np.float32)
        shift = np.asarray(gamma_deg, dtype=np.float64) / step_az
        chunk = 4096

        def quantize_chunk(lo: int) -> None:
            _turn_and_quantize(cdeg, dgrid, shift, codes, dist, offs, steps, lo, min(lo + chunk, n))

        for _ in run_threads(quantize_chunk, range(0, n, chunk), workers):
            pass
        gam = np.asarray(gamma_deg, dtype=np.float32)
        for name, arr in (("offset_deg", offs), ("step_deg", steps), ("ground_m", ground), ("convergence_deg", gam),
                          ("terrain_m", np.ascontiguousarray(terrain, dtype=np.float32).ravel())):
            mm[layout[name] : layout[name] + 4 * arr.size] = arr.view(np.uint8)
        # the estimator's first pass, exactly as it would make it from the arrays above
        grid = SkylineGrid(codes, offs, steps, cand.n_rows, cand.n_cols, cand.dx_m, cand.dy_m, dist, ground,
                           distance_min_m=DISTANCE_MIN_M, distance_log_step=DISTANCE_LOG_STEP)
        coarse, partial = grid.coarse
        for name, arr in (("coarse_codes", coarse), ("coarse_partial", partial.view(np.uint8)),
                          ("coarse_tau2", grid.coarse_tau2(0.0))):
            mm[layout[name] : layout[name] + arr.size] = np.ascontiguousarray(arr).ravel()
        del grid, coarse, partial
        mm.flush()
        crcs = [zlib.crc32(head)] + block_checksums(mm)
        with tmp.open("r+b") as fh:
            fh.seek(data_start + pos)
            fh.write(np.asarray(crcs, dtype="<u4").tobytes())


def block_checksums(body: np.ndarray) -> list[int]:
    """CRC32 of each CHECKSUM_BLOCK bytes of a database's array section."""
    return [zlib.crc32(body[i : i + CHECKSUM_BLOCK].data) for i in range(0, body.size, CHECKSUM_BLOCK)]


def verify_checksums(p: Path, header: dict, head: bytes, body: np.ndarray) -> None:
    """Compare the header and every block of ``body`` (the array section, checksum table included)
    with the table written at build; a mismatch is a DatabaseError naming the block."""
    spec = header.get("checksum")
    if spec is None:
        return  # a version 2 file written before the checksums
    try:
        size, offset, n_blocks = int(spec["block_bytes"]), int(spec["offset"]), int(spec["blocks"])
        if spec.get("algorithm") != "crc32" or size != CHECKSUM_BLOCK or n_blocks != -(-offset // size):
            raise ValueError(f"checksum entry {spec}")
    except (KeyError, TypeError, ValueError) as exc:
        raise DatabaseError(f"{p}: corrupt database header ({exc})") from None
    if body.size < offset + 4 * (1 + n_blocks):
        raise DatabaseError(f"{p}: truncated database: {body.size} bytes of arrays and checksums, expected "
                            f"{offset + 4 * (1 + n_blocks)}")
    table = body[offset : offset + 4 * (1 + n_blocks)].view("<u4")
    if zlib.crc32(head) != int(table[0]):
        raise DatabaseError(f"{p}: the header fails its CRC32 check: the file is damaged; rebuild it")
    arrays = body[:offset]
    # zlib releases the GIL on large buffers: the blocks are checked on every core
    with ThreadPoolExecutor(max_workers=max(len(os.sched_getaffinity(0)), 1)) as pool:
        crcs = list(pool.map(lambda lo: zlib.crc32(arrays[lo : lo + size].data), range(0, offset, size)))
    for k in range(n_blocks):
        lo = k * size
        if crcs[k] != int(table[1 + k]):
            hi = min(lo + size, offset)
            raise DatabaseError(
                f"{p}: block {k} of {n_blocks} (array bytes {lo}-{hi - 1}) fails its CRC32 check: the file "
                "is damaged; rebuild it"
            )


def load_database(path: str | Path, dem: Dem | None = None) -> SkylineDatabase:
    """Memory-map a database; refuses a foreign format or version, or one from another DEM."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            magic = fh.read(8)
            if magic != MAGIC:
                raise DatabaseError(f"{p}: not a Viper skyline database")
            hlen_raw = fh.read(4)
            hlen = int(np.frombuffer(hlen_raw, np.uint32)[0])
            if hlen > 1 << 24:
                raise ValueError(f"header length {hlen}")
            raw = fh.read(hlen)
            header = json.loads(raw.decode())
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
    except FileNotFoundError:
        raise DatabaseError(f"{p}: database not found") from None
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
        mm = np.memmap(p, mode="r", dtype=np.uint8, offset=start)
        verify_checksums(p, header, magic + hlen_raw + raw, mm)
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
