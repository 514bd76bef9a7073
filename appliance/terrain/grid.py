"""Grids of candidate nodes: where they lie, in which CRS, and the terrain under them.

Nodes form a regular grid in a metric CRS: the DEM's own when it is a projected CRS with scale
close to 1, else a transverse Mercator centred on the search area (a geographic DEM keeps its own
lon/lat grid, with metric spacing taken at the search area's centre).  Node (row, col) lies at
x = x0 + col * dx, y = y0 - row * dy; node index = row * n_cols + col.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from appliance.errors import InputError
from appliance.terrain.dem import Dem


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
    proj = f"+proj=tmerc +lat_0={float(lat_c)!r} +lon_0={float(lon_c)!r} +k=1 +x_0=0 +y_0=0 +a={a!r} +b={b!r} +units=m"
    return CRS.from_proj4(proj + " +no_defs")


Bounds = tuple[float, float, float, float]


def lon_overlap(w1: float, e1: float, w2: float, e2: float) -> bool:
    """Whether two longitude intervals [w1, e1] and [w2, e2] (degrees) meet, modulo 360: a box given
    in -180..180 meets one given in 0..360, or one across the 0/360 seam."""
    if e1 - w1 >= 360.0 or e2 - w2 >= 360.0:
        return True
    return any(w1 <= e2 + k * 360.0 and w2 + k * 360.0 <= e1 for k in (-2, -1, 0, 1, 2))


def plan_grids(
    dem: Dem,
    search_bounds: Bounds | None,
    spacing_m: float | None,
    max_range_m: float,
) -> tuple[NodeGrid, NodeGrid, tuple[int, int]]:
    """Candidate grid, terrain grid (candidates plus the horizon's reach) and the candidates' offset
    (row, col) inside the terrain grid."""
    sw, ss, se, sn = _search_area(dem, search_bounds)
    lon_c, lat_c = (sw + se) / 2.0, (ss + sn) / 2.0
    lattice = _lattice(dem, lon_c, lat_c, spacing_m)
    reach = max_range_m if not lattice.crs.is_geographic else max_range_m / min(
        lattice.dx_m / lattice.dx, lattice.dy_m / lattice.dy)
    to_grid = Transformer.from_crs(dem.crs.geodetic_crs, lattice.crs, always_xy=True)
    cx0, cy0, cx1, cy1 = _box_in_grid(to_grid, (sw, ss, se, sn))
    tx0, ty0, tx1, ty1 = _box_in_grid(to_grid, dem.bounds_lonlat())
    # a map that wraps around has no edge in longitude: its lon/lat box says nothing of where its
    # terrain ends in a grid centred on the search area (beyond its latitudes it samples as nodata)
    if dem.wraps_around or not np.all(np.isfinite([tx0, ty0, tx1, ty1])):
        tx0, ty0, tx1, ty1 = -np.inf, -np.inf, np.inf, np.inf
    # the terrain grid holds the candidates and the horizon's reach around them, within the map
    tx0, ty0 = min(max(tx0, cx0 - reach), cx0), min(max(ty0, cy0 - reach), cy0)
    tx1, ty1 = max(min(tx1, cx1 + reach), cx1), max(min(ty1, cy1 + reach), cy1)
    c0, c1 = lattice.indices(cx0, cx1, 0)
    r0, r1 = lattice.indices(cy0, cy1, 1)
    tc0, tc1 = lattice.indices(tx0, tx1, 0)
    tr0, tr1 = lattice.indices(ty0, ty1, 1)
    if c1 < c0 or r1 < r0:
        raise InputError(f"search bounds {search_bounds} contain no grid node at {lattice.dx:.1f} x "
                         f"{lattice.dy:.1f} m")
    cand = lattice.window(r0, r1, c0, c1)
    terr = lattice.window(tr0, tr1, tc0, tc1)
    return cand, terr, (tr1 - r1, c0 - tc0)


def _search_area(dem: Dem, search_bounds: Bounds | None) -> Bounds:
    """The search bounds (W, S, E, N degrees; default the whole map), checked and clipped to the map."""
    west, south, east, north = dem.bounds_lonlat()
    if search_bounds is None:
        search_bounds = (west, south, east, north)
    sw, ss, se, sn = search_bounds
    if not (sw < se and ss < sn):
        raise InputError(f"search bounds {search_bounds}: expected W,S,E,N with W < E and S < N")
    # longitudes given in another turn (-180..180 for a map in 0..360, or across the antimeridian)
    turn = next((k * 360.0 for k in (0, -1, 1, -2, 2) if sw + k * 360.0 < east and se + k * 360.0 > west), 0.0)
    sw, se = sw + turn, se + turn
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
    return sw, ss, se, sn


@dataclass(frozen=True)
class _Lattice:
    """The infinite lattice the grids' nodes lie on: node (i, j) at (x0 + j * dx, y0 + i * dy)."""

    crs: CRS
    x0: float
    y0: float
    dx: float
    dy: float
    dx_m: float
    dy_m: float

    def indices(self, lo: float, hi: float, axis: int) -> tuple[int, int]:
        """First and last lattice index with its coordinate inside [lo, hi] (x for axis 0, y for 1)."""
        o, d = (self.x0, self.dx) if axis == 0 else (self.y0, self.dy)
        return math.ceil((lo - o) / d - 1e-9), math.floor((hi - o) / d + 1e-9)

    def window(self, r0: int, r1: int, c0: int, c1: int) -> NodeGrid:
        """The grid of lattice nodes x index c0..c1, y index r0..r1 (its first row is the northmost)."""
        return NodeGrid(self.crs.to_wkt(), self.x0 + c0 * self.dx, self.y0 + r1 * self.dy, self.dx, self.dy,
                        r1 - r0 + 1, c1 - c0 + 1, self.dx_m, self.dy_m)


def _lattice(dem: Dem, lon_c: float, lat_c: float, spacing_m: float | None) -> _Lattice:
    """The lattice of a search area centred at (lon_c, lat_c): the DEM's own pixels when its CRS is
    metric enough and no spacing is asked for, else a transverse Mercator at ``spacing_m`` (default:
    the DEM's resolution)."""
    crs, native = _metric_grid_crs(dem, lon_c, lat_c)
    if native and spacing_m is None:
        dx, dy = abs(dem.transform.a), abs(dem.transform.e)
        ox, oy = dem.pixel_to_xy(np.array(0.0), np.array(0.0))
        if crs.is_geographic:
            geod = dem.geod
            _, _, dx_m = geod.inv(lon_c, lat_c, lon_c + dx, lat_c)
            _, _, dy_m = geod.inv(lon_c, lat_c - dy / 2, lon_c, lat_c + dy / 2)
        else:
            dx_m, dy_m = dx, dy
        lattice = _Lattice(crs, float(ox), float(oy), dx, dy, dx_m, dy_m)
    else:
        if crs.is_geographic:
            crs = _tmerc(dem, lon_c, lat_c)
        rx, ry = dem.resolution_m()
        dx, dy = (rx, ry) if spacing_m is None else (float(spacing_m), float(spacing_m))
        lattice = _Lattice(crs, 0.0, 0.0, dx, dy, dx, dy)
    if not (lattice.dx > 0 and lattice.dy > 0):
        raise InputError(f"grid spacing must be positive, got {lattice.dx} x {lattice.dy} m")
    return lattice


def _box_in_grid(to_grid: Transformer, bounds: Bounds) -> Bounds:
    """Bounding box in the grid's CRS of a lon/lat box, from 41 points along each of its edges."""
    lo_lon, lo_lat, hi_lon, hi_lat = bounds
    t = np.linspace(0, 1, 41)
    lons = np.concatenate([lo_lon + (hi_lon - lo_lon) * t, np.full_like(t, hi_lon),
                           lo_lon + (hi_lon - lo_lon) * t, np.full_like(t, lo_lon)])
    lats = np.concatenate([np.full_like(t, lo_lat), lo_lat + (hi_lat - lo_lat) * t,
                           np.full_like(t, hi_lat), lo_lat + (hi_lat - lo_lat) * t])
    x, y = to_grid.transform(lons, lats)
    return float(np.min(x)), float(np.min(y)), float(np.max(x)), float(np.max(y))


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
