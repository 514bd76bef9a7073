"""The live view seen by an independent client over whole `viper capture --live` runs.

For each run: a strict WebSocket client (tests/live_client.py: it subscribes once to each channel as
it is advertised, never again) starts connecting before the command starts and connects as soon as
the port opens; then ``viper capture --config CONFIG --seed N --live 127.0.0.1:PORT`` runs on the
simulated platform to its end.  The session's MCAP log, read back by the ``mcap`` reader, against what
the client received: per topic, messages in the log and received, refused subscriptions ("Unknown
channel ID" statuses), messages received twice.

Target: every message of the log received once, except at most the first sample of a raw sensor
topic (sent before the subscription completed); 0 refused subscriptions.

    python bench/live_view.py [--runs 20] [--config examples/sim.toml] [--quick] [--work DIR] [--code DIR]

--quick shortens the session as the tests do (GPS averaging 10 s, settling 0.2 s, a 320x240 camera);
--work keeps the simulated platform's skyline database (built on the first run) between invocations;
--code runs another checkout's ``viper`` (to measure a version before a change).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from datetime import date
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from mcap.reader import make_reader  # noqa: E402

from appliance.atomic import write_text_atomic  # noqa: E402
from appliance.logbook import topics as t  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402
from tests.live_client import StrictClient  # noqa: E402

RESULTS = HERE / "results" / "live_view.md"
#: the topics whose first sample may be sent before a client's subscription completes
RAW_SENSOR_TOPICS = (t.GPS_FIX, t.HEADING_RAW, t.TILT_RAW, t.STAGE_RAW, t.IMAGE)
QUICK = {"session": {"truth_duration_s": "10.0", "settle_s": "0.2"},
         "devices.camera": {"width": "320", "height": "240"}}


def quick_config(config: Path, folder: Path) -> Path:
    """``config`` with the :data:`QUICK` keys replaced (each table must already hold the key)."""
    lines, table = [], ""
    for line in config.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("["):
            table = stripped.strip("[]").split("]")[0]
        key = stripped.split("=", 1)[0].strip()
        if "=" in stripped and not stripped.startswith("#") and key in QUICK.get(table, {}):
            line = f"{key} = {QUICK[table][key]}"
        lines.append(line)
    out = folder / "quick.toml"
    write_text_atomic(out, "\n".join(lines) + "\n")
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def log_payloads(path: str) -> dict[str, list[bytes]]:
    payloads: dict[str, list[bytes]] = {}
    with open(path, "rb") as f:
        for _s, channel, message in make_reader(f).iter_messages(log_time_order=False):
            payloads.setdefault(channel.topic, []).append(bytes(message.data))
    return payloads


def one_run(seed: int, config: Path, work: Path, code: Path) -> dict:
    port = free_port()
    client = StrictClient(port, connect_timeout_s=600.0)
    client.start()  # connecting (refused) until the command's server listens
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "appliance.cli.main", "capture", "--config", str(config), "--log-dir", str(work),
         "--seed", str(seed), "--live", f"127.0.0.1:{port}"],
        cwd=work, env=dict(os.environ, PYTHONPATH=str(code)), capture_output=True, text=True, timeout=3600,
        check=False)
    wall_s = time.monotonic() - started
    client.closed.wait(10.0)
    client.finish()
    log_path = next((x[5:] for x in proc.stdout.splitlines() if x.startswith("log: ")), None)
    if log_path is None:
        raise SystemExit(f"run {seed}: no log (exit {proc.returncode}): {proc.stderr.strip()[-400:]}")
    logged = log_payloads(log_path)
    received: dict[str, list[bytes]] = {}
    for topic, _, data in client.messages:
        received.setdefault(topic, []).append(data)
    return {"seed": seed, "wall_s": wall_s, "exit": proc.returncode, "logged": logged, "received": received,
            "refused": len(client.refused()), "connected": client.server_info != {},
            "error": repr(client.error) if client.error else "",
            "stderr_lines": len(proc.stderr.splitlines())}


def verdict(run: dict) -> tuple[bool, list[str]]:
    """Whether ``run`` meets the target, and what it missed (topic: received/logged, and why)."""
    notes = []
    for topic in sorted(set(run["logged"]) | set(run["received"])):
        logged, got = run["logged"].get(topic, []), run["received"].get(topic, [])
        if got == logged:
            continue
        if topic in RAW_SENSOR_TOPICS and got == logged[1:]:
            notes.append(f"{topic} {len(got)}/{len(logged)} (first sample)")
            continue
        dup = sum((Counter(got) - Counter(logged)).values())
        notes.append(f"{topic} {len(got)}/{len(logged)}" + (f" ({dup} twice)" if dup else " (MISSED)"))
    ok = run["refused"] == 0 and all(n.endswith("(first sample)") for n in notes)
    return ok, notes


def row(run: dict) -> str:
    ok, notes = verdict(run)
    logged = sum(len(v) for v in run["logged"].values())
    received = sum(len(v) for v in run["received"].values())
    per_topic = ", ".join(f"{tp} {len(run['received'].get(tp, []))}/{len(v)}"
                          for tp, v in sorted(run["logged"].items()))
    return (f"| {run['seed']} | {run['wall_s']:.0f} | {run['exit']} | {logged} | {received} | {run['refused']} | "
            f"{'; '.join(notes) or 'all'} | {'yes' if ok else 'NO'} | {per_topic} |\n")


HEADER = """# The live view seen by an independent client (bench/live_view.py)

Each run: `viper capture --live 127.0.0.1:PORT` on the simulated platform, a strict client
(tests/live_client.py: one subscription per advertised channel, never repeated) connecting as soon as
the port opens; the session's MCAP log (mcap reader) against what the client received.  Target: every
message of the log received once, except at most the first sample of a raw sensor topic
(/gps/fix, /heading/raw, /tilt/raw, /stage/raw, /camera/image); 0 refused subscriptions.
Columns: wall time of the command (s), its exit status, messages in the log, received, refused
subscriptions, the topics not received exactly (received/logged), target met, and received/logged per
topic.

"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--config", type=Path, default=HERE.parent / "examples" / "sim.toml")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--work", type=Path, help="folder for the logs and the simulated database (default: temporary)")
    ap.add_argument("--code", type=Path, default=HERE.parent, help="the checkout whose viper runs")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--note", default="")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = (args.work or Path(tmp)).resolve()
        work.mkdir(parents=True, exist_ok=True)
        config = quick_config(args.config.resolve(), Path(tmp)) if args.quick else args.config.resolve()
        commit = checkout_commit(args.code)
        load = os.getloadavg()[0]
        append_result(args.out, HEADER,
                      f"\n## {date.today().isoformat()}: {args.runs} runs at {commit}, config {args.config.name}"
                      f"{' --quick' if args.quick else ''}, {os.cpu_count()} cores, load {load:.1f} at start"
                      f"{'; ' + args.note if args.note else ''}\n\n"
                      "| seed | wall (s) | exit | logged | received | refused | not exact | target | per topic |\n"
                      "|---|---|---|---|---|---|---|---|---|\n")
        met = 0
        for seed in range(args.first_seed, args.first_seed + args.runs):
            run = one_run(seed, config, work, args.code.resolve())
            met += verdict(run)[0]
            append_result(args.out, HEADER, row(run))
            print(row(run), end="", flush=True)
        append_result(args.out, HEADER, f"\nTarget met in {met} of {args.runs} runs.\n")
        print(f"target met in {met} of {args.runs} runs")
    return 0 if met == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
