"""The one atomic writer on real disks: modes, refusals, full and read-only file systems, cleanup.

Full and read-only disks are real tmpfs mounts (the tests skip with the reason where mounting is
not permitted); permissions alone would not do, since root ignores them.
"""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from appliance.atomic import (
    TMP_MARK,
    atomic_output,
    check_output_folder,
    check_output_path,
    remove_stale_temporaries,
    scratch_file,
    umask_mode,
    write_bytes_atomic,
    write_text_atomic,
)
from appliance.errors import OutputError
from appliance.logbook.writer import Logbook, remove_stale_reserves, reserve_path_of
from appliance.sim.scratch import LOCK_NAME, SimFolder, remove_stale_sim_folders


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every path under ``folder`` with its content (None for folders)."""
    return {str(p.relative_to(folder)): (None if p.is_dir() else p.read_bytes())
            for p in sorted(folder.rglob("*"))}


def mount_tmpfs(where: Path, size: str = "64k", read_only: bool = False) -> None:
    where.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if read_only else "")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or 'mount failed'}): needs root in a sandbox")


def fill(folder: Path) -> None:
    """Fill the file system of ``folder`` to the last byte."""
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        for size in (4096, 1):
            while True:
                try:
                    os.write(fd, b"\xa5" * size)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
                    break
    finally:
        os.close(fd)


@pytest.fixture
def full_disk(tmp_path):
    where = tmp_path / "full"
    mount_tmpfs(where)
    try:
        (where / "existing.csv").write_text("old content\n")
        fill(where)
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


@pytest.fixture
def read_only_disk(tmp_path):
    where = tmp_path / "ro"
    mount_tmpfs(where, read_only=True)
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield
    os.umask(old)


def test_a_new_file_gets_the_umask_mode_and_a_replaced_one_keeps_its_mode(tmp_path, umask_027):
    assert umask_mode() == 0o640
    new = tmp_path / "new.csv"
    write_text_atomic(new, "a,b\n")
    assert new.read_text() == "a,b\n"
    assert new.stat().st_mode & 0o7777 == 0o640
    old = tmp_path / "old.toml"
    old.write_text("x = 1\n")
    old.chmod(0o604)
    write_text_atomic(old, "x = 2\n")
    assert old.read_text() == "x = 2\n" and old.stat().st_mode & 0o7777 == 0o604
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.csv", "old.toml"]


@pytest.mark.parametrize("target, message", [
    ("missing/out.csv", "folder .*missing does not exist"),
    ("a_file/out.csv", "a_file is not a folder"),
    ("a_folder", "is a folder"),
])
def test_bad_places_are_one_line_errors_and_leave_nothing(tmp_path, target, message):
    (tmp_path / "a_file").write_text("keep me\n")
    (tmp_path / "a_folder").mkdir()
    before = snapshot(tmp_path)
    with pytest.raises(OutputError, match=message) as info:
        write_text_atomic(tmp_path / target, "data\n")
    assert "\n" not in str(info.value)
    assert snapshot(tmp_path) == before


def test_a_full_disk_is_one_line_and_the_old_file_is_untouched(full_disk):
    before = snapshot(full_disk)
    with pytest.raises(OutputError, match="existing.csv: cannot write: no space left on device"):
        write_bytes_atomic(full_disk / "existing.csv", b"x" * 100_000)
    with pytest.raises(OutputError, match="no space left on device"):
        write_bytes_atomic(full_disk / "new.png", b"x" * 100_000)
    assert snapshot(full_disk) == before


def test_a_memory_mapped_build_on_a_full_disk_fails_before_the_map(full_disk):
    """Pre-allocation turns the SIGBUS a memory map would die of into ENOSPC, before any work."""
    reached = []
    before = snapshot(full_disk)
    with pytest.raises(OutputError, match="no space left on device"):
        with atomic_output(full_disk / "map.viperdb", preallocate=1 << 20):
            reached.append(True)
    assert reached == []
    assert snapshot(full_disk) == before


def test_a_memory_mapped_build_lands_whole(tmp_path):
    out = tmp_path / "map.viperdb"
    data = np.arange(10_000, dtype=np.uint8)
    with atomic_output(out, preallocate=data.size + 16) as tmp:
        assert tmp.parent == tmp_path and TMP_MARK in tmp.name and not out.exists()
        assert tmp.stat().st_size == data.size + 16
        with open(tmp, "r+b") as fh:
            fh.write(b"VIPERDB\0" + bytes(8))
        mm = np.memmap(tmp, mode="r+", dtype=np.uint8, offset=16, shape=(data.size,))
        mm[:] = data
        mm.flush()
        del mm
    raw = out.read_bytes()
    assert raw[:8] == b"VIPERDB\0" and np.array_equal(np.frombuffer(raw[16:], np.uint8), data)
    assert [p.name for p in tmp_path.iterdir()] == ["map.viperdb"]


def test_a_failing_writer_leaves_the_old_file_and_no_temporary(tmp_path):
    out = tmp_path / "report.tif"
    out.write_bytes(b"previous")
    with pytest.raises(ZeroDivisionError):
        with atomic_output(out) as tmp:
            tmp.write_bytes(b"half")
            raise ZeroDivisionError
    assert out.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["report.tif"]


def test_a_read_only_disk_is_refused_before_and_during_the_write(read_only_disk):
    with pytest.raises(OutputError, match="read-only file system"):
        check_output_path(read_only_disk / "sky.csv")
    with pytest.raises(OutputError, match="read-only file system"):
        write_text_atomic(read_only_disk / "sky.csv", "a\n")
    with pytest.raises(OutputError, match="read-only file system"):
        check_output_folder(read_only_disk / "report")
    assert list(read_only_disk.iterdir()) == []


def test_output_checks(tmp_path):
    dem = tmp_path / "m.tif"
    dem.write_bytes(b"dem")
    with pytest.raises(OutputError, match="is also an input"):
        check_output_path(tmp_path / "." / "m.tif", [dem], force=True)
    link = tmp_path / "link.tif"
    link.symlink_to(dem)
    with pytest.raises(OutputError, match="is also an input"):
        check_output_path(link, [dem], force=True)
    with pytest.raises(OutputError, match="already exists .*--force"):
        check_output_path(dem)
    assert check_output_path(dem, force=True) == dem
    assert check_output_path(tmp_path / "new.viperdb", [dem]) == tmp_path / "new.viperdb"
    with pytest.raises(OutputError, match="report.html: already exists"):
        (tmp_path / "rep").mkdir()
        (tmp_path / "rep" / "report.html").write_text("x")
        check_output_folder(tmp_path / "rep", files=["summary.csv", "report.html"], force=False)
    with pytest.raises(OutputError, match="is a file, expected a folder"):
        check_output_folder(dem)
    assert check_output_folder(tmp_path / "a" / "b").is_dir()


def test_a_killed_sessions_reserve_is_removed_and_a_live_ones_kept(tmp_path):
    stale = reserve_path_of(tmp_path / "viper-killed.mcap")
    stale.write_bytes(bytes(65536))
    with Logbook.create(tmp_path / "viper-live.mcap"):
        live_reserve = reserve_path_of(tmp_path / "viper-live.mcap")
        assert live_reserve.exists() and not stale.exists()  # the new session cleaned the old one up
        stale.write_bytes(bytes(65536))
        assert remove_stale_reserves(tmp_path) == [stale]
        assert live_reserve.exists()
    assert not live_reserve.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["viper-live.mcap"]


def test_sim_folders_of_dead_processes_are_removed(tmp_path):
    dead = tmp_path / "viper-sim-dead"
    dead.mkdir()
    (dead / LOCK_NAME).write_bytes(b"")
    (dead / "gps").symlink_to("/dev/pts/999")
    foreign = tmp_path / "viper-sim-nolock"
    foreign.mkdir()
    live = SimFolder(tmp_path)
    assert not dead.exists() and live.path.is_dir() and foreign.is_dir()
    assert remove_stale_sim_folders(tmp_path) == []
    live.remove()
    assert not live.path.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["viper-sim-nolock"]


def test_a_killed_writers_temporary_is_removed_by_the_next_write(tmp_path):
    out = tmp_path / "map.viperdb"
    stale = tmp_path / f".map.viperdb.0badf00d{TMP_MARK}.viperdb"
    stale.write_bytes(b"half a database")
    other = tmp_path / f".other.viperdb.0badf00d{TMP_MARK}.viperdb"
    other.write_bytes(b"another output's")
    with atomic_output(out) as tmp:
        assert not stale.exists()
        tmp.write_bytes(b"whole")
        assert remove_stale_temporaries(tmp_path, out.name) == []  # a live writer's is kept
    assert out.read_bytes() == b"whole"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, other.name])


def open_files_under(folder: Path) -> list[str]:
    """What this process's open descriptors name under ``folder`` (an unnamed file shows as
    ``folder/#inode (deleted)`` or ``folder/.name (deleted)``)."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder) + "/"):
            found.append(target)
    return found


@pytest.mark.parametrize("tmpfile", [True, False], ids=["O_TMPFILE", "named-then-unlinked"])
def test_a_scratch_file_has_no_name_and_is_gone_after_the_block(tmp_path, monkeypatch, tmpfile):
    if not tmpfile:
        monkeypatch.delattr(os, "O_TMPFILE", raising=False)
    out = tmp_path / "map.viperdb"
    with scratch_file(out, preallocate=10_000) as fd:
        assert list(tmp_path.iterdir()) == []  # nothing a killed writer could leave behind
        assert os.fstat(fd).st_size == 10_000
        os.pwrite(fd, b"spilled", 5_000)
        assert os.pread(fd, 7, 5_000) == b"spilled"
        assert [t.endswith("(deleted)") for t in open_files_under(tmp_path)] == [True]
    assert open_files_under(tmp_path) == [] and list(tmp_path.iterdir()) == []
    with pytest.raises(ZeroDivisionError):
        with scratch_file(out):
            raise ZeroDivisionError
    assert open_files_under(tmp_path) == [] and list(tmp_path.iterdir()) == []


def test_a_scratch_file_on_a_full_disk_or_in_a_bad_place_is_one_line(full_disk, tmp_path):
    before = snapshot(full_disk)
    reached = []
    with pytest.raises(OutputError, match=r"map.viperdb: cannot write its scratch file: no space left on device"):
        with scratch_file(full_disk / "map.viperdb", preallocate=1 << 20):
            reached.append(True)
    assert reached == [] and snapshot(full_disk) == before and open_files_under(full_disk) == []
    with pytest.raises(OutputError, match="map.viperdb: cannot write: input/output error"):
        with scratch_file(tmp_path / "map.viperdb"):
            raise OSError(errno.EIO, "a failing disk")  # what a write in the block may raise
    with pytest.raises(OutputError, match="cannot write its scratch file: folder .*missing does not exist"):
        with scratch_file(tmp_path / "missing" / "map.viperdb"):
            pass
    assert list(tmp_path.iterdir()) == [full_disk]
