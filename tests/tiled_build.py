"""A small tiled skyline database for the tests and the bench, made from ordinary builds.

Not the product's tiled build: each tile here is an ordinary ``build_database`` over its own
lon/lat box, with an ``index.json`` written next to the tiles.  The boxes are cut half a node
between lattice nodes of the whole area's grid, so the tiles' candidate nodes partition the whole
area's nodes (no node in two tiles, none left out) and lie on the same lattice.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from appliance.atomic import write_text_atomic
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import Dem


def build_tiled(dem: Dem, folder: Path, bounds: tuple[float, float, float, float], tiles: tuple[int, int],
                max_range_m: float, n_azimuths: int = 360, whole: Path | None = None) -> Path:
    """Build a tiled database of ``tiles`` (rows, cols) over ``bounds`` (W, S, E, N) into ``folder``;
    with ``whole``, also the single-file database of the whole area there (built first: its grid
    decides where the tiles are cut)."""
    folder.mkdir(parents=True, exist_ok=True)
    whole = whole or folder / "whole.viperdb.tmp-grid"
    build_database(dem, whole, search_bounds=bounds, max_range_m=max_range_m, n_azimuths=n_azimuths, workers=2)
    g = load_database(whole).grid
    if whole.name.endswith(".tmp-grid"):
        whole.unlink()
    n_tr, n_tc = tiles
    row_cuts = [round(k * g.n_rows / n_tr) for k in range(n_tr + 1)]
    col_cuts = [round(k * g.n_cols / n_tc) for k in range(n_tc + 1)]
    entries = []
    for i in range(n_tr):
        for j in range(n_tc):
            r0, r1, c0, c1 = row_cuts[i], row_cuts[i + 1], col_cuts[j], col_cuts[j + 1]
            # half a node outside the tile's first and last nodes: a boundary never falls on a node
            west = g.x0 + (c0 - 0.5) * g.dx
            east = g.x0 + (c1 - 0.5) * g.dx
            north = g.y0 - (r0 - 0.5) * g.dy
            south = g.y0 - (r1 - 0.5) * g.dy
            box = (west, south, east, north)
            name = f"tile_r{i:03d}_c{j:03d}.viperdb"
            build_database(dem, folder / name, search_bounds=box, max_range_m=max_range_m, n_azimuths=n_azimuths,
                           workers=2)
            tg = load_database(folder / name).grid
            assert (tg.n_rows, tg.n_cols) == (r1 - r0, c1 - c0), (name, tg.n_rows, tg.n_cols)
            assert math.isclose(tg.x0, g.x0 + c0 * g.dx, abs_tol=1e-9 * abs(g.dx) + 1e-12)
            entries.append({"file": name, "row0": r0, "col0": c0, "n_rows": r1 - r0, "n_cols": c1 - c0,
                            "bounds_lonlat": list(box)})
    header = load_database(folder / entries[0]["file"]).header
    index = {
        "format": "viper-tiled-db", "format_version": 1,
        "lattice": {"crs_wkt": g.crs_wkt, "x0": g.x0, "y0": g.y0, "dx": g.dx, "dy": g.dy, "n_rows": g.n_rows,
                    "n_cols": g.n_cols, "dx_m": g.dx_m, "dy_m": g.dy_m},
        "tile_nodes": [max(e["n_rows"] for e in entries), max(e["n_cols"] for e in entries)],
        "tiles": entries,
        "n_azimuths": n_azimuths, "height_m": header["height_m"], "max_range_m": max_range_m,
        "refraction": header["refraction"], "body": header["body"],
        "sources": [{"name": header["dem_source"], "sha256": header["dem_sha256"]}],
    }
    write_text_atomic(folder / "index.json", json.dumps(index, indent=1))
    return folder
