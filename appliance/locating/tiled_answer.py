"""What a tiled search finds: each tile's search reduced to what travels back, and their combination.

A tile's outcome (:class:`TileOutcome`) is small enough to travel back from a Dask worker: the
tile's own JSON record, its best candidate's posterior bounds and normalisers, its most likely
nodes.  Their combination (:class:`TileCombination`, made by
:func:`appliance.locating.tile_combination.combine`) is what a :class:`appliance.locating.position.Position`
of a tiled search carries: the posterior bounds, the region across tiles, the status and the notes
of the answer, and, for a whole-body database, the answer's fit on the map's own surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from appliance.bodies import body_named, geodesic_distance_m
from appliance.estimator import confidence
from appliance.locating.tile_cache import open_tile
from appliance.locating.tiled_index import TiledIndex
from appliance.terrain.grid import lon_overlap


def covariance_json(cov: np.ndarray | None) -> list[list[float]] | None:
    """[[ee, en], [en, nn]] (m^2) as the JSON record carries it; None without one."""
    if cov is None:
        return None
    return [[round(float(cov[0, 0]), 4), round(float(cov[0, 1]), 4)],
            [round(float(cov[1, 0]), 4), round(float(cov[1, 1]), 4)]]


def radius_json(cov: np.ndarray | None) -> float | None:
    """The 95 % ellipse's semi-major axis (m) as the JSON record carries it; None without one."""
    return None if cov is None else round(confidence.radius_m(cov), 2)


@dataclass(frozen=True)
class TileOutcome:
    """One tile's search, reduced to what the combination and the outputs need (small enough to
    travel back from a Dask worker: no per-node maps, only the TOP_NODES most likely nodes)."""

    file: str
    error: str | None
    record: dict = field(default_factory=dict)  # the tile's own JSON record (Position.to_json), no region cells
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
    x: float = math.nan  # the best candidate in the tile grid's CRS
    y: float = math.nan
    crs: str = ""
    #: the noise learned from the tile's best fit: sigma's interval (deg) and the tempering; None
    #: where the search kept the sigma it was given
    noise: tuple[float, float, float] | None = None



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
    """The answer fitted on the map's own surface (:mod:`appliance.locating.verification`): where, in which
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
    #: the fit's covariance (east, north; m^2) at the noise learned from it; None where not made
    covariance_m2: np.ndarray | None = None
    #: the noise the fit's residuals give: sigma's interval (deg) and the tempering; None without
    noise: tuple[float, float, float] | None = None
    fits: int = 0  # places fitted (of those looked at)
    rivals: int = 0  # places fitted more than two cells away whose fit comes within RIVAL_SHARE of the best's


@dataclass(frozen=True)
class TileCombination:
    """The tiles' searches combined: the best tile's outcome, the best candidate's posterior bounds
    over every searched tile, the region across them, whether the answer is ambiguous and, where
    the map was at hand, the answer fitted on its own surface."""

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
    #: the noise the search weighed every tile at, learned from its first round's answer: sigma's
    #: interval (deg) and the tempering; None where it kept the sigma it was given
    noise: tuple[float, float, float] | None = None
    #: whether another tile holds a place of the region more than two cells from the answer
    rival_tiles: bool = False

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
    def x(self) -> float:
        return self.best.x if self.fit is None else self.fit.x

    @property
    def y(self) -> float:
        return self.best.y if self.fit is None else self.fit.y

    @property
    def crs(self) -> str:
        return self.best.crs if self.fit is None else self.fit.crs

    @property
    def heading_correction_deg(self) -> float:
        if self.fit is not None:
            return self.fit.heading_correction_deg
        return float(self.best.record["heading_correction_deg"])

    @property
    def covariance_m2(self) -> np.ndarray | None:
        """The answer's covariance (east, north; m^2): its fit's on the map's surface, else its best
        tile's exact fit's; None where there is none."""
        if self.fit is not None:
            return self.fit.covariance_m2
        cov = self.best.record.get("covariance_m2")
        return None if cov is None else np.asarray(cov, dtype=np.float64)

    def truth_error_m(self, truth: tuple[float, float]) -> float:
        return geodesic_distance_m(self.lat, self.lon, truth[0], truth[1], body_named(self.body))

    def status(self, index: TiledIndex | None = None, truth: tuple[float, float] | None = None) -> str:
        """'ambiguous' when the combination is, when it has no finite covariance, or when the truth
        (where known) lies outside both the region and the answer's 95 % ellipse; else 'ok'."""
        cov = self.covariance_m2
        if self.ambiguous or cov is None or not np.all(np.isfinite(cov)):
            return "ambiguous"
        if truth is not None and not self.truth_in_ellipse(truth) and (
                index is None or not self.truth_in_region(index, truth)):
            return "ambiguous"
        return "ok"

    def truth_in_ellipse(self, truth: tuple[float, float]) -> bool:
        """Whether the true (lat, lon) lies inside the answer's 95 % covariance ellipse (False
        without a finite covariance)."""
        cov = self.covariance_m2
        if cov is None or not np.all(np.isfinite(cov)):
            return False
        az, _, dist = body_named(self.body).geod.inv(self.lon, self.lat, truth[1], truth[0])
        offset = dist * np.array([math.sin(math.radians(az)), math.cos(math.radians(az))])
        return confidence.inside_ellipse(offset, cov)

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
            grid = open_tile(str(index.folder), t, None)[0].grid
            fr, fc = grid.xy_to_rc(*grid.lonlat_to_xy(lon, lat))
            r, c = int(round(float(fr))), int(round(float(fc)))
            if 0 <= r < grid.n_rows and 0 <= c < grid.n_cols and (t.file, r * grid.n_cols + c) in cells:
                return True
        return False

    def to_json(self, index: TiledIndex | None, truth: tuple[float, float] | None, max_cells: int) -> dict:
        """The single-file record (:meth:`appliance.locating.position.Position.to_json`) of the best tile, its
        bounds, region and status replaced by the combined ones, and which tiles were searched; the
        region lists its first ``max_cells`` cells and counts them all."""
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
                "cells": cells[:max_cells],
                "cells_truncated": len(cells) > max_cells,
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
        if self.noise is not None:
            out["sigma_deg"] = [round(v, 6) for v in self.noise[:2]]
        if self.fit is not None:
            f = self.fit
            out.update({"lat": round(f.lat, 8), "lon": round(f.lon, 8), "x": round(f.x, 3), "y": round(f.y, 3),
                        "covariance_m2": covariance_json(f.covariance_m2), "radius95_m": radius_json(f.covariance_m2),
                        "crs": f.crs, "heading_correction_deg": round(f.heading_correction_deg, 3),
                        "rms_residual_deg": round(f.rms_deg, 4),
                        "surface_fit": {"places": f.places, "screened": f.screened,
                                        "grid_distance_m": round(f.grid_distance_m, 1)}})
        if truth is not None:
            out["truth"] = {"lat": truth[0], "lon": truth[1], "error_m": round(self.truth_error_m(truth), 2)}
        return out
