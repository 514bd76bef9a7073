"""From a skyline database and measured skylines to positions in the map's coordinates.

The glue between the database file (terrain) and the pure estimator: runs single estimates or a
fused sequence, and turns results into the answer placed on the map (:class:`Position`, also the
answer of a tiled search, :mod:`appliance.locating.tiled_search`) and the JSON record that
``viper estimate --json`` prints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.bodies import body_named, geodesic_distance_m
from appliance.estimator import (
    EstimateResult,
    FirstPass,
    PositionPrior,
    SkylineGrid,
    confidence,
    estimate,
    transport_fix,
    transport_prior,
)
from appliance.estimator.estimate import OCCLUSION_WEIGHT
from appliance.estimator.raycast import bilinear
from appliance.locating.search_grid import crs_name, skyline_grid
from appliance.locating.tiled_answer import TileCombination, covariance_json, radius_json
from appliance.locating.tiled_index import TiledIndex
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase

MAX_REGION_CELLS_IN_JSON = 20_000


@dataclass(frozen=True)
class Move:
    """Dead-reckoned displacement between two stations: metres east and north, 1-sigma metres."""

    east_m: float
    north_m: float
    sigma_m: float

    def then(self, other: Move) -> Move:
        """This move followed by ``other``: displacements add, independent sigmas in quadrature."""
        return Move(self.east_m + other.east_m, self.north_m + other.north_m, math.hypot(self.sigma_m, other.sigma_m))


@dataclass(frozen=True)
class Position:
    """An answer placed on the map: where (lat, lon, and x, y in the grid's CRS), the grid's cell and
    the skyline answered.

    From one database, ``estimate`` is the estimator's answer on its grid (:attr:`result`).  From a
    tiled database, ``tiled`` is the combination of the searched tiles
    (:class:`appliance.locating.tiled_answer.TileCombination`), whose posterior bounds, region, status
    and notes are the answer's; no one grid's estimate stands for it, and ``estimate`` is None."""

    estimate: EstimateResult | None
    lat: float
    lon: float
    x: float
    y: float
    crs: str
    cell_size_m: tuple[float, float]
    source: str = ""
    tiled: TileCombination | None = None

    @property
    def result(self) -> EstimateResult:
        """The estimator's answer on the one grid searched (ValueError for a tiled search's answer)."""
        if self.estimate is None:
            raise ValueError("a tiled search's answer has no single grid's estimate: read its 'tiled' combination")
        return self.estimate

    @property
    def heading_correction_deg(self) -> float:
        """The compass's error the answer found (deg)."""
        return self.result.heading_correction_deg if self.tiled is None else self.tiled.heading_correction_deg

    @property
    def notes(self) -> list[str]:
        return self.result.notes if self.tiled is None else self.tiled.notes

    def region_lonlat(self, db: SkylineDatabase, limit: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Longitudes and latitudes of the region's cells (the first ``limit`` of them)."""
        lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(self.result.region_nodes[:limit]))
        return np.atleast_1d(lon), np.atleast_1d(lat)

    def to_json(self, db: SkylineDatabase | TiledIndex, truth: tuple[float, float] | None = None,
                max_cells: int | None = None) -> dict:
        """The answer's record against the database it came from (a file, or a tiled database's
        index); the region lists its first ``max_cells`` cells (default MAX_REGION_CELLS_IN_JSON) and
        counts them all."""
        limit = MAX_REGION_CELLS_IN_JSON if max_cells is None else max_cells
        if self.tiled is not None:
            if not isinstance(db, TiledIndex):
                raise TypeError("a tiled search's answer is recorded against its tiled database's index")
            return self.tiled.to_json(db, truth, limit)
        if isinstance(db, TiledIndex):
            raise TypeError("an answer from one database file is recorded against that file")
        r = self.result
        lon, lat = self.region_lonlat(db, limit)
        cells = [[round(float(a), 7), round(float(b), 7)] for a, b in zip(lat, lon)]
        out: dict = {
            "skyline": self.source,
            "lat": round(self.lat, 8),
            "lon": round(self.lon, 8),
            "x": round(self.x, 3) if abs(self.x) > 1000 else self.x,
            "y": round(self.y, 3) if abs(self.y) > 1000 else self.y,
            "crs": self.crs,
            "heading_correction_deg": round(r.heading_correction_deg, 3),
            "lower": r.lower,
            "upper": r.upper,
            "log10_lower": round(r.log_lower / math.log(10.0), 4),
            "region": {
                "area_m2": round(r.region_area_m2, 1),
                "cell_size_m": [round(v, 3) for v in self.cell_size_m],
                "n_cells": int(r.region_nodes.size),
                "cells": cells,
                "cells_truncated": int(r.region_nodes.size) > len(cells),
            },
            "covariance_m2": covariance_json(r.covariance_m2),
            "radius95_m": radius_json(r.covariance_m2),
            "altitude_m": _round_or_none(altitude_m(db, self), 2),
            "independent_azimuths": _round_or_none(r.independent_azimuths, 1),
            "ambiguous": r.ambiguous,
            "status": estimate_status(db, self, truth),
            "rms_residual_deg": round(r.rms_residual_deg, 4),
            "valid_azimuths": r.n_valid,
            "sigma_deg": list(r.sigma_deg),
            "candidates": r.candidates,
            "elapsed_ms": round(r.elapsed_s * 1e3, 2),
            "notes": r.notes,
        }
        if truth is not None:
            out["truth"] = {"lat": truth[0], "lon": truth[1], "error_m": round(truth_error_m(db, self, truth), 2)}
        return out


def _round_or_none(v: float, digits: int) -> float | None:
    return round(v, digits) if math.isfinite(v) else None


def altitude_m(db: SkylineDatabase, pos: Position) -> float:
    """The camera's altitude (m, the map's vertical datum): the map's surface under the answer plus
    the camera's height and the eye's offset the exact fit found; NaN off the map."""
    r = pos.result
    ground = bilinear(db.terrain_m, r.row + db.terrain_origin[0], r.col + db.terrain_origin[1])
    eye = r.eye_offset_m if math.isfinite(r.eye_offset_m) else 0.0
    return ground + float(db.height_m) + eye


def truth_error_m(db: SkylineDatabase, pos: Position, truth: tuple[float, float]) -> float:
    """Geodesic distance (m) on the database's body from the estimate to ``truth`` (lat, lon)."""
    return geodesic_distance_m(pos.lat, pos.lon, truth[0], truth[1], body_named(db.header["body"]))


def truth_offset_m(db: SkylineDatabase, pos: Position, truth: tuple[float, float]) -> np.ndarray:
    """Where the true (lat, lon) lies from the estimate: metres east and north, along the geodesic
    on the database's body."""
    az, _, dist = body_named(db.header["body"]).geod.inv(pos.lon, pos.lat, truth[1], truth[0])
    a = math.radians(float(az))
    return np.array([dist * math.sin(a), dist * math.cos(a)])


def truth_in_ellipse(db: SkylineDatabase, pos: Position, truth: tuple[float, float],
                     level: float = confidence.LEVEL) -> bool:
    """Whether the true (lat, lon) lies inside the estimate's covariance ellipse at ``level``."""
    cov = pos.result.covariance_m2
    return cov is not None and confidence.inside_ellipse(truth_offset_m(db, pos, truth), cov, level)


def truth_in_region(db: SkylineDatabase, pos: Position, truth: tuple[float, float]) -> bool:
    """Whether the true (lat, lon) lies inside the estimate's 95 % region: the answer's ellipse, or a
    cell of a rival place (the node nearest the truth among the region's rival nodes)."""
    if truth_in_ellipse(db, pos, truth):
        return True
    x, y = db.grid.lonlat_to_xy(truth[1], truth[0])
    fr, fc = db.grid.xy_to_rc(x, y)
    r, c = int(round(float(fr))), int(round(float(fc)))
    if not (0 <= r < db.grid.n_rows and 0 <= c < db.grid.n_cols):
        return False
    return bool(np.isin(r * db.grid.n_cols + c, pos.result.rival_nodes))


def estimate_status(db: SkylineDatabase, pos: Position, truth: tuple[float, float] | None = None) -> str:
    """'ambiguous' when rival places share the posterior, or the truth (where known) lies outside the
    region; else 'ok'."""
    if pos.result.ambiguous or (truth is not None and not truth_in_region(db, pos, truth)):
        return "ambiguous"
    return "ok"


def area_text(area_m2: float) -> str:
    """An area as a person reads it: m^2 below a hectare, else km^2."""
    return f"{area_m2:.0f} m^2" if area_m2 < 1e4 else f"{area_m2 / 1e6:.3f} km^2"


def fix_status(pos: Position) -> str:
    """"ok +- R m" (R: the 95 % ellipse's semi-major axis) or "ambiguous": what a person reads."""
    r = pos.result
    return "ambiguous" if r.ambiguous else sure_text(r.covariance_m2)


def sure_text(cov: np.ndarray | None) -> str:
    """"ok +- R m" for an answer that is not ambiguous with the covariance ``cov`` (m^2), R its 95 %
    ellipse's semi-major axis; "ambiguous" without a finite one."""
    if cov is None or not np.all(np.isfinite(cov)):
        return "ambiguous"
    return f"ok ± {confidence.radius_m(cov):.1f} m"


def status_text(db: SkylineDatabase, pos: Position, truth: tuple[float, float] | None = None) -> str:
    """:func:`fix_status` ("ok +- R m"), or "ambiguous" where :func:`estimate_status` says so (the truth,
    where known, outside the region)."""
    return fix_status(pos) if estimate_status(db, pos, truth) == "ok" else "ambiguous"


def answer_text(pos: Position, record: dict) -> str:
    """The answer in one line as ``viper estimate`` prints it, from the answer and its record
    (:meth:`Position.to_json`): position, status, the tile of a tiled search, heading correction,
    region, residual and, where the record has the truth, the error."""
    err = f"  error {record['truth']['error_m']:.0f} m" if "truth" in record else ""
    if pos.tiled is None:
        r = pos.result
        status = fix_status(pos) if record["status"] == "ok" else record["status"]
        tile, area, cells, residual = "", area_text(r.region_area_m2), int(r.region_nodes.size), r.rms_residual_deg
    else:
        status = sure_text(pos.tiled.covariance_m2) if record["status"] == "ok" else record["status"]
        tile = f"  tile {pos.tiled.tile}"
        area, cells = f"{pos.tiled.region_area_m2 / 1e6:.3f} km^2", len(pos.tiled.region)
        residual = record["rms_residual_deg"]
    return (f"{pos.lat:.6f}, {pos.lon:.6f}  {status}{tile}  heading correction {pos.heading_correction_deg:+.1f} deg"
            f"  region {area} ({cells} cells)  residual {residual:.2f} deg{err}")


def place(db: SkylineDatabase, result: EstimateResult, source: str = "") -> Position:
    """The estimator's answer on ``db``'s grid placed on the map."""
    x, y = db.grid.rc_to_xy(result.row, result.col)
    lon, lat = db.grid.xy_to_lonlat(x, y)
    return Position(result, float(lat), float(lon), float(x), float(y), crs_name(db),
                    (db.grid.dx_m, db.grid.dy_m), source)


def place_tiled(tiled: TileCombination, source: str = "") -> Position:
    """A tiled search's answer placed on the map: where its combination puts it (its best tile's
    node, or its fit on the map's own surface), in that tile's grid coordinates."""
    return Position(None, tiled.lat, tiled.lon, tiled.x, tiled.y, tiled.crs, tiled.best.cell_size_m, source, tiled)


def locate(
    db: SkylineDatabase,
    skyline: Skyline,
    sigma_deg: tuple[float, float],
    heading_tolerance_deg: float | None,
    *,
    log_prior: np.ndarray | None = None,
    source: str = "",
    grid: SkylineGrid | None = None,
    height_m: float | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    map_sigma_m: float = 0.0,
    position_prior: PositionPrior | None = None,
    refine: bool = True,
    rescore_floor: float | None = None,
    first: FirstPass | None = None,
    learn_noise: bool = True,
    sigma_floor_deg: float | None = None,
    temper: float = 1.0,
    allowed_sigma_deg: float | None = None,
    polish: bool = False,
) -> Position:
    """Estimate where ``skyline`` was seen; ``height_m`` is the camera's height above the map's
    surface for the exact refinement (default: the database's).  The skyline's confidence weighs
    its azimuths; ``occlusion_weight``, ``map_sigma_m``, ``position_prior``, ``refine``,
    ``rescore_floor``, ``first``, ``learn_noise``, ``sigma_floor_deg``, ``temper``,
    ``allowed_sigma_deg`` and ``polish`` are those of
    :func:`appliance.estimator.estimate`."""
    g = skyline_grid(db) if grid is None else grid
    res = estimate(g, skyline.azimuth_deg, skyline.elevation_deg, sigma_deg, heading_tolerance_deg, log_prior,
                   height_m=height_m, weights=skyline.confidence, occlusion_weight=occlusion_weight,
                   map_sigma_m=map_sigma_m, position_prior=position_prior, refine=refine,
                   rescore_floor=rescore_floor, first=first, learn_noise=learn_noise, temper=temper,
                   sigma_floor_deg=sigma_floor_deg, allowed_sigma_deg=allowed_sigma_deg, polish=polish)
    return place(db, res, source)


def _move_on_grid(db: SkylineDatabase, pos: Position, move: Move) -> tuple[float, float]:
    """``move`` (true east and north) along the grid's axes (x, y in metres), turned by the grid
    convergence at ``pos``."""
    gamma = math.radians(float(db.convergence_deg[pos.result.node]))
    c, s = math.cos(gamma), math.sin(gamma)
    # grid +x is (cos g, -sin g) and grid +y is (sin g, cos g) in (east, north)
    return move.east_m * c - move.north_m * s, move.east_m * s + move.north_m * c


def transported_prior(db: SkylineDatabase, grid: SkylineGrid, pos: Position, move: Move) -> np.ndarray:
    """The log prior per node of the next station: ``pos``'s posterior moved by ``move`` (true east and
    north, turned onto the grid's axes by the grid convergence at ``pos``) and blurred by its sigma."""
    x_m, y_m = _move_on_grid(db, pos, move)
    return transport_prior(pos.result.posterior_map, grid.n_rows, grid.n_cols, grid.dx_m, grid.dy_m, x_m, y_m,
                           move.sigma_m)


def transported_fix(db: SkylineDatabase, grid: SkylineGrid, pos: Position, move: Move) -> PositionPrior | None:
    """The same belief in continuous form, for the exact fit between nodes: ``pos``'s fix and its
    covariance moved by ``move``.  None when ``pos`` is ambiguous (its posterior has more than one
    place, which one Gaussian would misstate) or has no exact fit's covariance."""
    cov = pos.result.covariance_cells
    if pos.result.ambiguous or cov is None:
        return None
    x_m, y_m = _move_on_grid(db, pos, move)
    return transport_fix(pos.result.row, pos.result.col, cov, grid.dx_m, grid.dy_m, x_m, y_m, move.sigma_m)


def locate_sequence(
    db: SkylineDatabase,
    skylines: list[tuple[str, Skyline]],
    moves: list[Move],
    sigma_deg: tuple[float, float],
    heading_tolerance_deg: float | None,
    *,
    height_m: float | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    map_sigma_m: float = 0.0,
) -> list[Position]:
    """Fuse a sequence: each skyline's prior is the previous posterior moved by ``moves[i-1]``.

    Every position is reported where the platform stood for that skyline.
    """
    if len(moves) != len(skylines) - 1:
        raise ValueError(f"{len(skylines)} skylines need {len(skylines) - 1} moves, got {len(moves)}")
    g = skyline_grid(db)
    out: list[Position] = []
    prior, fix = None, None
    for i, (name, sky) in enumerate(skylines):
        pos = locate(db, sky, sigma_deg, heading_tolerance_deg, log_prior=prior, source=name, grid=g,
                     height_m=height_m, occlusion_weight=occlusion_weight, map_sigma_m=map_sigma_m,
                     position_prior=fix)
        out.append(pos)
        if i < len(moves):
            prior, fix = transported_prior(db, g, pos, moves[i]), transported_fix(db, g, pos, moves[i])
    return out
