"""The estimator's view of a skyline database: its search grid, and the name of its grid's CRS."""

from __future__ import annotations

import functools

from pyproj import CRS

from appliance.estimator import SkylineGrid
from appliance.estimator.exact import Terrain
from appliance.terrain.database import SkylineDatabase


def skyline_grid(db: SkylineDatabase) -> SkylineGrid:
    """The database's arrays as the estimator searches them (codes, ranges, terrain, first pass)."""
    g = db.grid
    terrain = Terrain(db.terrain_m, db.terrain_origin[0], db.terrain_origin[1], db.convergence_deg, db.height_m,
                      db.r_eff_m, float(db.header["max_range_m"]))
    dc = db.header["distance_code"]
    return SkylineGrid(db.codes, db.offset_deg, db.step_deg, n_rows=g.n_rows, n_cols=g.n_cols, dx_m=g.dx_m,
                       dy_m=g.dy_m, distance_codes=db.distance_codes, ground_m=db.ground_m, terrain=terrain,
                       distance_min_m=float(dc["min_m"]), distance_log_step=float(dc["log_step"]),
                       first_pass=(db.coarse_codes, db.coarse_partial, db.coarse_tau2))


def crs_name(db: SkylineDatabase) -> str:
    """The grid's CRS as EPSG:n where it has a code, else its PROJ string."""
    return _crs_label(db.grid.crs_wkt)


@functools.lru_cache(maxsize=512)
def _crs_label(crs_wkt: str) -> str:
    # looking a custom CRS up in the EPSG catalogue takes tens of ms: once per CRS (a whole-body
    # database has a few hundred facets, each on its own projection)
    crs = CRS.from_wkt(crs_wkt)
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_proj4()
