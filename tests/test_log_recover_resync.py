"""``viper log recover`` on a log with a corrupt stretch in the middle: it resynchronises on the next
valid record and keeps everything after it.  The logs are written by the appliance's Logbook; the
recovered files are opened with the independent ``mcap`` reader."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from appliance.logbook import Logbook
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import CLOSING_BYTES

T0 = 1_700_000_000_000_000_000
REPO = Path(__file__).resolve().parents[1]
N = 92


def write_log(path: Path) -> list[int]:
    """N GPS fixes and a tilt message every third, one chunk per flush; the log's length after each (the
    file holds the room for its closing records beyond it)."""
    sizes = []
    with Logbook.create(path, reserve_bytes=0) as lb:
        for i in range(N):
            lb.write_proto(t.GPS_FIX, m.location_fix(T0 + i, 33.0 + i * 1e-6, -97.0), T0 + i)
            if i % 3 == 0:
                lb.write_json(t.TILT_RAW, "viper.TiltRaw", {"roll_deg": i}, T0 + i)
            lb.flush()
            sizes.append(os.path.getsize(path) - CLOSING_BYTES)
    return sizes


def fix_times(path: Path) -> list[int]:
    """The GPS fixes' times, as the independent mcap reader (which seeks through the summary) reads them."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        return [msg.log_time for _, ch, msg in reader.iter_messages(log_time_order=False) if ch.topic == t.GPS_FIX]


def recover(broken: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "appliance.cli.main", "log", "recover", str(broken),
                           "--out", str(out)], cwd=broken.parent, env=dict(os.environ, PYTHONPATH=str(REPO)),
                          capture_output=True, text=True, timeout=120, check=False)


def test_garbage_inserted_in_the_middle_keeps_the_messages_after_it(tmp_path):
    src = tmp_path / "session.mcap"
    sizes = write_log(src)
    data = src.read_bytes()
    at = sizes[40]  # between the 41st and the 42nd flush's chunks
    garbage = np.random.default_rng(7).integers(0, 256, 5000, dtype=np.uint8).tobytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[:at] + garbage + data[at:])
    r = recover(broken, tmp_path / "fixed.mcap")
    assert r.returncode == 0 and r.stderr == ""
    assert fix_times(tmp_path / "fixed.mcap") == [T0 + i for i in range(N)]
    lines = r.stdout.splitlines()
    assert lines[0] == (f"{tmp_path / 'fixed.mcap'}: recovered {N + 31} messages on 2 topics (source complete; "
                        f"5000 corrupt bytes skipped in 1 stretch from byte {at})")
    assert lines[1] == f"{broken}: corrupt bytes {at} to {at + 5000} skipped"


def test_a_corrupt_record_length_near_the_start_loses_only_its_record(tmp_path):
    src = tmp_path / "session.mcap"
    sizes = write_log(src)
    data = bytearray(src.read_bytes())
    assert data[sizes[0]] == 0x06  # the second flush's chunk starts where the first flush ended
    data[sizes[0] + 1:sizes[0] + 9] = (1 << 40).to_bytes(8, "little")  # its length, now past the end
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    r = recover(broken, tmp_path / "fixed.mcap")
    assert r.returncode == 0, r.stderr
    times = fix_times(tmp_path / "fixed.mcap")
    # the first chunk, then all but the one whose record was broken (its message index records go with it)
    assert times == [T0] + [T0 + i for i in range(2, N)]
    assert "recovered" in r.stdout and "corrupt bytes skipped in 1 stretch" in r.stdout


def test_a_stretch_of_garbage_overwriting_records_and_a_torn_tail(tmp_path):
    src = tmp_path / "session.mcap"
    sizes = write_log(src)
    data = bytearray(src.read_bytes())
    data[sizes[10] + 20:sizes[20] + 5] = b"\xa5" * (sizes[20] + 5 - sizes[10] - 20)  # over ten chunks
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data[:sizes[70] + 50]))  # and cut short inside the 72nd chunk
    r = recover(broken, tmp_path / "fixed.mcap")
    assert r.returncode == 0, r.stderr
    times = fix_times(tmp_path / "fixed.mcap")
    assert times == [T0 + i for i in range(11)] + [T0 + i for i in range(22, 71)]  # 11-21 were overwritten
    assert f"cut at byte {sizes[70]} of {sizes[70] + 50}" in r.stdout
