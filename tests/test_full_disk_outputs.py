"""Outputs on a full disk and what killed runs leave: ``viper estimate --report`` publishes no GeoTIFF
cut short, ``viper replay`` leaves its folder as it was, the next precompute removes a dead writer's
temporary whatever its output's name, and a tiled build leaves no Dask scratch in ``$TMPDIR``.

A full disk is a filled tmpfs where mounting is permitted, else RLIMIT_FSIZE in the command's process
(a write past the limit fails with EFBIG, as one on a full disk fails with ENOSPC)."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio

from appliance.atomic import temporary_path
from appliance.sim.field_session import run_field_session
from appliance.skyline import Skyline, write_skyline_csv
from appliance.terrain.database import build_database
from appliance.terrain.horizon import render_skyline
from tests.conftest import small_config
from tests.test_full_disk_sessions import viper
from tests.test_hardening_atomic import fill, mount_tmpfs

BOUNDS = "-84.30,36.55,-84.27,36.57"
LAT, LON = 36.5631, -84.2850


@pytest.fixture(scope="module")
def small_db(tmp_path_factory, dem):
    folder = tmp_path_factory.mktemp("db")
    build_database(dem, folder / "j.viperdb", search_bounds=tuple(float(v) for v in BOUNDS.split(",")),
                   max_range_m=5000, progress=None)
    write_skyline_csv(Skyline(np.arange(360.0), render_skyline(dem, LAT, LON, max_range_m=5000).elevation_deg),
                      folder / "a.csv")
    return folder


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``, hidden ones too, with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_geotiff_cut_short_is_refused_before_its_rename(small_db, tmp_path):
    # the writer alone, in a process whose files cannot grow past 4 KiB: GDAL's write fails part-way
    script = ("import sys; from pathlib import Path; from appliance.terrain.database import load_database;"
              "from appliance.skyline import read_skyline_csv; from appliance import locate;"
              "from appliance.outputs.files import write_geotiff;"
              "db = load_database(sys.argv[1]); pos = locate(db, read_skyline_csv(sys.argv[2]), (0.3, 1.2), 5.0);"
              "import resource; resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096));"
              "write_geotiff(db, pos, Path(sys.argv[3]))")
    r = subprocess.run([sys.executable, "-c", script, str(small_db / "j.viperdb"), str(small_db / "a.csv"),
                        str(tmp_path / "p.tif")], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])), check=False)
    assert r.returncode != 0
    assert "appliance.errors.OutputError: " + str(tmp_path / "p.tif") + ": cannot write: file too large (" in r.stderr
    assert "_tiffWriteProc" not in r.stderr  # the TIFF library's own lines became the reason
    assert os.listdir(tmp_path) == []


@pytest.fixture
def disk(tmp_path):
    where = tmp_path / "disk"
    mount_tmpfs(where, size="2m")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_estimate_report_on_a_disk_that_fills_during_the_geotiff(small_db, tmp_path, disk):
    free = viper(["estimate", str(small_db / "j.viperdb"), str(small_db / "a.csv"), "--report", "rep"], tmp_path)
    assert free.returncode == 0, free.stderr
    png, tif = (tmp_path / "rep" / "01-a.png").stat().st_size, (tmp_path / "rep" / "01-a-posterior.tif").stat().st_size
    assert tif > 4096
    fill(disk)
    with open(disk / "filler", "r+b") as f:  # room for the picture and the first page of the GeoTIFF
        f.truncate(os.fstat(f.fileno()).st_size - (png // 4096 + 2) * 4096)
    r = viper(["estimate", str(small_db / "j.viperdb"), str(small_db / "a.csv"), "--report", str(disk / "rep")],
              tmp_path)
    assert r.returncode == 1 and r.stdout == ""
    (line,) = r.stderr.splitlines()
    assert line.startswith(f"viper estimate: error: {disk}/rep/01-a-posterior.tif: cannot write: no space left "
                           "on device ("), line
    assert tree(disk / "rep") == {"01-a.png": (tmp_path / "rep" / "01-a.png").read_bytes()}


@pytest.fixture(scope="module")
def session_log(tmp_path_factory, dem, window_db):
    r, _ = run_field_session(small_config(), tmp_path_factory.mktemp("logs"), seed=5, dem=dem, db=window_db)
    return r.log_path


def test_replay_that_fails_midway_leaves_its_folder_as_it_was(session_log, window_db, tmp_path):
    log = tmp_path / "s.mcap"
    shutil.copy(session_log, log)
    args = ["replay", str(log), "--db", str(window_db.path), "--out", "out", "--force"]
    first = viper(args, tmp_path)
    assert first.returncode == 0, first.stderr
    before = tree(tmp_path / "out")
    sizes = {name: len(data) for name, data in before.items()}
    # room for the results log, not for the map's picture written after it
    assert sizes["s.replay.mcap"] < sizes["s.map.png"]
    r = viper(args, tmp_path, file_size_limit=sizes["s.replay.mcap"] + 100)
    assert r.returncode == 1
    (line,) = r.stderr.splitlines()
    assert line.startswith("viper replay: error: ") and ": cannot write: file too large" in line
    assert ".tmp" not in line and "s.map.png" in line
    assert tree(tmp_path / "out") == before  # nothing new, nothing replaced, no staging folder
    # into a new folder: none is left
    r = viper(["replay", str(log), "--db", str(window_db.path), "--out", "new"], tmp_path,
              file_size_limit=sizes["s.replay.mcap"] + 100)
    assert r.returncode == 1 and not (tmp_path / "new").exists()


def test_a_dead_precomputes_temporary_is_removed_by_the_next_precompute_into_that_folder(tmp_path):
    # as a killed precompute leaves it: named by the writer, with the id of a process that has ended
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                           check=True)
    dead = temporary_path(tmp_path / "old.viperdb")
    stale = dead.with_name(dead.name.replace(f".{os.getpid()}-", f".{int(ended.stdout)}-"))
    stale.write_bytes(b"\0" * 100_000)
    # a live writer's temporary (this process, holding its lock) is kept
    live = temporary_path(tmp_path / "busy.viperdb")
    live.write_bytes(b"half")
    fd = os.open(live, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        r = viper(["precompute", "jacksboro", "--search-bounds", BOUNDS, "--max-range", "3000",
                   "--out", "other.viperdb"], tmp_path)
        assert r.returncode == 0, r.stderr
        assert sorted(os.listdir(tmp_path)) == sorted([live.name, "other.viperdb"])
    finally:
        os.close(fd)


def test_a_tiled_build_on_a_local_cluster_leaves_no_dask_scratch(tmp_path):
    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    r = viper(["precompute", "jacksboro", "--search-bounds", BOUNDS, "--max-range", "3000", "--tiles",
               "--tile-nodes", "20,20", "--workers", "1", "--out", "tiled"], tmp_path, env={"TMPDIR": str(scratch)})
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "tiled" / "index.json").is_file()
    assert list(scratch.iterdir()) == []
    with rasterio.Env():  # the tiles are whole databases
        assert len(list((tmp_path / "tiled").glob("tile_*.viperdb"))) == 4
