"""The tiled database's file format: one memory-mapped database per tile against a Zarr store.

What a tiled search reads of one tile, each way, with the page cache warm (the tile searched before):
open it, read the first pass's arrays of every node (box-averaged codes, their gaps, parallax
variances, offsets and steps), then the full skylines (codes and ranges) of the few hundred nodes the
rescoring keeps.  Reported: the median time of each over alternating rounds, the memory each adds to
the process that is its own (anonymous; a mapped file's pages are the page cache's, shared by every
process that maps the tile), and the storage.

The Zarr store holds the same arrays in chunks of CHUNK_ROWS nodes, with Zarr's default codec.  Zarr is
not a dependency of the appliance; this bench needs it installed beside it (``pip install zarr``).

    python bench/tiled_format.py [--db bench/cache/n44w072-full.viperdb] [--rounds 5]
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

#: what a search reads of every node, and what it reads of the rescored nodes only
FIRST_PASS = ("coarse_codes", "coarse_partial", "coarse_tau2", "offset_deg", "step_deg")
RESCORED = ("codes", "distance_codes")
CHUNK_ROWS = 65536
RESCORED_NODES = 500


def rss_anon_bytes() -> int:
    """This process's anonymous resident memory (what is its own, not file pages)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) * 1024
    return 0


def checksum(a: np.ndarray) -> float:
    """The sum of an array's finite values, a block of rows at a time (no temporary of its size)."""
    total = 0.0
    for r0 in range(0, a.shape[0], CHUNK_ROWS):
        b = np.asarray(a[r0 : r0 + CHUNK_ROWS])
        total += float(np.sum(np.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0), dtype=np.float64)
                       if b.dtype.kind == "f" else np.sum(b, dtype=np.int64))
    return total


def read_mapped(path: Path, rows: np.ndarray) -> tuple[int, float]:
    """Open the database, read its first-pass arrays and the rescored rows; a checksum of what was read."""
    from appliance.terrain.database import load_database

    db = load_database(path)
    total = 0.0
    for name in FIRST_PASS:
        total += checksum(np.asarray(getattr(db, name)))
    for name in RESCORED:
        total += checksum(np.asarray(getattr(db, name))[rows])
    return 0, total


def read_zarr(store: Path, rows: np.ndarray) -> tuple[int, float]:
    import zarr

    g = zarr.open_group(str(store), mode="r")
    held = 0
    total = 0.0
    for name in FIRST_PASS:
        a = g[name][...]
        held += a.nbytes
        total += checksum(a)
    for name in RESCORED:
        a = g[name].oindex[rows, :]
        held += a.nbytes
        total += checksum(a)
    return held, total


def main() -> int:
    from appliance.atomic import write_text_atomic
    from appliance.terrain.database import load_database

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--db", default=str(HERE / "cache" / "n44w072-full.viperdb"))
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    try:
        import zarr
    except ImportError:
        print("this bench needs zarr (pip install zarr); it is not a dependency of the appliance", file=sys.stderr)
        return 2
    path = Path(args.db)
    if not path.is_file():
        print(f"{path}: no such database (bench/estimator_speed.py builds it)", file=sys.stderr)
        return 2
    db = load_database(path)
    n = db.codes.shape[0]
    # the rescored nodes lie together around the answer: a block of about RESCORED_NODES nodes
    n_cols = db.grid.n_cols
    side = int(np.ceil(np.sqrt(RESCORED_NODES)))
    r0, c0 = db.grid.n_rows // 3, n_cols // 3
    rows = ((np.arange(r0, r0 + side)[:, None]) * n_cols + np.arange(c0, c0 + side)[None, :]).ravel()
    load_before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        store = Path(tmp) / "tile.zarr"
        g = zarr.open_group(str(store), mode="w")
        for name in FIRST_PASS + RESCORED:
            a = np.asarray(getattr(db, name))
            chunks = (min(CHUNK_ROWS, a.shape[0]),) + a.shape[1:]
            g.create_array(name, shape=a.shape, dtype=a.dtype, chunks=chunks)[...] = a
        del db
        zarr_bytes = sum(p.stat().st_size for p in store.rglob("*") if p.is_file())
        arrays_bytes = 0
        db = load_database(path)
        for name in FIRST_PASS + RESCORED:
            arrays_bytes += np.asarray(getattr(db, name)).nbytes
        del db
        ref_m, ref_z = read_mapped(path, rows)[1], read_zarr(store, rows)[1]
        if ref_m != ref_z:
            print(f"the two formats read different values ({ref_m} vs {ref_z})", file=sys.stderr)
            return 1
        times: dict[str, list[float]] = {"mapped": [], "zarr": []}
        held = {"mapped": 0, "zarr": 0}
        for _ in range(args.rounds):
            for name, fn, src in (("mapped", read_mapped, path), ("zarr", read_zarr, store)):
                before = rss_anon_bytes()
                t = time.perf_counter()
                own, _ = fn(src, rows)
                times[name].append(time.perf_counter() - t)
                held[name] = max(held[name], own, rss_anon_bytes() - before)
    load_after = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    med = {k: float(np.median(v)) for k, v in times.items()}
    lines = [
        "# The tiled database's format: a memory-mapped database per tile against Zarr (bench/tiled_format.py)",
        "",
        f"{date.today().isoformat()}, {platform.machine()}, `python bench/tiled_format.py --db {path.name} --rounds "
        f"{args.rounds}`, zarr {zarr.__version__} (default codec, chunks of {CHUNK_ROWS:,} nodes).",
        "",
        f"One tile of {n:,} nodes: open it, read the first pass's arrays of every node ({', '.join(FIRST_PASS)}) "
        f"and the full skylines ({', '.join(RESCORED)}) of a block of {rows.size} nodes (the rescored nodes lie "
        "together around the answer), page cache warm, {args.rounds} rounds in alternation.",
        "",
        "| format | time (median) | memory of its own | storage of these arrays |",
        "|---|---|---|---|",
        f"| database file, memory-mapped | {med['mapped'] * 1e3:.0f} ms | {held['mapped'] / 2**20:.0f} MiB | "
        f"{arrays_bytes / 2**20:.0f} MiB |",
        f"| Zarr | {med['zarr'] * 1e3:.0f} ms | {held['zarr'] / 2**20:.0f} MiB | {zarr_bytes / 2**20:.0f} MiB |",
        "",
        f"Load before: `{load_before}`",
        "",
        f"Load after: `{load_after}`",
        "",
    ]
    out = HERE / "results" / "tiled_format.md"
    old = out.read_text() if out.exists() else ""
    write_text_atomic(out, (old + "\n" if old else "") + "\n".join(lines if not old else lines[2:]))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
