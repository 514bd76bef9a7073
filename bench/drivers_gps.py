"""Driver benchmarks: NMEA decode throughput on the real gpsd logs, PTU command round trip over a pty.

Run: .venv/bin/python bench/drivers_gps.py     (writes bench/results/drivers_gps.md)
Throughput: all logs in ../shared/data/nmea_gps concatenated, framed and decoded into fixes, best of 5.
Target: far above a 115200-baud port's 11.5 kB/s, so one core decodes many receivers in real time.
"""

from __future__ import annotations

import datetime
import logging
import sys
import tempfile
import time
from pathlib import Path

from appliance.atomic import write_text_atomic
from appliance.drivers.gps import GpsDecoder
from appliance.drivers.nmea_framer import NmeaFramer
from appliance.drivers.policy import ErrorPolicy
from appliance.drivers.ptu import PanTiltUnit
from appliance.drivers.transport import open_serial
from appliance.sim.ptu_twin import PtuTwin
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimClock, SimWorld

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "nmea_gps"
OUT = ROOT / "bench" / "results" / "drivers_gps.md"


def decode_all(blob: bytes) -> int:
    fr, dec = NmeaFramer(), GpsDecoder(ErrorPolicy.SKIP)
    fixes = dec.feed(fr.feed(blob, 0)) + dec.feed(fr.flush(0)) + dec.flush()
    return len(fixes)


def main() -> int:
    logging.basicConfig(level=logging.ERROR)
    logs = sorted(DATA.glob("*.log"))
    if not logs:
        print(f"no logs in {DATA}", file=sys.stderr)
        return 1
    blob = b"".join(b"".join(ln for ln in p.read_bytes().splitlines(True) if not ln.startswith(b"#")) for p in logs)
    best = float("inf")
    fixes = 0
    for _ in range(5):
        t0 = time.perf_counter()
        fixes = decode_all(blob)
        best = min(best, time.perf_counter() - t0)
    rate = len(blob) / best
    print(f"decode: {len(blob)} bytes, {fixes} fixes in {best * 1e3:.1f} ms = {rate / 1e6:.2f} MB/s")

    world = SimWorld(36.6, -84.25, 500.0, clock=SimClock(datetime.datetime(2026, 6, 1, tzinfo=datetime.timezone.utc)))
    with tempfile.TemporaryDirectory() as tmp:
        port = PtyPort(Path(tmp) / "ptu")
        twin = PtuTwin(world, port)
        twin.start()
        unit = PanTiltUnit(open_serial(str(port.path), 9600, 0.05))
        n = 200
        t0 = time.perf_counter()
        for i in range(n):
            if i % 20 == 0:
                unit.command(f"PP{i}")  # interleaved moves: each answer must be the current position
            assert unit.position() == i - i % 20
        rtt = (time.perf_counter() - t0) / n
        unit.close()
        twin.stop()
        port.close()
    print(f"PTU query round trip over a pty: {rtt * 1e3:.2f} ms")

    OUT.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(
        OUT,
        "# Driver benchmarks\n\n"
        f"{datetime.date.today().isoformat()}, 2 cores (shared with other jobs: times vary), "
        "`bench/drivers_gps.py`.\n\n"
        "| figure | measured | target |\n|---|---|---|\n"
        f"| NMEA framing + decoding, {len(logs)} gpsd logs ({len(blob)} bytes, {fixes} fixes) | "
        f"{rate / 1e6:.2f} MB/s | >= 1.15 MB/s (100 x a 115200-baud port) |\n"
        f"| PTU position query round trip (pty twin) | {rtt * 1e3:.2f} ms | <= 20 ms |\n",
    )
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
