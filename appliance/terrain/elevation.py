"""A gridded elevation model (:class:`Dem`): heights on a grid of pixels, their georeferencing, and
bilinear heights at any point of the map's CRS or of lon/lat, across the 0/360 seam and the poles of
a whole body's map.  :mod:`appliance.terrain.dem` reads every map file into one.

Heights are metres above the body's reference (geoid on Earth, the 1737.4 km sphere on the Moon);
nodata is NaN, never 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from affine import Affine
from pyproj import CRS, Geod, Transformer

from appliance.bodies import Body


@dataclass(frozen=True, eq=False)
class Dem:
    """A gridded elevation model.

    ``elevation_m[row, col]`` is the height (m, NaN = nodata) at the centre of pixel (row, col);
    ``transform`` maps (col, row) pixel *edges* to CRS coordinates, as in rasterio.
    """

    elevation_m: np.ndarray
    transform: Affine
    crs: CRS
    body: Body
    source: str
    sha256: str
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.elevation_m.shape[0]), int(self.elevation_m.shape[1]))

    @property
    def is_geographic(self) -> bool:
        return bool(self.crs.is_geographic)

    @cached_property
    def _to_lonlat(self) -> Transformer:
        return Transformer.from_crs(self.crs, self.crs.geodetic_crs, always_xy=True)

    @cached_property
    def _from_lonlat(self) -> Transformer:
        return Transformer.from_crs(self.crs.geodetic_crs, self.crs, always_xy=True)

    @cached_property
    def geod(self) -> Geod:
        ell = self.crs.ellipsoid
        if ell is None:  # pragma: no cover - every CRS we accept has one
            return Geod(a=self.body.semi_major_m, f=0.0)
        return Geod(a=ell.semi_major_metre, b=ell.semi_minor_metre)

    def xy_to_lonlat(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        lon, lat = self._to_lonlat.transform(np.asarray(x, float), np.asarray(y, float))
        return np.asarray(lon), np.asarray(lat)

    def lonlat_to_xy(self, lon: np.ndarray | float, lat: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        x, y = self._from_lonlat.transform(np.asarray(lon, float), np.asarray(lat, float))
        return np.asarray(x), np.asarray(y)

    def xy_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (col, row) of pixel centres: (0, 0) is the centre of the first pixel."""
        col, row = affine_apply(~self.transform, np.asarray(x, float), np.asarray(y, float))
        return np.asarray(col) - 0.5, np.asarray(row) - 0.5

    def pixel_to_xy(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = affine_apply(self.transform, np.asarray(col, float) + 0.5, np.asarray(row, float) + 0.5)
        return np.asarray(x), np.asarray(y)

    @cached_property
    def wraps_around(self) -> bool:
        """True for a global map whose columns close the full 360 degrees of longitude."""
        rows, cols = self.shape
        xs, ys = affine_apply(self.transform, np.array([0.5, 1.5]), np.array([rows / 2, rows / 2]))
        lon, _ = self.xy_to_lonlat(xs, ys)
        step = (float(lon[1] - lon[0]) + 180.0) % 360.0 - 180.0
        return abs(abs(step) * cols - 360.0) < 0.5 * abs(step)

    @cached_property
    def _poles(self) -> tuple[bool, bool]:
        """Whether the top and the bottom edge of a map that wraps around are the poles (a whole
        body's map); a map with an odd column count cannot pair a column with its opposite one."""
        rows, cols = self.shape
        if not self.wraps_around or cols % 2:
            return False, False
        xs, ys = affine_apply(self.transform, np.array([cols / 2, cols / 2]), np.array([0.0, float(rows)]))
        _, lat = self.xy_to_lonlat(xs, ys)
        tol = 0.01 * 180.0 / rows  # a hundredth of a pixel: map labels round their pixel size
        return bool(abs(abs(float(lat[0])) - 90.0) < tol), bool(abs(abs(float(lat[1])) - 90.0) < tol)

    @property
    def whole_body(self) -> bool:
        """True for a map of the whole body: it wraps around and reaches both poles."""
        return all(self._poles)

    @cached_property
    def _wrapped(self) -> np.ndarray:
        """The heights with the first column repeated after the last; for a whole body's map, also a
        row beyond each pole: the edge row across the pole, i.e. shifted by 180 degrees of longitude,
        so that bilinear samples between the last row of pixel centres and the pole exist."""
        z = self.elevation_m
        top, bottom = self._poles
        half = self.shape[1] // 2
        parts = ([np.roll(z[:1], -half, axis=1)] if top else []) + [z] + (
            [np.roll(z[-1:], -half, axis=1)] if bottom else [])
        z = np.vstack(parts) if len(parts) > 1 else z
        return np.hstack([z, z[:, :1]])

    @cached_property
    def _lon_period(self) -> float:
        """A full turn of longitude in the units of a lon/lat map's x axis (360 for degrees); 0 for
        a projected map, whose x does not wrap."""
        if not self.is_geographic or not self.crs.axis_info:
            return 0.0
        radians_per_unit = float(self.crs.axis_info[0].unit_conversion_factor)
        return 2.0 * np.pi / radians_per_unit if radians_per_unit > 0 else 0.0

    def wrap_x(self, x: np.ndarray) -> np.ndarray:
        """On a lon/lat map, longitudes moved by whole turns to the turn that starts at the map's
        west edge, so that -179.99, 180.01 and 540.01 all land on a map spanning 179.98..180.03 (or
        0..360, or -180..180); x unchanged on a projected map."""
        x = np.asarray(x, dtype=float)
        period = self._lon_period
        if not period:
            return x
        west = self._west_x
        return west + np.mod(x - west, period)

    @cached_property
    def _west_x(self) -> float:
        return self.bounds_xy()[0]

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height (m) at CRS coordinates; NaN off the map or next to nodata.  A map that
        wraps around is read across its 0/360 seam, and a whole body's map across its poles; a
        lon/lat map takes a longitude in any turn (-180..180 or 0..360 alike)."""
        col, row = self.xy_to_pixel(self.wrap_x(x), y)
        if self.wraps_around:
            return bilinear(self._wrapped, np.mod(col, self.shape[1]), row + (1.0 if self._poles[0] else 0.0))
        return bilinear(self.elevation_m, col, row)

    def sample_lonlat(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        x, y = self.lonlat_to_xy(lon, lat)
        return self.sample(x, y)

    def bounds_xy(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) of the pixel edges in the DEM's CRS."""
        rows, cols = self.shape
        xs, ys = affine_apply(self.transform, np.array([0, cols, 0, cols]), np.array([0, 0, rows, rows]))
        return float(np.min(xs)), float(np.min(ys)), float(np.max(xs)), float(np.max(ys))

    def bounds_lonlat(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the map, densified along its edges.  The edges are
        followed around the map, so that a map across the antimeridian keeps one turn of longitude
        (179.98..180.03, not -180..180), whatever range its CRS gives longitudes in."""
        rows, cols = self.shape
        t = np.linspace(0.0, 1.0, 41)
        back = t[::-1]
        cs = np.concatenate([t * cols, np.full_like(t, cols), back * cols, np.zeros_like(t)])
        rs = np.concatenate([np.zeros_like(t), t * rows, np.full_like(t, rows), back * rows])
        x, y = affine_apply(self.transform, cs, rs)
        lon, lat = self.xy_to_lonlat(x, y)
        if np.isfinite(lon).all():
            lon = np.unwrap(lon, period=360.0)
        west, east = float(lon.min()), float(lon.max())
        if east - west > 350.0:  # a global map: its edges wrap around the antimeridian
            west, east = -180.0, 180.0
        return west, max(float(lat.min()), -90.0), east, min(float(lat.max()), 90.0)

    def resolution_m(self, lonlat: tuple[float, float] | None = None) -> tuple[float, float]:
        """Ground size (m) of one pixel along x and y at the map's centre, or of the pixel holding
        ``lonlat`` (lon, lat): on a lon/lat map a pixel narrows towards the poles."""
        if lonlat is None:
            rows, cols = self.shape
            c, r = cols / 2.0, rows / 2.0
        else:
            col, row = self.xy_to_pixel(*self.lonlat_to_xy(*lonlat))
            c, r = float(np.floor(col)) + 0.5, float(np.floor(row)) + 0.5
        xs, ys = affine_apply(self.transform, np.array([c, c + 1, c]), np.array([r, r, r + 1]))
        lon, lat = self.xy_to_lonlat(xs, ys)
        _, _, dx = self.geod.inv(lon[0], lat[0], lon[1], lat[1])
        _, _, dy = self.geod.inv(lon[0], lat[0], lon[2], lat[2])
        return float(dx), float(dy)

    def info(self) -> dict[str, object]:
        finite = self.elevation_m[np.isfinite(self.elevation_m)]
        epsg = self.crs.to_epsg()
        return {
            "source": self.source,
            "crs": f"EPSG:{epsg}" if epsg else self.crs.to_string(),
            "body": self.body.name.value,
            "shape": list(self.shape),
            "resolution_m": [round(v, 3) for v in self.resolution_m()],
            "bounds_lonlat": [round(v, 7) for v in self.bounds_lonlat()],
            "elevation_min_m": float(finite.min()),
            "elevation_max_m": float(finite.max()),
            "nodata_cells": int(np.count_nonzero(~np.isfinite(self.elevation_m))),
            "sha256": self.sha256,
        }


def affine_apply(t: Affine, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply an affine transform to arrays of (col, row)."""
    col = np.asarray(col, dtype=float)
    row = np.asarray(row, dtype=float)
    return t.a * col + t.b * row + t.c, t.d * col + t.e * row + t.f


def bilinear(grid: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``grid`` at fractional pixel-centre coordinates; NaN outside."""
    col = np.asarray(col, dtype=float)
    row = np.asarray(row, dtype=float)
    nrows, ncols = grid.shape
    inside = (col >= 0) & (row >= 0) & (col <= ncols - 1) & (row <= nrows - 1)
    c = np.where(inside, col, 0.0)
    r = np.where(inside, row, 0.0)
    c0 = np.minimum(np.floor(c).astype(np.intp), max(ncols - 2, 0))
    r0 = np.minimum(np.floor(r).astype(np.intp), max(nrows - 2, 0))
    fc = c - c0
    fr = r - r0
    c1 = np.minimum(c0 + 1, ncols - 1)
    r1 = np.minimum(r0 + 1, nrows - 1)
    z = np.zeros(c.shape)
    # a corner of zero weight does not count, so a point on a node next to nodata keeps its height
    for rr, cc, w in ((r0, c0, (1 - fc) * (1 - fr)), (r0, c1, fc * (1 - fr)), (r1, c0, (1 - fc) * fr),
                      (r1, c1, fc * fr)):
        z = z + np.where(w > 0, grid[rr, cc] * w, 0.0)
    return np.where(inside, z, np.nan)
