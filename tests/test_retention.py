"""Retention of the session logs: the oldest complete logs go first, never the open one nor (with
keep_unreplayed) one not replayed; bad settings are one line; a session refused for want of room is
said in STATUS and the daemon tries again at its next slot."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from pathlib import Path

import pytest

from appliance.acquisition import retention
from appliance.acquisition.daemon import SessionDaemon
from appliance.acquisition.notify import Notifier
from appliance.acquisition.session import SessionResult, open_session_log
from appliance.config import Compression, Config, LogbookConfig, SessionConfig, load_config
from appliance.errors import ConfigError
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook
from appliance.outputs.styles import MAP_LAYER_SUFFIXES


def write_log(folder: Path, name: str, mtime_s: float, payload_bytes: int = 8000) -> Path:
    """A real sealed MCAP log of about ``payload_bytes`` with modification time ``mtime_s``."""
    path = folder / name
    lb = Logbook.create(path, compression=Compression.NONE, reserve_bytes=1024)
    lb.write_json(t.SESSION, "viper.Session", {"session_id": os.urandom(payload_bytes // 2).hex()}, 1)
    lb.close()
    os.utime(path, (mtime_s, mtime_s))
    return path


def folder_of_logs(tmp_path: Path, n: int) -> list[Path]:
    """``n`` logs whose names sort the other way round from their ages (oldest first in the list)."""
    return [write_log(tmp_path, f"viper-2026060{9 - i}T120000Z-{i:08x}.mcap", 1_000_000.0 + 100 * i)
            for i in range(n)]


def test_retention_removes_the_oldest_complete_logs_first_never_the_open_one(tmp_path):
    logs = folder_of_logs(tmp_path, 5)
    # a log being written: the oldest file of all, no footer yet, its reserve beside it
    open_path = tmp_path / "viper-20260610T120000Z-open0000.mcap"
    open_log = Logbook.create(open_path, compression=Compression.NONE, reserve_bytes=1024)
    open_log.write_json(t.SESSION, "viper.Session", {"session_id": "open"}, 1)
    open_log.flush()
    os.utime(open_path, (999_000.0, 999_000.0))
    assert not retention.is_complete(open_path) and all(retention.is_complete(p) for p in logs)
    total = retention.logs_total_bytes(tmp_path)
    assert total == sum(p.stat().st_size for p in [*logs, open_path]) + 1024  # the reserve counts
    cap = total - logs[0].stat().st_size - logs[1].stat().st_size
    cfg = LogbookConfig(reserve_bytes=1024, max_total_bytes=cap)
    said: list[str] = []
    out = retention.enforce(tmp_path, cfg, say=said.append)
    assert [f.path for f in out.removed] == logs[:2] and out.holds and out.total_bytes == cap
    assert sorted(p.name for p in tmp_path.glob("viper-*.mcap")) == sorted(p.name for p in [*logs[2:], open_path])
    assert len(said) == 2 and said[0].startswith(f"retention: removed {logs[0]} (") and "max_total_bytes" in said[0]
    # the log a session names as its own is never removed, complete or not
    cap2 = retention.logs_total_bytes(tmp_path) - logs[3].stat().st_size
    out = retention.enforce(tmp_path, dataclasses.replace(cfg, max_total_bytes=cap2), open_log=logs[2])
    assert [f.path for f in out.removed] == [logs[3]] and logs[2].exists() and open_path.exists()
    open_log.close()


def test_keep_unreplayed_removes_only_the_replayed_logs(tmp_path):
    logs = folder_of_logs(tmp_path, 4)
    for p in (logs[1], logs[3]):
        retention.mark_replayed(p, "replayed into /tmp/replay")
    assert retention.replayed_marker(logs[1]).read_text() == "replayed into /tmp/replay\n"
    least = LogbookConfig(reserve_bytes=1024).least_log_bytes
    cfg = LogbookConfig(reserve_bytes=1024, max_total_bytes=least, keep_unreplayed=True)
    out = retention.enforce(tmp_path, cfg)
    assert [f.path for f in out.removed] == [logs[1], logs[3]] and not out.holds
    assert sorted(tmp_path.iterdir()) == sorted([logs[0], logs[2]])  # the markers went with their logs
    with pytest.raises(retention.NoRoomError, match="no room for the next log .*not replayed"):
        retention.make_room(tmp_path, cfg)
    assert sorted(tmp_path.iterdir()) == sorted([logs[0], logs[2]])
    # without keep_unreplayed the same limit removes the oldest until the two logs' 16.6 kB fit in 17408 bytes
    out = retention.enforce(tmp_path, dataclasses.replace(cfg, keep_unreplayed=False))
    assert [f.path for f in out.removed] == [logs[0]] and out.holds and logs[2].exists()


def test_a_logs_map_layers_count_with_it_and_go_with_it(tmp_path):
    logs = folder_of_logs(tmp_path, 3)
    # the layers a session writes beside its log: bytes the cap must count, files retention must not orphan
    for p in logs:
        for suffix in MAP_LAYER_SUFFIXES:
            p.with_name(p.stem + suffix).write_bytes(b"x" * 3000)
    other = tmp_path / "jacksboro.viperdb"
    other.write_bytes(b"y" * 50_000)  # not a log's: neither counted nor removed
    per_log = [p.stat().st_size + 3000 * len(MAP_LAYER_SUFFIXES) for p in logs]
    assert retention.logs_total_bytes(tmp_path) == sum(per_log)
    out = retention.enforce(tmp_path, LogbookConfig(reserve_bytes=1024, max_total_bytes=sum(per_log[1:])))
    assert [f.path for f in out.removed] == [logs[0]] and out.holds
    assert not any(n.name.startswith(logs[0].stem) for n in tmp_path.iterdir())
    assert sorted(n.name for n in tmp_path.iterdir()) == sorted(
        [other.name] + [q.stem + e for q in logs[1:] for e in (*MAP_LAYER_SUFFIXES, ".mcap")])


def test_keep_free_bytes_counts_the_disk(tmp_path):
    logs = folder_of_logs(tmp_path, 3)
    free = retention.disk_free_bytes(tmp_path)
    # 10 MB less than is free: nothing to do (other writers on this disk move it by far less meanwhile)
    out = retention.enforce(tmp_path, LogbookConfig(keep_free_bytes=max(1, free - 10_000_000)))
    assert out.removed == [] and out.holds
    # a terabyte more than is free: every log goes, oldest first, and the limit still fails
    out = retention.enforce(tmp_path, LogbookConfig(keep_free_bytes=free + 10**12))
    assert [f.path for f in out.removed] == logs and not out.holds
    assert out.reason.endswith(f"keep_free_bytes {free + 10**12}")


def test_bad_retention_settings_are_one_line(tmp_path, capsys):
    from appliance.cli.main import main

    small = tmp_path / "small.toml"
    small.write_text("[logbook]\nreserve_bytes = 1024\nmax_total_bytes = 5000\n")
    with pytest.raises(ConfigError) as e:
        load_config(small)
    assert str(e.value) == (f"{small}: logbook.max_total_bytes: expected 0 (no cap) or at least one log: "
                            "reserve_bytes + 16384 = 17408 bytes, got 5000")
    st = os.statvfs(tmp_path)
    disk = st.f_blocks * st.f_frsize
    big = tmp_path / "big.toml"
    big.write_text(f"[platform]\nkind = \"sim\"\n[logbook]\nkeep_free_bytes = {disk + 1}\n")
    logs = tmp_path / "logs"
    rc = main(["daemon", "session", "--config", str(big), "--log-dir", str(logs)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1
    assert err[0] == (f"viper daemon: error: logbook.keep_free_bytes: expected less than the size of the disk of "
                      f"{logs} ({disk} bytes), got {disk + 1}")
    assert not logs.exists()


class RecordingNotifier(Notifier):
    """A notifier that keeps the STATUS lines instead of sending them."""

    def __init__(self) -> None:
        super().__init__(None)
        self.statuses: list[str] = []

    def notify(self, **fields: str | int) -> None:
        if "STATUS" in fields:
            self.statuses.append(str(fields["STATUS"]))


def test_a_session_refused_for_room_is_in_status_and_the_daemon_tries_again(tmp_path, caplog):
    logs = folder_of_logs(tmp_path, 3)  # about 8 kB each, none replayed
    size = max(p.stat().st_size for p in logs)
    logbook = LogbookConfig(log_dir=tmp_path, reserve_bytes=1024, compression=Compression.NONE,
                            # two logs, their replayed markers (counted with them) and the least log
                            max_total_bytes=2 * size + 64 + LogbookConfig(reserve_bytes=1024).least_log_bytes,
                            keep_unreplayed=True)
    config = Config(logbook=logbook, session=SessionConfig(interval_s=0.05, max_sessions=1))

    def run(log_dir: Path, should_stop: object, on_status: object) -> SessionResult:
        sid, path, lb = open_session_log(config, log_dir, time.time_ns())
        lb.write_json(t.SESSION, "viper.Session", {"session_id": sid}, time.time_ns())
        lb.close()
        return SessionResult(path, sid)

    notifier = RecordingNotifier()
    daemon = SessionDaemon(config, tmp_path, notifier, run)
    rc: list[int] = []
    thread = threading.Thread(target=lambda: rc.append(daemon.run()))
    thread.start()
    try:
        deadline = time.monotonic() + 60
        while sum("not started" in s for s in notifier.statuses) < 2:
            assert thread.is_alive() and time.monotonic() < deadline, notifier.statuses
            time.sleep(0.01)
        for p in logs:  # replayed now: the next slot may remove them
            retention.mark_replayed(p, "replayed")
    finally:
        thread.join(timeout=60)
        daemon.request_stop()
    assert rc == [0] and len(daemon.results) == 1
    refused = [s for s in notifier.statuses if "not started" in s]
    assert refused[0].startswith(f"session 1 not started: {tmp_path}: no room for the next log (logs take ")
    assert "not replayed (keep_unreplayed); next attempt in 0.05 s" in refused[0]
    assert notifier.statuses[-2].startswith("session 1 degraded") or notifier.statuses[-2].startswith("session 1 ok")
    journal = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("session 1 not started:") for m in journal)
    # room for the least log (17408 bytes, more than the reserve and a tenth over the logs there): the
    # cap holds two logs and that, so the oldest went and the two others stayed with the new one
    assert not logs[0].exists() and logs[1].exists() and logs[2].exists()
    assert daemon.results[0].log_path.exists()
    assert sum(m.startswith("retention: removed") for m in journal) == 1
