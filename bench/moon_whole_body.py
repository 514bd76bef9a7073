"""The LOLA Moon as a whole-body tiled database, and positions located anywhere on it.

Builds every facet of the LOLA 4 px/deg map (appliance/terrain/whole_body.py) on a Dask
LocalCluster of two single-threaded workers, cached in bench/cache/ (a rerun reuses it and
reports the first build's figures); then places seeded positions uniformly on the sphere between
latitudes -80 and +80 degrees, renders each one's skyline with render_skyline at the database's
camera height, range and one-degree azimuths, reads it with a compass off by up to 4 degrees
(uniform) and 0.2 degrees of Gaussian noise, and locates it twice: within a box of 100 km around
the truth, and over the whole body (every facet, one Dask task per facet on the same cluster).
"Within two cells" is a geodesic error at most twice the facets' node spacing.

    python bench/moon_whole_body.py [--positions 20] [--whole-positions 20] [--max-range 150000]
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.atomic import write_text_atomic  # noqa: E402
from appliance.bodies import geodesic_distance_m  # noqa: E402
from appliance.locating.surface_fit import SCREEN_PLACES, SURFACE_PLACES  # noqa: E402
from appliance.locating.tile_cache import SearchParams  # noqa: E402
from appliance.locating.tiled_index import box_around, open_surface, open_tiled  # noqa: E402
from appliance.locating.tiled_search import locate_tiled  # noqa: E402
from appliance.skyline import Skyline  # noqa: E402
from appliance.terrain.database import load_database  # noqa: E402
from appliance.terrain.horizon import render_skyline  # noqa: E402
from appliance.terrain.mosaic import open_map  # noqa: E402
from appliance.terrain.whole_body import build_whole_body, default_spacing_m  # noqa: E402

LOLA = HERE.parent.parent / "shared" / "data" / "dem_planetary" / "LDEM_4.LBL"
PARAMS = SearchParams((0.3, 1.2), 4.0)
HEIGHT_M = 1.5
N_AZ = 360
COMPASS_DEG = 4.0
NOISE_DEG = 0.2
MAX_LAT = 80.0


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def measured(dem, lat: float, lon: float, max_range_m: float, rng: np.random.Generator) -> Skyline:
    az = np.arange(360.0)
    err = rng.uniform(-COMPASS_DEG, COMPASS_DEG)
    truth = render_skyline(dem, lat, lon, HEIGHT_M, az, max_range_m).elevation_deg
    el = np.interp((az + err) % 360.0, az, truth, period=360.0) + rng.normal(0.0, NOISE_DEG, az.size)
    return Skyline(az, el)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--positions", type=int, default=20)
    ap.add_argument("--whole-positions", type=int, default=20, help="how many of them to locate over the whole body")
    ap.add_argument("--max-range", type=float, default=150_000.0)
    ap.add_argument("--box-km", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--grid-only", action="store_true", help="answers on the facets' grid, not fitted on the map")
    args = ap.parse_args()
    from distributed import Client, LocalCluster

    source = open_map([str(LOLA)], None)
    dem = source.load()
    spacing = default_spacing_m(dem)
    folder = HERE / "cache" / f"moon_whole_body_{spacing:.0f}m_{args.max_range / 1000:.0f}km"
    folder.mkdir(parents=True, exist_ok=True)
    stats_path = folder / "build_stats.json"
    out = HERE / "results" / "moon_whole_body.md"
    load_before = uptime()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
        res = build_whole_body(source, folder, max_range_m=args.max_range, n_azimuths=N_AZ, height_m=HEIGHT_M,
                               client=client)
        if res.built:
            stats = {"seconds": res.seconds, "built": len(res.built), "peak_rss_bytes": res.peak_rss_bytes,
                     "uptime": load_before, "date": date.today().isoformat()}
            write_text_atomic(stats_path, json.dumps(stats, indent=1))
        stats = json.loads(stats_path.read_text())
        index = open_tiled(folder)
        surface, why_not = (None, "--grid-only") if args.grid_only else open_surface(index)
        if surface is None:
            print(f"answers stay on the facets' grid: {why_not}", flush=True)
        nodes = 0
        storage = 0
        for t in index.tiles:
            nodes += int(load_database(index.path(t)).valid_nodes.sum())
            storage += index.path(t).stat().st_size
        print(f"{len(index.tiles)} facets, {nodes} nodes, {storage / 2**30:.2f} GiB, built in {stats['seconds']:.0f} s",
              flush=True)

        rng = np.random.default_rng(args.seed)
        s = np.sin(np.radians(MAX_LAT))
        lats = np.degrees(np.arcsin(rng.uniform(-s, s, args.positions)))
        lons = rng.uniform(0.0, 360.0, args.positions)
        rows: list[dict] = []

        # the earlier runs' sections (every "## " heading after this run's Build and Positions) stay below it
        kept = out.read_text().splitlines() if out.exists() else []
        at = next((i for i, line in enumerate(kept) if line.startswith("## ") and line not in
                   ("## Build", "## Positions")), len(kept))
        earlier = "\n".join(["", *kept[at:]]) if at < len(kept) else ""

        def write() -> None:
            write_text_atomic(out, report(rows, index, nodes, storage, stats, spacing, args, load_before,
                                          surface is not None) + earlier)

        skies = [measured(dem, float(lat), float(lon), index.max_range_m, np.random.default_rng(args.seed * 1000 + k))
                 for k, (lat, lon) in enumerate(zip(lats, lons))]
        # first every position within its box (a few facets each), then over the whole body
        for k, (lat, lon) in enumerate(zip(lats, lons)):
            sky = skies[k]
            row: dict = {"lat": float(lat), "lon": float(lon), "relief": float(np.nanmax(sky.elevation_deg)
                                                                              - np.nanmin(sky.elevation_deg))}
            t0 = time.perf_counter()
            r = locate_tiled(index, sky, PARAMS, box=box_around(float(lat), float(lon), args.box_km * 1e3, "moon"),
                             surface=surface)
            row["box"] = (geodesic_distance_m(lat, lon, r.lat, r.lon, dem.body), time.perf_counter() - t0,
                          r.tiled.status() != "ok", len(r.tiled.tiles_searched),
                          r.tiled.truth_in_ellipse((float(lat), float(lon))))
            rows.append(row)
            print(k, "box", [round(v, 2) if isinstance(v, float) else v for v in row["box"]], flush=True)
            write()
        for k, (lat, lon) in enumerate(zip(lats, lons)):
            if k >= args.whole_positions:
                break
            t0 = time.perf_counter()
            r = locate_tiled(index, skies[k], PARAMS, client=client, surface=surface)
            rows[k]["whole"] = (geodesic_distance_m(lat, lon, r.lat, r.lon, dem.body), time.perf_counter() - t0,
                                r.tiled.status() != "ok", len(r.tiled.tiles_searched),
                                r.tiled.truth_in_ellipse((float(lat), float(lon))))
            print(k, "whole", [round(v, 2) if isinstance(v, float) else v for v in rows[k]["whole"]], flush=True)
            write()
    return 0


def report(rows: list[dict], index, nodes: int, storage: int, stats: dict, spacing: float,
           args: argparse.Namespace, load_before: str, fitted: bool) -> str:
    cell2 = 2.0 * spacing
    lines = [
        "# The LOLA Moon as a whole-body tiled database",
        "",
        f"Run {date.today().isoformat()} on {platform.machine()}, 2 cores shared with other jobs, by "
        "`python bench/moon_whole_body.py` (bench/moon_whole_body.py).",
        "",
        "## Build",
        "",
        f"LOLA LDEM_4 (1440 x 720, 7.58 km pixels), {len(index.tiles)} facets (15-degree bands cut into boxes "
        f"about as wide as high, two polar caps beyond +-75 degrees), nodes every {spacing:.0f} m (half a pixel), "
        f"{N_AZ} azimuths, camera {HEIGHT_M} m, reach {index.max_range_m / 1000:.0f} km, on a LocalCluster of 2 "
        "single-threaded workers.",
        "",
        "| facets | nodes | storage | build time | peak worker memory | load before the build (uptime) |",
        "|---|---|---|---|---|---|",
        f"| {len(index.tiles)} | {nodes:,} | {storage / 2**30:.2f} GiB | {stats['seconds']:.0f} s "
        f"({stats['built']} facets built) | {stats['peak_rss_bytes'] / 2**20:.0f} MiB | {stats['uptime']} |",
        "",
        "## Positions",
        "",
        f"{len(rows)} seeded positions (seed {args.seed}) uniform on the sphere between -{MAX_LAT:.0f} and "
        f"+{MAX_LAT:.0f} degrees of latitude; skylines by render_skyline at the database's height, range and "
        f"one-degree azimuths, compass error uniform within +-{COMPASS_DEG:.0f} deg, noise {NOISE_DEG} deg "
        f"(Gaussian); estimator sigma {PARAMS.sigma_deg}, heading tolerance {PARAMS.heading_tolerance_deg} deg. "
        f"Within two cells: geodesic error <= {cell2 / 1000:.2f} km (twice the facets' spacing).",
        "",
        ("Answers fitted on the map's own surface (up to "
         f"{SCREEN_PLACES} contending places of the facets' region screened on the map, the grid's best and the "
         f"{SURFACE_PLACES - 1} that screen best fitted, appliance/locating/verification.py)." if fitted else
         "Answers on the facets' grid alone (refined on the facets' resampled surface), not fitted on the map."),
        "",
        f"Load before the estimates (uptime): {load_before}",
        "",
    ]
    for key, name in (("box", f"within a {args.box_km:.0f} km box around the truth"),
                      ("whole", "over the whole body (every facet, no box)")):
        got = [r[key] for r in rows if key in r]
        if not got:
            continue
        err = np.array([g[0] for g in got])
        t = np.array([g[1] for g in got])
        within = float(np.mean(err <= cell2)) * 100.0
        right = err <= cell2
        ok = np.array([not g[2] for g in got])
        ellipse = np.array([g[4] for g in got])
        lines += [f"### Located {name}", "",
                  "| positions | within two cells | median error | max error | ambiguous | right and ok (of right) | "
                  "wrong and ok (target 0) | truth in 95 % ellipse (right answers) | facets searched | "
                  "time per estimate (median) |", "|---|---|---|---|---|---|---|---|---|---|",
                  f"| {len(got)} | {within:.0f} % | {np.median(err) / 1000:.2f} km | {err.max() / 1000:.1f} km | "
                  f"{int((~ok).sum())} | {int((ok & right).sum())} of {int(right.sum())} | "
                  f"{int((ok & ~right).sum())} | "
                  f"{int((ellipse & right).sum())} of {int(right.sum())} | {int(np.median([g[3] for g in got]))} | "
                  f"{np.median(t):.1f} s |", ""]
    lines += ["### Every position", "", "| lat | lon | skyline relief (deg) | box error (km) | whole-body error (km) |",
              "|---|---|---|---|---|"]
    for r in rows:
        w = f"{r['whole'][0] / 1000:.1f}{' (ambiguous)' if r['whole'][2] else ''}" if "whole" in r else "-"
        lines.append(f"| {r['lat']:.2f} | {r['lon']:.2f} | {r['relief']:.2f} | "
                     f"{r['box'][0] / 1000:.1f}{' (ambiguous)' if r['box'][2] else ''} | {w} |")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
