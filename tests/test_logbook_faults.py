"""Power cuts, kills, full disks and corrupt bytes: the log keeps everything flushed before."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import pytest
from mcap.reader import make_reader

from appliance.cli.main import main
from appliance.errors import LogError
from appliance.logbook import Logbook, LogbookFullError, LogReader, recover_log
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.sink import DurableFile
from appliance.logbook.writer import CLOSING_BYTES, LIBRARY, PROFILE

T0 = 1_700_000_000_000_000_000
REPO = Path(__file__).resolve().parents[1]


def fix(i):
    return m.location_fix(T0 + i, 33.0 + i * 1e-6, -97.0)


def write_flushed(path, n):
    """n messages, flushed one by one; returns the log's length after each flush (the file holds the
    room for its closing records beyond it, zeros)."""
    sizes = []
    lb = Logbook.create(path, reserve_bytes=0)
    for i in range(n):
        lb.write_proto(t.GPS_FIX, fix(i), T0 + i)
        if i % 3 == 0:
            lb.write_json(t.TILT_RAW, "viper.TiltRaw", {"roll_deg": i}, T0 + i)
        lb.flush()
        held = path.read_bytes()[-CLOSING_BYTES:]
        assert held == bytes(CLOSING_BYTES)
        sizes.append(os.path.getsize(path) - CLOSING_BYTES)
    lb.close()
    return sizes


def read_times(path):
    with open(path, "rb") as f:
        return [
            msg.log_time
            for _, ch, msg in make_reader(f).iter_messages(log_time_order=False)
            if ch.topic == t.GPS_FIX
        ]


def test_truncated_at_every_offset_reads_every_flushed_message(tmp_path):
    src = tmp_path / "full.mcap"
    sizes = write_flushed(src, 12)
    data = src.read_bytes()
    header_end = 8 + 9 + 4 + len(PROFILE) + 4 + len(LIBRARY)  # magic and header record
    broken = tmp_path / "broken.mcap"
    for cut in range(header_end, len(data), 3):
        broken.write_bytes(data[:cut])
        reader = LogReader(broken)
        times = [msg.log_time_ns for msg in reader.messages() if msg.topic == t.GPS_FIX]
        flushed = sum(1 for s in sizes if s <= cut)
        # every flushed message, and at most the one whose chunk was whole but not its index
        assert times == [T0 + i for i in range(len(times))], f"cut at byte {cut}"
        assert flushed <= len(times) <= flushed + 1, f"cut at byte {cut}"
        assert not reader.complete and reader.problem is not None


def test_truncated_logs_recover_into_valid_mcap(tmp_path):
    src = tmp_path / "full.mcap"
    sizes = write_flushed(src, 12)
    data = src.read_bytes()
    header_end = 8 + 9 + 4 + len(PROFILE) + 4 + len(LIBRARY)
    broken = tmp_path / "broken.mcap"
    cuts = [0, 8, header_end - 1, header_end, sizes[0] - 1, sizes[0], sizes[4] + 3, sizes[-1], len(data) - 1]
    for cut in cuts:
        broken.write_bytes(data[:cut])
        out = tmp_path / f"fixed{cut}.mcap"
        if cut < header_end:
            with pytest.raises(LogError, match="not an MCAP log"):
                recover_log(broken, out)
            assert not out.exists()
            continue
        report = recover_log(broken, out)
        flushed = sum(1 for s in sizes if s <= cut)
        times = read_times(out)  # mcap's own seeking reader opens the recovered file
        assert times == [T0 + i for i in range(len(times))] and flushed <= len(times) <= flushed + 1
        assert not report.source_complete and report.stopped_at is not None


def test_recover_refuses_what_is_not_a_log(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(LogError, match="not an MCAP log"):
        recover_log(bad, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()
    with pytest.raises(LogError, match="not found"):
        recover_log(tmp_path / "missing.mcap", tmp_path / "out.mcap")


def test_corrupt_bytes_in_the_middle_stop_reading_with_the_offset(tmp_path):
    src = tmp_path / "full.mcap"
    sizes = write_flushed(src, 10)
    data = bytearray(src.read_bytes())
    hit = sizes[5] + 40  # inside the chunk after the sixth flush
    data[hit : hit + 8] = b"\xff" * 8
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    reader = LogReader(bad)
    times = [msg.log_time_ns for msg in reader.messages() if msg.topic == t.GPS_FIX]
    assert times == [T0 + i for i in range(6)]
    assert not reader.complete and reader.stopped_at == sizes[5]
    assert "byte" in (reader.problem or "")


def test_full_disk_seals_a_valid_log_with_everything_before(tmp_path):
    reserve = tmp_path / ".reserve"

    class SmallDisk(DurableFile):
        """A disk of 3000 bytes shared by the log and the 100-byte reserve file beside it."""

        def write(self, data):
            room = 3000 - (100 if reserve.exists() else 0) - self.tell()
            if len(data) > room:
                if room > 0:  # a torn, partial write, as the kernel does it
                    self._pos += os.write(self.fd, bytes(data)[:room])
                raise OSError(errno.ENOSPC, "No space left on device")
            return super().write(data)

    path = tmp_path / "s.mcap"
    lb = Logbook(SmallDisk(path), name=str(path), reserve_path=reserve, reserve_bytes=100)
    written = 0
    with pytest.raises(LogbookFullError, match="disk full; log sealed with"):
        for i in range(1000):
            lb.write_proto(t.GPS_FIX, fix(i), T0 + i)
            lb.write_proto(t.IMAGE, m.compressed_image(T0 + i, os.urandom(150)), T0 + i)
            written = i + 1
            lb.flush()
    assert lb.disk_full and not reserve.exists()
    with pytest.raises(LogbookFullError):
        lb.write_proto(t.GPS_FIX, fix(0), T0)
    lb.close()
    times = read_times(path)  # valid MCAP: the seeking reader falls back to the empty summary
    assert written > 3 and lb.messages_durable == 2 * (written - 1)  # the last flush failed
    assert times == [T0 + i for i in range(written - 1)]
    reader = LogReader(path)
    list(reader.messages())
    assert reader.complete and reader.problem is None


def _mount_tmpfs(where: Path, size: str) -> bool:
    if shutil.which("mount") is None or os.geteuid() != 0:
        return False
    where.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True, check=False
    )
    return r.returncode == 0


def test_full_tmpfs_ends_cleanly(tmp_path):
    mnt = tmp_path / "small"
    if not _mount_tmpfs(mnt, "256k"):
        pytest.skip("cannot mount a small tmpfs here (needs root and mount rights)")
    try:
        path = mnt / "s.mcap"
        lb = Logbook.create(path, reserve_bytes=16 * 1024)
        n = 0
        with pytest.raises(LogbookFullError):
            for i in range(10_000):
                lb.write_proto(t.IMAGE, m.compressed_image(T0 + i, os.urandom(20_000)), T0 + i)
                n += 1
                lb.flush()
        lb.close()
        with open(path, "rb") as f:
            got = [msg.log_time for _, _, msg in make_reader(f).iter_messages(log_time_order=False)]
        assert got == [T0 + i for i in range(len(got))] and len(got) >= n - 1 and n > 3
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


CHILD = textwrap.dedent("""
    import sys, time
    from appliance.logbook import Logbook
    from appliance.logbook import messages as m, topics as t
    lb = Logbook.create(sys.argv[1], fsync_interval_s=3600)
    i = 0
    while True:
        lb.write_proto(t.IMAGE, m.compressed_image(%d + i, bytes(2000)), %d + i)
        lb.write_json(t.CAPTURE, "viper.Capture", {"index": i, "stage_deg": 15.0 * i}, %d + i)
        lb.flush()
        print(i, flush=True)
        lb.write_proto(t.IMAGE, m.compressed_image(%d + i, bytes(3000)), %d + i)  # never flushed
        i += 1
        time.sleep(0.002)
""") % ((T0,) * 5)


def test_kill_9_mid_capture_loses_nothing_flushed(tmp_path):
    path = tmp_path / f"{uuid.uuid4().hex}.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True, cwd=REPO
    )
    assert proc.stdout is not None
    flushed = -1
    for line in proc.stdout:
        flushed = int(line)
        if flushed >= 25:
            break
    proc.kill()
    proc.wait()
    out = tmp_path / "fixed.mcap"
    report = recover_log(path, out)
    assert not report.source_complete
    reader = LogReader(out)
    captures = [msg.decode()["index"] for msg in reader.messages() if msg.topic == t.CAPTURE]
    assert reader.complete
    assert captures[: flushed + 1] == list(range(flushed + 1))


def test_cli_info_and_recover(tmp_path, capsys):
    src = tmp_path / "full.mcap"
    write_flushed(src, 4)
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(src.read_bytes()[:-30])
    assert main(["log", "info", str(src)]) == 0
    out = capsys.readouterr().out
    assert "/gps/fix" in out and " 4  foxglove.LocationFix" in out and "complete" in out
    assert main(["log", "info", str(broken)]) == 1
    assert "INCOMPLETE" in capsys.readouterr().out
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(broken), "--out", str(fixed)]) == 0
    assert "recovered 6 messages on 2 topics" in capsys.readouterr().out
    assert read_times(fixed) == [T0 + i for i in range(4)]
    assert main(["log", "recover", str(broken), "--out", str(fixed)]) != 0
    assert "already exists" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    assert main(["log", "info", str(junk)]) == 1
    assert "INCOMPLETE" in capsys.readouterr().out


LIMITED_CHILD = textwrap.dedent("""
    import resource, sys
    from appliance.errors import LogError
    from appliance.logbook import Logbook
    from appliance.logbook import messages as m, topics as t
    limit = int(sys.argv[2])
    if limit:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    lb = Logbook.create(sys.argv[1], reserve_bytes=1024)
    try:
        for i in range(6):
            lb.write_proto(t.GPS_FIX, m.location_fix(%d + i, 33.0 + i * 1e-6, -97.0), %d + i)
            lb.write_proto(t.IMAGE, m.compressed_image(%d + i, bytes(range(i, i + 200))), %d + i)
            lb.flush()
            print("flushed", lb.messages_durable, flush=True)
        lb.close()
    except LogError as exc:
        print(exc, file=sys.stderr)
        sys.exit(1)
""") % ((T0,) * 4)


def _limited_log(path: Path, limit: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", LIMITED_CHILD, str(path), str(limit)], capture_output=True,
                          text=True, cwd=REPO, timeout=60, check=False)


def _data_section_crc_checked(data: bytes) -> int:
    """The DataEnd record's offset, once its CRC is checked against the bytes before it."""
    import zlib

    from mcap.records import DataEnd
    from mcap.stream_reader import StreamReader

    with open_bytes(data) as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=True, validate_crcs=True)
        pos = 0
        for record in reader.records:
            if isinstance(record, DataEnd):
                assert record.data_section_crc == zlib.crc32(data[:pos])
                return pos
            pos = f.tell()
    raise AssertionError("no DataEnd record")


def open_bytes(data: bytes):
    import io

    return io.BytesIO(data)


def test_a_file_size_limit_just_after_a_flush_still_leaves_a_sealed_log(tmp_path):
    """RLIMIT_FSIZE falling in the 50 bytes after a flush: freeing the reserve gives the log itself no room,
    so the log is closed within the room its last complete flush held."""
    free = tmp_path / "free.mcap"
    r = _limited_log(free, 0)
    assert r.returncode == 0, r.stderr
    whole = free.read_bytes()
    starts = [0] + _chunk_ends(whole)
    assert len(starts) == 7  # the header and metadata, and one chunk (with its index) per flush
    for k, extra in ((2, 0), (2, 1), (2, 30), (2, 49), (2, 50), (4, 25)):
        limit = starts[k] + extra
        log = tmp_path / f"limit-{limit}.mcap"
        r = _limited_log(log, limit)
        kept = k if extra >= 50 else k - 1  # flushes whose closing records had room
        assert r.returncode == 1
        assert r.stderr == f"{log}: write failed (File too large); log sealed with {2 * kept} durable messages\n"
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(f".{log.name}")) == []
        data = log.read_bytes()
        reader = LogReader(log)
        times = [msg.log_time_ns for msg in reader.messages() if msg.topic == t.GPS_FIX]
        assert reader.complete and reader.problem is None, (limit, reader.problem)
        assert times == [T0 + i for i in range(kept)]
        # nothing lost: the log is the free run's up to that flush, then its closing records
        end = _data_section_crc_checked(data)
        assert end == starts[kept] and data[:end] == whole[:end]
        with open(log, "rb") as f:  # mcap's own seeking reader opens it
            assert [msg.log_time for _, ch, msg in make_reader(f).iter_messages(log_time_order=False)
                    if ch.topic == t.GPS_FIX] == times


def _chunk_ends(data: bytes) -> list[int]:
    """Where each flush ended: the offsets after each chunk's message index records."""
    from mcap.records import Chunk, DataEnd, MessageIndex
    from mcap.stream_reader import StreamReader

    ends, pos, last = [], 0, None
    with open_bytes(data) as f:
        for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
            if isinstance(last, (Chunk, MessageIndex)) and not isinstance(record, MessageIndex):
                ends.append(pos)
            if isinstance(record, DataEnd):
                break
            last, pos = record, f.tell()
    return ends


def test_a_sparse_log_of_gigabytes_is_read_as_far_as_it_holds_records(tmp_path):
    """A log whose file runs on in zeros for 6 GiB (a sparse file: a disk image, a flush's room never written)
    is read record by record from the file, not into memory: `log info` under a 1 GiB address-space limit
    stops at the zeros at once, in one line, and says where."""
    src = tmp_path / "short.mcap"
    lb = Logbook.create(src, reserve_bytes=0)
    lb.close()
    data = src.read_bytes()
    header_end = 8 + 9 + int.from_bytes(data[9:17], "little")  # the magic, then the header record
    sparse = tmp_path / "sparse.mcap"
    with open(sparse, "wb") as f:
        f.write(data[:header_end])
        f.truncate(6 << 30)
    limit = 1 << 30
    code = (f"import resource, sys; resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit})); "
            "from appliance.cli.main import main; sys.exit(main(['log', 'info', sys.argv[1]]))")
    out = subprocess.run([sys.executable, "-c", code, str(sparse)], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 1, out.stderr
    first = out.stdout.splitlines()[0]
    assert first.startswith(f"{sparse}: {6 << 30} bytes, 0 messages, INCOMPLETE: zeros where a record should "
                            f"start at byte {header_end}")
    assert "Traceback" not in out.stderr
