"""Tiled skyline database on Dask against the single-process build, on the SRTM mosaic
N43E006 + N43E007 (1201 x 2401 nodes at the map's own spacing), 360 azimuths.

Reports the wall time of each, the peak resident memory of the single build's process and of the
busiest tile worker (each task reads its process's peak with getrusage), and how many nodes of the
tiled database differ from the single build (codes, ranges, offset or step).  Until the sweep cuts
the horizon off exactly at the maximum range, a tile whose terrain window is clipped at the reach
can see a different horizon than the whole map gives, so a non-zero count is expected and reported.

    python bench/tiled_build.py [--tile-nodes 1201,1201] [--workers 2] [--azimuths 360]
    python bench/tiled_build.py --probe-spacing 30   # one tile of the 30 m build: a worker's peak memory
    python bench/tiled_build.py --full-spacing 30 --out DIR   # the whole 30 m build on the local cluster

The probe builds the tile with the largest terrain window in this process: the peak memory a worker
needs for it.  The full build writes the whole tiled database into DIR (kept, so that an interrupted
run resumes with the missing tiles) and appends its wall time, the largest worker's peak memory,
the storage and the rate per worker to tiled_build_30m.md.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
SHARED = HERE.parent.parent / "shared" / "data" / "dem_srtm_hgt"
TILES = [str(SHARED / "N43E006.hgt"), str(SHARED / "N43E007.hgt")]


def _single(folder: str, n_az: int, queue: multiprocessing.Queue) -> None:
    """Child process: the single-process build of the whole mosaic; sends back seconds and peak RSS."""
    from appliance.terrain.database import build_database
    from appliance.terrain.mosaic import open_map

    t0 = time.perf_counter()
    dem = open_map(TILES, Path(folder) / "single.vrt").load()
    build_database(dem, Path(folder) / "single.viperdb", n_azimuths=n_az, progress=None)
    queue.put((time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024))


#: the control: a window of the mosaic, built with a reach longer than the whole map, so that every
#: tile's terrain window is the single build's: any differing node would be the tiling's own error
CONTROL_BOUNDS = (6.9, 43.6, 7.3, 43.8)
CONTROL_RANGE_M = 300_000.0
CONTROL_AZIMUTHS = 32


def _control(client: object, folder: Path) -> tuple[int, int, int]:
    """Differing nodes, nodes and tiles of the control build (single vs tiled, same window)."""
    from appliance.terrain.database import build_database
    from appliance.terrain.mosaic import open_map
    from appliance.terrain.tiled import build_tiled

    out = folder / "control_tiled"
    out.mkdir()
    source = open_map(TILES, out / "mosaic.vrt")
    build_database(source.load(), folder / "control.viperdb", CONTROL_BOUNDS, n_azimuths=CONTROL_AZIMUTHS,
                   max_range_m=CONTROL_RANGE_M, progress=None)
    res = build_tiled(source, out, CONTROL_BOUNDS, n_azimuths=CONTROL_AZIMUTHS, max_range_m=CONTROL_RANGE_M,
                      tile_nodes=(80, 160), client=client)
    differ, n_nodes = _differing_nodes(folder / "control.viperdb", out)
    return differ, n_nodes, len(res.index["tiles"])


def _differing_nodes(single_path: Path, tiled: Path) -> tuple[int, int]:
    """Nodes of the tiled database in ``tiled`` that differ from the single build; nodes."""
    import numpy as np

    from appliance.terrain.database import load_database

    single = load_database(single_path)
    index = json.loads((tiled / "index.json").read_text())
    n_cols = single.grid.n_cols
    differ = 0
    for t in index["tiles"]:
        db = load_database(tiled / t["file"])
        rows = np.arange(t["row0"], t["row0"] + t["n_rows"])
        cols = np.arange(t["col0"], t["col0"] + t["n_cols"])
        idx = (rows[:, None] * n_cols + cols[None, :]).ravel()
        bad = (np.any(np.asarray(db.codes) != single.codes[idx], axis=1)
               | np.any(np.asarray(db.distance_codes) != single.distance_codes[idx], axis=1))
        for name in ("offset_deg", "step_deg"):
            a, b = np.asarray(getattr(db, name)), np.asarray(getattr(single, name))[idx]
            bad |= ~((a == b) | (np.isnan(a) & np.isnan(b)))
        differ += int(np.count_nonzero(bad))
    return differ, single.grid.n_nodes


def probe(args: argparse.Namespace) -> int:
    """One tile (the largest terrain window) of the build at ``--probe-spacing``, in this process."""
    from appliance.atomic import write_text_atomic
    from appliance.terrain.horizon import DEFAULT_HEIGHT_M, DEFAULT_MAX_RANGE_M
    from appliance.terrain.mosaic import open_map
    from appliance.terrain.tiled import build_tile, plan_tiles

    tile_nodes = tuple(int(v) for v in args.tile_nodes.split(","))
    load_before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        source = open_map(TILES, Path(tmp) / "mosaic.vrt")
        dem = source.header()
        plan = plan_tiles(dem, None, args.probe_spacing, DEFAULT_MAX_RANGE_M, tile_nodes)  # type: ignore[arg-type]
        tile = max(plan.tiles, key=lambda t: t.terrain[2] * t.terrain[3])
        params = {"height_m": DEFAULT_HEIGHT_M, "n_azimuths": args.azimuths, "refraction": dem.body.refraction,
                  "max_range_m": DEFAULT_MAX_RANGE_M}
        res = build_tile(source, tmp, plan, tile, params)
    g = plan.cand
    lines = [
        f"# One tile of the {args.probe_spacing:g} m tiled build: a worker's peak memory",
        "",
        f"{date.today().isoformat()}, {platform.machine()}, `python bench/tiled_build.py --probe-spacing "
        f"{args.probe_spacing:g} --tile-nodes {args.tile_nodes} --azimuths {args.azimuths}`.",
        "",
        f"SRTM N43E006 + N43E007 on a transverse Mercator lattice of {args.probe_spacing:g} m: {g.n_rows} x "
        f"{g.n_cols} = {g.n_nodes:,} candidates in {len(plan.tiles)} tiles of {tile_nodes[0]} x {tile_nodes[1]}. "
        f"The tile with the largest terrain window ({tile.file}: {tile.terrain[2]} x {tile.terrain[3]} terrain "
        f"nodes, max range {DEFAULT_MAX_RANGE_M / 1000:.0f} km) built alone in one process: "
        f"**{res['seconds']:.0f} s, peak RSS {res['peak_rss_bytes'] / 2**20:.0f} MiB** (what one single-threaded "
        "worker needs).  The whole build was not run.",
        "",
        f"Load before: `{load_before}`",
        "",
    ]
    out = HERE / "results" / f"tiled_build_{args.probe_spacing:g}m.md"
    write_text_atomic(out, "\n".join(lines))
    print("\n".join(lines))
    return 0


def full(args: argparse.Namespace) -> int:
    """The whole tiled build at ``--full-spacing`` into ``--out`` on a local cluster; appended to the results."""
    from distributed import Client, LocalCluster

    from appliance.atomic import write_text_atomic
    from appliance.terrain.mosaic import open_map
    from appliance.terrain.tiled import build_tiled

    tile_nodes = tuple(int(v) for v in args.tile_nodes.split(","))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load_before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    started = time.perf_counter()

    def show(done: int, total: int, unit: str) -> None:
        print(f"{time.perf_counter() - started:7.0f} s  {done}/{total} {unit}", flush=True)

    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=50) as cluster, Client(cluster) as client:
        source = open_map(TILES, out / "mosaic.vrt")
        result = build_tiled(source, out, spacing_m=args.full_spacing, n_azimuths=args.azimuths,
                             tile_nodes=tile_nodes, client=client, progress=show)  # type: ignore[arg-type]
    wall = time.perf_counter() - started
    load_after = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    lat = result.index["lattice"]
    n_nodes = int(lat["n_rows"]) * int(lat["n_cols"])
    tile_bytes = sum((out / t["file"]).stat().st_size for t in result.index["tiles"])
    built_nodes = sum(t["n_rows"] * t["n_cols"] for t in result.index["tiles"] if t["file"] in result.built)
    rate = built_nodes / (wall * args.workers)
    lines = [
        "",
        f"## The whole {args.full_spacing:g} m build ({date.today().isoformat()}, {platform.machine()})",
        "",
        f"`python bench/tiled_build.py --full-spacing {args.full_spacing:g} --tile-nodes {args.tile_nodes} "
        f"--workers {args.workers} --azimuths {args.azimuths}`: SRTM N43E006 + N43E007, {lat['n_rows']} x "
        f"{lat['n_cols']} = {n_nodes:,} candidates ({lat['dx_m']:.1f} x {lat['dy_m']:.1f} m) in "
        f"{len(result.index['tiles'])} tiles, LocalCluster of {args.workers} single-threaded worker processes.",
        "",
        f"- tiles built in this run: {len(result.built)} ({built_nodes:,} candidates); kept from an earlier run: "
        f"{len(result.kept)}; wholly on nodata, left out: {len(result.void)}",
        f"- wall time: **{wall / 60:.1f} min**; {rate:,.0f} candidates per second per worker",
        f"- peak RSS of the largest worker: **{result.peak_rss_bytes / 2**20:.0f} MiB** (target 2 GB per worker)",
        f"- storage: {tile_bytes / 2**30:.1f} GiB in {len(result.index['tiles'])} tile files "
        f"({tile_bytes / max(n_nodes, 1):.0f} bytes per candidate, each tile's terrain window included)",
        "",
        f"Load before: `{load_before}`",
        "",
        f"Load after: `{load_after}`",
        "",
    ]
    res = HERE / "results" / f"tiled_build_{args.full_spacing:g}m.md"
    old = res.read_text() if res.exists() else ""
    write_text_atomic(res, old + "\n".join(lines))
    print("\n".join(lines))
    return 0


def main() -> int:
    from appliance.atomic import write_text_atomic

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tile-nodes", default="1201,1201")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--azimuths", type=int, default=360)
    ap.add_argument("--probe-spacing", type=float, help="build only the largest tile at this spacing (m)")
    ap.add_argument("--full-spacing", type=float, help="build the whole tiled database at this spacing (m)")
    ap.add_argument("--out", help="with --full-spacing: the database folder (kept; a rerun resumes)")
    args = ap.parse_args()
    if args.full_spacing:
        if not args.out:
            ap.error("--full-spacing needs --out")
        return full(args)
    if args.probe_spacing:
        return probe(args)
    tile_nodes = tuple(int(v) for v in args.tile_nodes.split(","))
    load_before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        ctx = multiprocessing.get_context("spawn")
        queue = ctx.Queue()
        proc = ctx.Process(target=_single, args=(tmp, args.azimuths, queue))
        proc.start()
        single_s, single_rss = queue.get()
        proc.join()
        print(f"single: {single_s:.1f} s, peak RSS {single_rss / 2**20:.0f} MiB", flush=True)

        from distributed import Client, LocalCluster

        from appliance.terrain.mosaic import open_map
        from appliance.terrain.tiled import build_tiled

        out = folder / "tiled"
        out.mkdir()
        t0 = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                          silence_logs=50) as cluster, Client(cluster) as client:
            source = open_map(TILES, out / "mosaic.vrt")
            result = build_tiled(source, out, n_azimuths=args.azimuths, tile_nodes=tile_nodes,  # type: ignore[arg-type]
                                 client=client)
            tiled_s = time.perf_counter() - t0
            control = _control(client, folder)
        print(f"tiled: {tiled_s:.1f} s, peak RSS per worker {result.peak_rss_bytes / 2**20:.0f} MiB", flush=True)
        differ, n_nodes = _differing_nodes(folder / "single.viperdb", out)
        lat = result.index["lattice"]
        tile_bytes = sum((out / t["file"]).stat().st_size for t in result.index["tiles"])
        single_bytes = (folder / "single.viperdb").stat().st_size
    load_after = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(f"differing nodes: {differ} of {n_nodes}; control: {control[0]} of {control[1]}")
    lines = [
        "# Tiled skyline database on Dask vs the single-process build",
        "",
        f"{date.today().isoformat()}, {platform.machine()}, `python bench/tiled_build.py --tile-nodes "
        f"{args.tile_nodes} --workers {args.workers} --azimuths {args.azimuths}`.",
        "",
        f"Map: SRTM N43E006 + N43E007 read as one VRT mosaic: {lat['n_rows']} x {lat['n_cols']} nodes "
        f"({lat['dx_m']:.1f} x {lat['dy_m']:.1f} m), {args.azimuths} azimuths, max range "
        f"{result.index['max_range_m'] / 1000:.0f} km; tiles of {tile_nodes[0]} x {tile_nodes[1]} nodes "
        f"({len(result.index['tiles'])} tiles), LocalCluster of {args.workers} single-threaded worker processes.",
        "",
        "| build | wall time (s) | peak RSS (MiB) | output (MiB) |",
        "|---|---|---|---|",
        f"| single process (2 threads) | {single_s:.1f} | {single_rss / 2**20:.0f} (the process) | "
        f"{single_bytes / 2**20:.0f} |",
        f"| tiled, {args.workers} workers | {tiled_s:.1f} | {result.peak_rss_bytes / 2**20:.0f} (the largest "
        f"worker) | {tile_bytes / 2**20:.0f} |",
        "",
        f"Nodes of the tiled database differing from the single build (codes, ranges, offset or step): "
        f"**{differ} of {n_nodes}**.",
        "",
        "Each tile reads the map under it plus the horizon's reach (and two cells), and the sweep cuts every "
        "node's horizon off at exactly the maximum range, so a tile node sees the same terrain as in the single "
        "build.  A node counts as differing when one azimuth's horizon changes, since that moves the node's "
        "offset and step and so every code.  Each tile file also holds its terrain window (the reach "
        "included), hence the larger output.",
        "",
        f"Control: the window {','.join(str(v) for v in CONTROL_BOUNDS)} (W,S,E,N) of the same mosaic, "
        f"{CONTROL_AZIMUTHS} azimuths, max range {CONTROL_RANGE_M / 1000:.0f} km (longer than the map, so every "
        f"tile's terrain window is the whole map, as the single build's is), {control[2]} tiles: "
        f"**{control[0]} of {control[1]}** nodes differ.",
        "",
        f"Load before: `{load_before}`",
        "",
        f"Load after: `{load_after}`",
        "",
        "The 30 m build's peak memory per worker: `--probe-spacing 30`, in tiled_build_30m.md.",
        "",
    ]
    res = HERE / "results" / "tiled_build.md"
    write_text_atomic(res, "\n".join(lines))
    print(f"wrote {res}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
