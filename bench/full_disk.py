"""20 runs on a full disk: ``viper capture``, ``viper daemon session``, ``viper estimate --report`` and
``viper replay``, 5 of each, each with the disk filling at a different byte offset.

Run: .venv/bin/python bench/full_disk.py [--per-command 5] [--after-flushes]
     (appends to bench/results/full_disk.md)

``--per-command N`` spreads N offsets per command over the same range (5: the fractions below);
``--after-flushes`` adds, for capture and the daemon, a run with the limit 25 bytes after each flush
of the log a run with room writes (where a log has just room for its data but not its closing records).

The full disk is RLIMIT_FSIZE in the command's process (a write past the limit fails with EFBIG, as
one on a full disk fails with ENOSPC).  The offsets are spread over the sizes of the files a run
with room writes (from a few bytes to most of the largest file), so the disk fills in each file in
turn.  After every run, every file under a final name in its output folder is opened with an
independent reader (the ``mcap`` stream reader from the magic to the footer and the closing magic,
CRCs checked: a log sealed when the disk filled is whole; rasterio, OpenCV, ``json``, ``csv``,
the HTML's closing tag): a file that is empty or does not read whole counts as left truncated.  A
run that failed (non-zero exit, or a write error named anywhere) counts as "not on stderr" if stderr
does not say so in one line, or if the error went to stdout, or if a traceback was printed.
Targets: 0 files left truncated or empty, every failure on stderr.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import numpy as np  # noqa: E402

from appliance.skyline import Skyline, write_skyline_csv  # noqa: E402
from appliance.terrain.dem import load_dem  # noqa: E402
from appliance.terrain.horizon import render_skyline  # noqa: E402
from bench.input_fuzz import _demo_seed  # noqa: E402
from bench.results_file import append_result  # noqa: E402

OUT = ROOT / "bench" / "results" / "full_disk.md"
NO_DEVICES = ('[platform]\nkind = "hardware"\n[devices.compass]\nkind = "nmea"\n'
              '[devices.inclinometer]\nkind = "nmea"\n')
ERRORS = ("File too large", "file too large", "No space left", "no space left", "disk full", "cannot write",
          "write failed")
FRACTIONS = (0.001, 0.05, 0.3, 0.6, 0.95)


def viper(args: list[str], cwd: Path, limit: int | None = None) -> subprocess.CompletedProcess[str]:
    def preexec() -> None:
        if limit is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run([sys.executable, "-m", "appliance.cli.main", *args], cwd=cwd, preexec_fn=preexec,
                          env=dict(os.environ, PYTHONPATH=str(ROOT), VIPER_SOCKET=""), capture_output=True,
                          text=True, timeout=600, check=False)


def whole(path: Path) -> bool:
    """Whether ``path`` is non-empty and reads whole with a reader of its format."""
    if path.stat().st_size == 0:
        return False
    try:
        if path.suffix == ".mcap":  # from its magic to its footer and closing magic, every CRC checked
            from mcap.stream_reader import StreamReader

            with open(path, "rb") as f:
                for _ in StreamReader(f, validate_crcs=True).records:
                    pass
        elif path.suffix == ".tif":
            import rasterio

            with rasterio.open(path) as ds:
                ds.read()
        elif path.suffix == ".png":
            import cv2

            return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None
        elif path.suffix == ".geojson":
            json.loads(path.read_text())
        elif path.suffix == ".csv":
            list(csv.reader(io.StringIO(path.read_text())))
        elif path.suffix == ".html":
            return path.read_text().rstrip().endswith("</html>")
    except Exception:  # noqa: BLE001 - whatever the reader raises, the file is not whole
        return False
    return True


def final_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(".")] if folder.is_dir() else []


def judge(r: subprocess.CompletedProcess[str], out: Path) -> tuple[list[str], bool, str]:
    """The files left truncated or empty, whether a failure was not (only) on stderr, and the stderr line."""
    bad = [str(p.relative_to(out.parent)) for p in final_files(out) if not whole(p)]
    failed = r.returncode != 0 or any(e in r.stdout + r.stderr for e in ERRORS)
    lines = r.stderr.strip().splitlines()
    said = bool(lines) and "Traceback" not in r.stderr and not any(e in r.stdout for e in ERRORS)
    return bad, failed and not said, (lines[-1] if lines else "")[:140]


def cases(work: Path) -> dict[str, tuple[list[str], Path]]:
    """Each command's arguments (into ``out``) and the folder of its outputs, after one run with room."""
    # a small reserve beside the log, so that most offsets fall in the log itself
    (work / "viper.toml").write_text(NO_DEVICES + "[logbook]\nreserve_bytes = 1024\n")
    (work / "daemon.toml").write_text(NO_DEVICES + "[logbook]\nreserve_bytes = 1024\n"
                                      "[session]\ninterval_s = 0.1\nmax_sessions = 3\n")
    log, db = _demo_seed()
    shutil.copy(log, work / "s.mcap")
    el = render_skyline(load_dem("jacksboro"), 36.5731, -84.2687).elevation_deg
    write_skyline_csv(Skyline(np.arange(360.0), el), work / "a.csv")
    return {
        "capture": (["capture", "--config", "viper.toml", "--log-dir", "{out}"], work),
        "daemon": (["daemon", "session", "--config", "daemon.toml", "--log-dir", "{out}"], work),
        "estimate --report": (["estimate", str(db), "a.csv", "--report", "{out}"], work),
        "replay": (["replay", "s.mcap", "--db", str(db), "--out", "{out}"], work),
    }


def flush_ends(log: Path) -> list[int]:
    """Where each flush of ``log`` ended: the offsets after each chunk's message index records."""
    from mcap.records import Chunk, DataEnd, MessageIndex
    from mcap.stream_reader import StreamReader

    ends, pos, last = [], 0, None
    with open(log, "rb") as f:
        for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
            if isinstance(last, (Chunk, MessageIndex)) and not isinstance(record, MessageIndex):
                ends.append(pos)
            if isinstance(record, DataEnd):
                break
            last, pos = record, f.tell()
    return ends


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-command", type=int, default=len(FRACTIONS), help="offsets per command")
    ap.add_argument("--after-flushes", action="store_true",
                    help="for capture and the daemon, also a limit 25 bytes after each flush of the log")
    opts = ap.parse_args()
    fractions = (FRACTIONS if opts.per_command == len(FRACTIONS)
                 else tuple(float(f) for f in np.geomspace(0.001, 0.95, opts.per_command)))
    rows, totals = [], {"runs": 0, "truncated": 0, "not_on_stderr": 0}
    with tempfile.TemporaryDirectory(prefix="viper-full-disk-") as tmp:
        work = Path(tmp)
        for name, (args, cwd) in cases(work).items():
            tag = name.split()[0]
            free = viper([a.replace("{out}", f"{tag}-free") for a in args], cwd)
            largest = max((p.stat().st_size for p in final_files(cwd / f"{tag}-free")), default=0)
            limits = [max(1, int(largest * fraction)) for fraction in fractions]
            logs = sorted((cwd / f"{tag}-free").glob("viper-*.mcap"))
            if opts.after_flushes and logs:
                limits += [end + 25 for end in flush_ends(logs[0])]
            for k, limit in enumerate(limits):
                out = cwd / f"{tag}-{k}"
                r = viper([a.replace("{out}", out.name) for a in args], cwd, limit)
                bad, unsaid, line = judge(r, out)
                totals["runs"] += 1
                totals["truncated"] += len(bad)
                totals["not_on_stderr"] += unsaid
                rows.append(f"| {name} | {limit} | {r.returncode} | {len(final_files(out))} | {len(bad)} | "
                            f"{'no' if unsaid else 'yes'} | {line.replace('|', '/')} |")
                print(rows[-1], flush=True)
            print(f"{name}: with room exit {free.returncode}, largest file {largest} bytes", flush=True)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = ("# Full disk: capture, daemon, estimate --report, replay\n\n"
              "Written by `bench/full_disk.py`; the disk fills at the byte offset in column 2 (RLIMIT_FSIZE).\n")
    load = os.getloadavg()[0]
    how = f"--per-command {opts.per_command}{' --after-flushes' if opts.after_flushes else ''}"
    text = (f"\n## {stamp}\n\n`{how}`, load average {load:.1f} on {os.cpu_count()} CPUs.\n\n"
            f"{totals['runs']} runs: {totals['truncated']} files left truncated or empty under a "
            f"final name, {totals['not_on_stderr']} failures not on stderr (targets: 0 and 0)\n\n"
            "| command | limit (bytes) | exit | files left | truncated or empty | failure on stderr "
            "| last stderr line |\n"
            "|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
    append_result(OUT, header, text)
    print(text)
    return 0 if totals["truncated"] == totals["not_on_stderr"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
