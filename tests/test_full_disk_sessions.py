"""Sessions on a full disk, imitated by RLIMIT_FSIZE in the command's process (a write past the limit
fails with EFBIG, as one on a full disk fails with ENOSPC): ``viper capture`` and ``viper daemon
session`` leave no empty or half-written log under a final name, say what happened in one line on
stderr (never stdout) and in STATUS=, and exit non-zero when nothing was written."""

from __future__ import annotations

import os
import re
import resource
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from appliance.logbook import LogReader
from appliance.logbook import topics as t
from tests.test_hardening_atomic import fill, mount_tmpfs

REPO = Path(__file__).resolve().parents[1]
# the hardware platform with no device at all: a session runs in a moment and logs its procedures' failures
NO_DEVICES = ('[platform]\nkind = "hardware"\n[devices.compass]\nkind = "nmea"\n'
              '[devices.inclinometer]\nkind = "nmea"\n')


def viper(args: list[str], cwd: Path, file_size_limit: int | None = None,
          env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    def limit() -> None:
        if file_size_limit is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit, file_size_limit))

    return subprocess.run([sys.executable, "-m", "appliance.cli.main", *args], cwd=cwd, preexec_fn=limit,
                          env=dict(os.environ, PYTHONPATH=str(REPO), **(env or {})), capture_output=True,
                          text=True, timeout=120, check=False)


def files_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != ".session.lock")


def test_capture_that_cannot_open_its_log_leaves_no_file(tmp_path):
    (tmp_path / "viper.toml").write_text(NO_DEVICES)
    r = viper(["capture", "--config", "viper.toml", "--log-dir", "logs"], tmp_path, file_size_limit=1000)
    assert r.returncode == 1 and r.stdout == ""
    (line,) = r.stderr.splitlines()
    assert line.startswith("viper capture: error: logs/.viper-") and "cannot reserve 65536 bytes" in line
    assert "File too large; no log written: viper-" in line and line.endswith(".mcap removed")
    assert files_in(tmp_path / "logs") == []


def test_daemon_that_writes_nothing_says_so_and_exits_non_zero(tmp_path):
    (tmp_path / "viper.toml").write_text(NO_DEVICES + "[session]\ninterval_s = 0.1\nmax_sessions = 3\n")
    sock_path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(0.2)
    datagrams: list[str] = []

    def listen(stop: threading.Event) -> None:  # as systemd does, or the daemon blocks on a full queue
        while not stop.is_set():
            try:
                datagrams.append(sock.recv(4096).decode())
            except TimeoutError:
                pass

    stop = threading.Event()
    listener = threading.Thread(target=listen, args=(stop,), daemon=True)
    listener.start()
    try:
        r = viper(["daemon", "session", "--config", "viper.toml", "--log-dir", "logs"], tmp_path,
                  file_size_limit=1000, env={"NOTIFY_SOCKET": sock_path})
    finally:
        stop.set()
        listener.join(timeout=5)
        sock.close()
    assert r.returncode == 1 and r.stdout == ""
    lines = r.stderr.splitlines()
    assert len(lines) == 4
    for n, line in enumerate(lines[:3], 1):
        assert line.startswith(f"session {n} skipped: logs/.viper-") and line.endswith(".mcap removed"), line
    assert lines[3] == "no session was written: all 3 sessions failed to write their log"
    skipped = [d for d in datagrams if "skipped" in d]
    assert len(skipped) == 3 and all("File too large; no log written" in d for d in skipped)
    assert files_in(tmp_path / "logs") == []


def _flush_offsets(log: Path) -> list[int]:
    """Where each chunk starts: the log's length after each flush (the independent mcap reader)."""
    with open(log, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=True)
        offsets, pos = [], 0
        for record in reader.records:
            if isinstance(record, Chunk):
                offsets.append(pos)
            pos = f.tell()
    return offsets


def test_disk_full_mid_session_seals_the_log_and_reports_on_stderr(tmp_path):
    (tmp_path / "viper.toml").write_text(NO_DEVICES + "[logbook]\nreserve_bytes = 1024\n")
    free = viper(["capture", "--config", "viper.toml", "--log-dir", "free"], tmp_path)
    (whole,) = (tmp_path / "free").glob("viper-*.mcap")
    starts = _flush_offsets(whole)
    assert len(starts) >= 4
    # room for the first two flushes and a little more: the third one fails part-way
    r = viper(["capture", "--config", "viper.toml", "--log-dir", "full"], tmp_path, file_size_limit=starts[2] + 120)
    assert free.returncode == r.returncode == 1  # no device, no frame
    (log,) = (tmp_path / "full").glob("viper-*.mcap")
    assert files_in(tmp_path / "full") == [log.name]  # the reserve is gone
    # the error on stderr only, in one line; stdout has the session's result
    (line,) = r.stderr.splitlines()
    assert line == f"full/{log.name}: write failed (File too large); log sealed with 4 durable messages"
    assert "File too large" not in r.stdout and f"log: full/{log.name}" in r.stdout
    assert "failed; frames 0" in r.stdout
    # what was flushed before the disk filled is in a complete, readable log
    reader = LogReader(log)
    messages = list(reader.messages())
    assert reader.complete and len(messages) == 4
    assert [m.decode().message for m in messages if m.topic == t.LOG][0].endswith("started")


def test_a_log_that_fills_the_disk_before_its_first_flush_is_removed(tmp_path):
    # the log opens (its header and a small reserve fit), its first flush does not
    (tmp_path / "viper.toml").write_text(NO_DEVICES + "[logbook]\nreserve_bytes = 100\n")
    r = viper(["capture", "--config", "viper.toml", "--log-dir", "logs"], tmp_path, file_size_limit=400)
    assert r.returncode == 1 and r.stdout == ""
    (line,) = r.stderr.splitlines()
    assert line.startswith("viper capture: error: logs/viper-") and "write failed (File too large)" in line
    assert line.endswith(".mcap removed") and "it held no message" in line
    assert files_in(tmp_path / "logs") == []


@pytest.fixture
def small_disk(tmp_path):
    """A 256 KiB tmpfs with a ``logs`` folder, filled to the last byte (skipped where mounting is not permitted)."""
    where = tmp_path / "disk"
    mount_tmpfs(where, size="256k")
    try:
        (where / "logs").mkdir()
        (where / "logs" / ".session.lock").touch()
        fill(where)
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_on_a_full_disk_capture_and_the_daemon_leave_no_file_and_say_so(tmp_path, small_disk):
    (tmp_path / "viper.toml").write_text(NO_DEVICES + "[session]\ninterval_s = 0.1\nmax_sessions = 3\n")
    logs = small_disk / "logs"
    r = viper(["capture", "--config", "viper.toml", "--log-dir", str(logs)], tmp_path)
    assert r.returncode == 1 and r.stdout == ""
    (line,) = r.stderr.splitlines()
    assert "No space left on device" in line and line.endswith(".mcap removed")
    r = viper(["daemon", "session", "--config", "viper.toml", "--log-dir", str(logs)], tmp_path)
    assert r.returncode == 1 and r.stdout == ""
    lines = r.stderr.splitlines()
    assert [x.split(":")[0] for x in lines[:3]] == ["session 1 skipped", "session 2 skipped", "session 3 skipped"]
    assert lines[3:] == ["no session was written: all 3 sessions failed to write their log"]
    assert files_in(logs) == []


def test_a_disk_that_fills_during_the_session_leaves_a_sealed_log_and_one_stderr_line(tmp_path, small_disk):
    (tmp_path / "viper.toml").write_text(NO_DEVICES)
    # room for the reserve and two pages of log (the metadata records take most of one)
    with open(small_disk / "filler", "r+b") as f:
        f.truncate(os.fstat(f.fileno()).st_size - 65536 - 8192)
    r = viper(["capture", "--config", "viper.toml", "--log-dir", str(small_disk / "logs")], tmp_path)
    (log,) = (small_disk / "logs").glob("viper-*.mcap")
    assert r.returncode == 1 and files_in(small_disk / "logs") == [log.name]  # the reserve is gone
    (line,) = r.stderr.splitlines()
    assert re.fullmatch(rf"{re.escape(str(log))}: disk full; log sealed with \d+ durable messages", line), line
    assert "disk full" not in r.stdout and "failed; frames 0" in r.stdout
    reader = LogReader(log)
    messages = list(reader.messages())
    assert reader.complete and len(messages) == int(line.split()[-3]) > 0
