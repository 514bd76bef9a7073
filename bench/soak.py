"""Soak: ``viper daemon session`` through many simulated sessions in accelerated time, with the logs
capped at ``max_total_bytes`` = a number of logs' worth.

Run: .venv/bin/python bench/soak.py [--sessions 300] [--cap-logs 20] [--minutes 25]
(appends to bench/results/soak.md; ``--minutes`` ends the run with SIGTERM when the time is up)

The daemon runs as the service does, a process of its own with ``$NOTIFY_SOCKET``; this script
listens on that socket and, at every session's closing STATUS (sent after the retention's pass that
follows the session), reads the daemon's /proc/PID/status (VmRSS, Threads) and /proc/PID/fd, the
bytes of the logs in the folder (the logs and their reserve files, what the cap counts) and checks
that the log the session just wrote is there and complete.  A thread samples the logs' bytes every
20 ms besides, for the peak while a session writes.  At the end every log left is read from its
magic to its footer (CRCs checked) and its summary read back.

The sessions are made cheap: a generated 8 x 8 DEM of 1 km cells (the simulated camera renders
the DEM's skyline for every frame; on the embedded map a frame takes seconds), frames of 64 x 48
pixels, 8 compass steps, 2 s of GPS truth, the simulated clock 200 times real time; no skyline
database, so the estimate is skipped (the session is "degraded") and the logs are real logs of
everything else.  ``--no-camera`` unplugs the camera from the start (no frames: the short test).
"""

from __future__ import annotations

import argparse
import datetime
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from appliance.acquisition.retention import is_complete, logs_total_bytes  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402

OUT = ROOT / "bench" / "results" / "soak.md"
LAT, LON = 36.6, -84.25


def write_dem(path: Path) -> None:
    """An 8 x 8 DEM of 0.01 deg cells around (LAT, LON), heights 400-460 m."""
    import numpy as np
    import rasterio
    from rasterio.transform import Affine

    z = (400 + 60 * np.random.default_rng(0).random((8, 8))).astype("float32")
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=1, dtype="float32", crs="EPSG:4326",
                       transform=Affine(0.01, 0.0, LON - 0.04, 0.0, -0.01, LAT + 0.04)) as ds:
        ds.write(z, 1)


def config_text(dem: Path, log_dir: Path, sessions: int, cap_bytes: int, camera: bool, time_rate: float = 200.0,
                truth_s: float = 2.0) -> str:
    """The soak's configuration (see the module's description)."""
    return (f'[platform]\nkind = "sim"\n'
            f'[logbook]\nlog_dir = "{log_dir}"\nreserve_bytes = 4096\nmax_total_bytes = {cap_bytes}\n'
            f"[session]\ninterval_s = 0.05\nmax_sessions = {sessions}\nlevel_poll_s = 0.05\ncompass_steps = 8\n"
            f"truth_duration_s = {truth_s}\ntruth_min_fixes = 1\nsettle_s = 0.0\ncapture_overlap = 0.0\n"
            "[devices.camera]\nwidth = 64\nheight = 48\nflush_frames = 0\n"
            f'[sim]\ndem = "{dem}"\nlat_deg = {LAT}\nlon_deg = {LON}\ntime_rate = {time_rate}\ngps_rate_hz = 5.0\n'
            + ("" if camera else "[sim.faults]\ncamera_unplug_after = 0\n"))


@dataclass
class Row:
    n: int
    t_s: float
    rss_kib: int
    fds: int
    threads: int
    logs_bytes: int
    logs: int
    name: str
    present: bool


@dataclass
class Soak:
    rows: list[Row] = field(default_factory=list)
    peak_bytes: int = 0
    removed: list[str] = field(default_factory=list)
    incomplete_left: list[str] = field(default_factory=list)
    left: int = 0
    exit_code: int | None = None
    wall_s: float = 0.0
    stderr_tail: str = ""
    no_room: int = 0


def proc_status(pid: int) -> tuple[int, int, int]:
    """(VmRSS KiB, threads, open fds) of process ``pid``."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        fields[key] = value.strip()
    return int(fields["VmRSS"].split()[0]), int(fields["Threads"]), len(os.listdir(f"/proc/{pid}/fd"))


def whole(path: Path) -> bool:
    """``path`` read from its magic to its footer with CRCs checked, and its summary read back."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as f:
            for _ in StreamReader(f, validate_crcs=True).records:
                pass
        with open(path, "rb") as f:
            return make_reader(f).get_summary() is not None
    except Exception:  # noqa: BLE001 - whatever the reader raises, the log is not whole
        return False


def run_soak(work: Path, sessions: int, cap_bytes: int, minutes: float, camera: bool = True,
             verbose: bool = False) -> Soak:
    """The daemon through ``sessions`` sessions with the logs capped at ``cap_bytes`` (see the module)."""
    dem, logs = work / "dem.tif", work / "logs"
    if not dem.exists():
        write_dem(dem)
    (work / "soak.toml").write_text(config_text(dem, logs, sessions, cap_bytes, camera))
    sock_path = work / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.settimeout(1.0)
    out = Soak()
    done = threading.Event()

    def sample_peak() -> None:
        while not done.wait(0.02):
            if logs.is_dir():
                out.peak_bytes = max(out.peak_bytes, logs_total_bytes(logs))

    sampler = threading.Thread(target=sample_peak, daemon=True)
    sampler.start()
    err_path = work / "daemon.stderr"
    env = dict(os.environ, PYTHONPATH=str(ROOT), NOTIFY_SOCKET=str(sock_path), VIPER_SOCKET="")
    start = time.monotonic()
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "appliance.cli.main", "daemon", "session", "--config",
                                 str(work / "soak.toml")], stdout=subprocess.DEVNULL, stderr=err, env=env)
    try:
        while proc.poll() is None:
            if time.monotonic() - start > minutes * 60.0:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=300)
                break
            try:
                msg = sock.recv(65536).decode()
            except TimeoutError:
                continue
            status = next((ln[7:] for ln in msg.splitlines() if ln.startswith("STATUS=")), "")
            words = status.split()
            if "not started" in status:
                out.no_room += 1
            if len(words) > 2 and words[0] == "session" and words[2] in ("ok", "degraded", "failed", "ambiguous"):
                name = status.rsplit(": ", 1)[-1]
                rss, threads, fds = proc_status(proc.pid)
                path = logs / name
                present = path.exists() and is_complete(path)
                out.rows.append(Row(int(words[1]), time.monotonic() - start, rss, threads, fds,
                                    logs_total_bytes(logs), len(list(logs.glob("viper-*.mcap"))), name, present))
                if verbose:
                    print(f"session {words[1]}: {out.rows[-1]}", flush=True)
        out.exit_code = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
        done.set()
        sampler.join()
        sock.close()
    out.wall_s = time.monotonic() - start
    err_text = err_path.read_text()
    out.removed = [ln.split("removed ", 1)[1].split(" (", 1)[0] for ln in err_text.splitlines()
                   if "retention: removed" in ln]
    out.stderr_tail = "\n".join(err_text.strip().splitlines()[-3:])
    left = sorted(logs.glob("viper-*.mcap"))
    out.left = len(left)
    out.incomplete_left = [p.name for p in left if not whole(p)]
    return out


def log_size(work: Path, camera: bool, sessions: int = 2) -> int:
    """The largest log of ``sessions`` sessions without a cap."""
    s = run_soak(work, sessions, 0, 10.0, camera)
    sizes = [p.stat().st_size for p in (work / "logs").glob("viper-*.mcap")]
    if s.exit_code != 0 or not sizes:
        raise SystemExit(f"the sizing run failed (exit {s.exit_code}): {s.stderr_tail}")
    (work / "notify.sock").unlink()
    for p in (work / "logs").iterdir():
        p.unlink()
    return max(sizes)


def mean(values: list[int]) -> float:
    return sum(values) / len(values)


def report(s: Soak, sessions: int, cap_logs: int, cap_bytes: int, one_log: int, command: str,
           commit: str = "") -> tuple[str, bool]:
    rows = s.rows
    n = len(rows)
    if not rows:
        return f"\nCommand: `{command}`: no session ended (daemon exit {s.exit_code}): {s.stderr_tail}\n", False
    warm = rows[max(1, n // 10): max(2, n // 5)] or rows[:1]
    end = rows[-max(1, n // 10):]
    rss_growth = 100.0 * (mean([r.rss_kib for r in end]) / mean([r.rss_kib for r in warm]) - 1.0)
    fds = sorted({r.fds for r in rows[1:]} or {0})
    threads = sorted({r.threads for r in rows[1:]} or {0})
    missing = [r.name for r in rows if not r.present]
    over = max((r.logs_bytes for r in rows), default=0)
    per_session = (rows[-1].t_s - rows[0].t_s) / (n - 1) if n > 1 else float("nan")
    checks = {
        "disk never above the cap (peak of 20 ms samples)": s.peak_bytes <= cap_bytes,
        "RSS growth < 5 % (warm-up window against the last tenth)": rss_growth < 5.0,
        "open fds flat after the first session": len(fds) == 1,
        "threads flat after the first session": len(threads) == 1,
        "0 incomplete logs left": not s.incomplete_left,
        "every session's own log there and complete when it ended": not missing,
        f"{sessions} sessions run": n >= sessions,
    }
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"\n## {stamp} (commit {commit or checkout_commit(ROOT)}, {os.cpu_count()} CPUs, load "
             f"{os.getloadavg()[0]:.1f} at the end)\n",
             f"Command: `{command}`\n",
             f"{n} sessions in {s.wall_s / 60:.1f} min ({per_session:.1f} s per session with the daemon's "
             f"interval of 0.05 s); daemon exit {s.exit_code}; one log {one_log} bytes, cap {cap_logs} logs = "
             f"{cap_bytes} bytes; {len(s.removed)} logs removed by retention, {s.left} left; "
             f"{s.no_room} sessions refused for want of room.\n",
             "| measure | value |", "|---|---|",
             f"| logs' bytes at session ends: max | {over} |",
             f"| logs' bytes, peak of 20 ms samples | {s.peak_bytes} (cap {cap_bytes}) |",
             f"| RSS: first session / warm-up window / last tenth (KiB) | {rows[0].rss_kib} / "
             f"{mean([r.rss_kib for r in warm]):.0f} / {mean([r.rss_kib for r in end]):.0f} |",
             f"| RSS growth, warm-up window to the last tenth | {rss_growth:+.2f} % |",
             f"| open fds after session 1 / distinct values after | {rows[0].fds if rows else '-'} / {fds} |",
             f"| threads after session 1 / distinct values after | {rows[0].threads if rows else '-'} / {threads} |",
             f"| logs left incomplete | {len(s.incomplete_left)} {s.incomplete_left[:3]} |",
             f"| sessions whose own log was missing or incomplete at its end | {len(missing)} |",
             "", "| target | met |", "|---|---|"]
    lines += [f"| {k} | {'yes' if v else 'NO'} |" for k, v in checks.items()]
    sample = rows[:: max(1, n // 12)]
    sample += [r for r in rows[-1:] if r not in sample]
    lines += ["", "| session | t (s) | RSS (KiB) | fds | threads | logs' bytes | logs |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {r.n} | {r.t_s:.0f} | {r.rss_kib} | {r.fds} | {r.threads} | {r.logs_bytes} | {r.logs} |"
              for r in sample]
    return "\n".join(lines) + "\n", all(checks.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sessions", type=int, default=300)
    ap.add_argument("--cap-logs", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=25.0, help="end the run with SIGTERM after this long")
    ap.add_argument("--no-camera", action="store_true", help="no frames (the camera unplugged from the start)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    command = "python bench/soak.py " + " ".join(sys.argv[1:] if argv is None else argv)
    commit = checkout_commit(ROOT)  # the code the daemon runs, before anything changes during the run
    with tempfile.TemporaryDirectory(prefix="viper-soak-") as tmp:
        work = Path(tmp)
        one_log = log_size(work, not args.no_camera)
        cap = args.cap_logs * one_log
        s = run_soak(work, args.sessions, cap, args.minutes, not args.no_camera, verbose=True)
    text, ok = report(s, args.sessions, args.cap_logs, cap, one_log, command, commit)
    header = ("# Soak: the session daemon through hundreds of simulated sessions, logs capped\n\n"
              "Written by `bench/soak.py` (its docstring says what is measured and how).\n")
    append_result(args.out, header, text)
    print(text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
