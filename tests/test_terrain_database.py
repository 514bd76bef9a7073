"""The skyline database: contents against the renderer, identity checks, atomic writes."""

from __future__ import annotations

import errno
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.cli.main import main
from appliance.errors import DatabaseError, InputError, OutputError
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from appliance.terrain.quantize import quantize
from tests.conftest import data_file

# A window of jacksboro: small enough for a quick build, with the whole map around it for the horizon.
WINDOW = (-84.30, 36.55, -84.24, 36.60)


@pytest.fixture(scope="module")
def jacksboro_db(tmp_path_factory):
    dem = load_dem("jacksboro")
    path = tmp_path_factory.mktemp("db") / "jacksboro.viperdb"
    build_database(dem, path, search_bounds=WINDOW, progress=None)
    return dem, load_database(path, dem)


def test_header_records_identity_and_grid(jacksboro_db):
    dem, db = jacksboro_db
    h = db.header
    assert h["dem_sha256"] == dem.sha256
    assert h["format_version"] == 3 and h["n_azimuths"] == 360 and h["height_m"] == 1.5
    assert h["body"] == "earth" and h["refraction"] == pytest.approx(0.13)
    # nodes are the DEM's own grid nodes inside the window
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(np.arange(db.grid.n_nodes)))
    assert lon.min() >= WINDOW[0] and lon.max() <= WINDOW[2]
    assert lat.min() >= WINDOW[1] and lat.max() <= WINDOW[3]
    col, row = dem.xy_to_pixel(lon, lat)
    assert np.allclose(col, np.round(col), atol=1e-6) and np.allclose(row, np.round(row), atol=1e-6)
    assert np.allclose(db.ground_m, dem.elevation_m[np.round(row).astype(int), np.round(col).astype(int)])
    # one byte per azimuth
    assert db.codes.dtype == np.uint8 and db.codes.shape == (db.grid.n_nodes, 360)


def test_database_skylines_follow_the_renderer(jacksboro_db):
    dem, db = jacksboro_db
    rng = np.random.default_rng(11)
    errors = []
    for i in rng.choice(db.grid.n_nodes, 12, replace=False):
        lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(i))
        exact = render_skyline(dem, float(lat), float(lon), azimuths_deg=db.azimuths_deg).elevation_deg
        errors.append(db.skylines_deg(i) - exact)
    e = np.concatenate(errors)
    # The sweep gives each node the horizon of a line at most a quarter row beside it beyond two
    # columns; nearer terrain is sampled on the exact ray.
    assert np.sqrt(np.mean(e**2)) < 0.35
    assert np.median(np.abs(e)) < 0.15


def test_terrain_outside_the_search_bounds_shapes_the_horizon(jacksboro_db, tmp_path):
    dem, db = jacksboro_db
    small = tmp_path / "small.viperdb"
    build_database(dem, small, search_bounds=(-84.27, 36.57, -84.265, 36.575), progress=None)
    sdb = load_database(small)
    x, y = sdb.grid.node_xy(0)
    r, c = db.grid.xy_to_rc(x, y)
    j = int(round(float(r))) * db.grid.n_cols + int(round(float(c)))
    assert np.nanmax(np.abs(sdb.skylines_deg(0) - db.skylines_deg(j))) <= 0.1 + 1e-4  # one quantisation step
    assert np.isfinite(sdb.skylines_deg(0)).all()


@settings(max_examples=50, deadline=None)
@given(st.floats(-30, 60), st.floats(0.0, 25.4), st.integers(0, 2**31 - 1))
def test_quantisation_error_at_most_005_deg(base, span, seed):
    rng = np.random.default_rng(seed)
    el = base + rng.uniform(0, 1, (3, 360)) * span
    el[0, rng.integers(0, 360, 20)] = np.nan
    codes, off, step = quantize(el)
    decoded = np.where(codes == 255, np.nan, off[:, None] + step[:, None] * codes)
    assert np.array_equal(np.isnan(decoded), np.isnan(el))
    assert np.nanmax(np.abs(decoded - el)) <= 0.05 + 1e-4


def test_database_of_another_dem_or_version_is_refused(jacksboro_db, tmp_path):
    _, db = jacksboro_db
    other = load_dem(data_file("dem_geotiff/gmted2010_clips/matterhorn.tiff"))
    with pytest.raises(DatabaseError, match="built from DEM"):
        load_database(db.path, other)
    raw = bytearray(open(db.path, "rb").read())
    header = raw[12 : 12 + int(np.frombuffer(bytes(raw[8:12]), np.uint32)[0])]
    patched = header.replace(b'"format_version": 3', b'"format_version": 1')
    assert patched != header
    bad = tmp_path / "v1.viperdb"
    bad.write_bytes(bytes(raw[:12]) + patched + bytes(raw[12 + len(header):]))
    with pytest.raises(DatabaseError, match=r"format version 1, this viper reads version 3; rebuild it with "
                                            r"`viper precompute jacksboro\S* --out v1.viperdb`"):
        load_database(bad)
    junk = tmp_path / "junk.viperdb"
    junk.write_bytes(b"hello")
    with pytest.raises(DatabaseError, match="not a Viper skyline database"):
        load_database(junk)


def test_interrupted_build_leaves_nothing(tmp_path):
    dem = load_dem("jacksboro")
    out = tmp_path / "x.viperdb"

    def interrupt(done, total, label):
        if done == 40:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_database(dem, out, search_bounds=WINDOW, progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_search_bounds_outside_the_dem(tmp_path, capsys):
    dem = load_dem("jacksboro")
    with pytest.raises(InputError, match="outside the DEM"):
        build_database(dem, tmp_path / "x.viperdb", search_bounds=(10, 10, 11, 11), progress=None)
    assert main(["precompute", "jacksboro", "--out", str(tmp_path / "y.viperdb"),
                 "--search-bounds", "10,10,11,11"]) == 2
    assert "outside the DEM" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("rel", [
    "dem_usgs_ascii/SainteHelens.dem",
    "dem_geotiff/msh00_MountStHelens_2000_webmerc.tif",
    "dem_planetary/LDEM_4.LBL",
    "dem_other/topobathy.npz",
])
def test_precompute_cli_on_other_maps(rel, tmp_path, capsys):
    dem = load_dem(data_file(rel))
    w, s, e, n = dem.bounds_lonlat()
    cx, cy = (w + e) / 2, (s + n) / 2
    half = 0.01 if dem.body.name.value == "earth" else 0.3
    if "topobathy" in rel:
        half = 0.1
    # the Moon map's cells are 7.6 km: its range must hold the near field's cells
    reach_m = 20000 if dem.body.name.value == "earth" else 50000
    out = tmp_path / "db.viperdb"
    bounds = f"{cx - half},{cy - half},{cx + half},{cy + half}"
    assert main(["precompute", str(data_file(rel)), "--out", str(out), f"--search-bounds={bounds}",
                 "--max-range", str(reach_m)]) == 0
    db = load_database(out, dem)
    assert db.header["body"] == dem.body.name.value
    i = int(np.nonzero(db.valid_nodes)[0][len(np.nonzero(db.valid_nodes)[0]) // 2])
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(i))
    exact = render_skyline(dem, float(lat), float(lon), azimuths_deg=db.azimuths_deg, max_range_m=reach_m)
    e_ = db.skylines_deg(i) - exact.elevation_deg
    assert np.sqrt(np.nanmean(e_**2)) < 0.5
    assert json.loads(json.dumps(db.header))["n_azimuths"] == 360


def _parts(path):
    raw = bytearray(open(path, "rb").read())
    hlen = int(np.frombuffer(bytes(raw[8:12]), np.uint32)[0])
    return raw, hlen, json.loads(bytes(raw[12 : 12 + hlen]).decode())


def test_checksum_table_follows_the_arrays(jacksboro_db):
    import zlib

    _, db = jacksboro_db
    raw, hlen, header = _parts(db.path)
    spec = header["checksum"]
    start = 12 + hlen
    assert spec["algorithm"] == "crc32" and spec["block_bytes"] == 1 << 20
    assert spec["blocks"] == -(-spec["offset"] // (1 << 20)) >= 1
    assert len(raw) == start + spec["offset"] + 4 * (1 + spec["blocks"])
    table = np.frombuffer(bytes(raw[start + spec["offset"] :]), "<u4")
    assert int(table[0]) == zlib.crc32(bytes(raw[:start]))
    assert int(table[1]) == zlib.crc32(bytes(raw[start : start + min(1 << 20, spec["offset"])]))


def test_a_flipped_bit_is_caught_naming_its_block(jacksboro_db, tmp_path, capsys):
    _, db = jacksboro_db
    raw, hlen, header = _parts(db.path)
    spec = header["checksum"]
    start = 12 + hlen
    last = spec["blocks"] - 1
    for where, block in ((start + 10, 0), (start + spec["offset"] - 3, last)):
        bad = bytearray(raw)
        bad[where] ^= 0x10
        path = tmp_path / f"flip{block}.viperdb"
        path.write_bytes(bytes(bad))
        with pytest.raises(DatabaseError) as err:
            load_database(path)
        lo = block << 20
        hi = min(lo + (1 << 20), spec["offset"]) - 1
        assert str(err.value) == (f"{path}: block {block} of {spec['blocks']} (array bytes {lo}-{hi}) fails its CRC32 "
                                  "check: the file is damaged; rebuild it")
    # a flip inside the header that keeps it valid JSON: 1.5 m becomes 1.7 m
    bad = bytearray(raw)
    i = bad.index(b'"height_m": 1.5')
    bad[i + len('"height_m": 1.')] ^= 0x02
    assert b'"height_m": 1.7' in bad
    path = tmp_path / "header.viperdb"
    path.write_bytes(bytes(bad))
    with pytest.raises(DatabaseError, match="the header fails its CRC32 check"):
        load_database(path)
    rc = main(["estimate", str(path), str(tmp_path / "none.csv")])
    assert rc != 0 and capsys.readouterr().err.count("\n") == 1


def test_a_truncated_checksum_table_is_refused(jacksboro_db, tmp_path):
    _, db = jacksboro_db
    raw, _, _ = _parts(db.path)
    path = tmp_path / "cut.viperdb"
    path.write_bytes(bytes(raw[:-2]))
    with pytest.raises(DatabaseError, match="truncated database"):
        load_database(path)


def test_a_version_2_file_without_checksums_still_loads(jacksboro_db, tmp_path):
    _, db = jacksboro_db
    raw, hlen, header = _parts(db.path)
    spec = header.pop("checksum")
    text = json.dumps(header).encode()
    old = bytes(raw[:12]) + text.ljust(hlen, b" ") + bytes(raw[12 + hlen : 12 + hlen + spec["offset"]])
    path = tmp_path / "old.viperdb"
    path.write_bytes(old)
    again = load_database(path)
    assert "checksum" not in again.header
    np.testing.assert_array_equal(np.asarray(again.codes), np.asarray(db.codes))


# Two nested windows: the inner one sweeps only the lines through its own nodes.  Both are centred
# alike, as a geographic DEM's metric spacing is taken at the centre of the search area.
INNER = (-84.280, 36.565, -84.260, 36.585)
SHORT_REACH_M = 60_000.0


def _node_offset(outer, inner) -> tuple[int, int]:
    """(row, col) of the inner grid's node (0, 0) in the outer grid."""
    r = (outer.grid.y0 - inner.grid.y0) / outer.grid.dy
    c = (inner.grid.x0 - outer.grid.x0) / outer.grid.dx
    assert abs(r - round(r)) < 1e-6 and abs(c - round(c)) < 1e-6
    return int(round(r)), int(round(c))


def test_a_window_build_gives_each_node_the_skyline_of_a_larger_build(tmp_path):
    dem = load_dem("jacksboro")
    build_database(dem, tmp_path / "outer.viperdb", WINDOW, max_range_m=SHORT_REACH_M, progress=None)
    build_database(dem, tmp_path / "inner.viperdb", INNER, max_range_m=SHORT_REACH_M, progress=None)
    outer = load_database(tmp_path / "outer.viperdb", dem)
    inner = load_database(tmp_path / "inner.viperdb", dem)
    assert inner.grid.n_nodes < outer.grid.n_nodes // 4
    r0, c0 = _node_offset(outer, inner)
    g = inner.grid
    rows = (np.arange(g.n_rows)[:, None] + r0) * outer.grid.n_cols + (np.arange(g.n_cols)[None, :] + c0)
    idx = rows.ravel()
    assert np.array_equal(np.asarray(inner.codes), np.asarray(outer.codes)[idx])
    assert np.array_equal(np.asarray(inner.distance_codes), np.asarray(outer.distance_codes)[idx])
    assert np.array_equal(inner.offset_deg, outer.offset_deg[idx], equal_nan=True)
    assert np.array_equal(inner.step_deg, outer.step_deg[idx])


def test_the_build_gives_the_same_bytes_on_one_thread_or_several(tmp_path):
    dem = load_dem("jacksboro")
    for workers in (1, 3):
        build_database(dem, tmp_path / f"w{workers}.viperdb", INNER, max_range_m=SHORT_REACH_M, n_azimuths=72,
                       progress=None, workers=workers)
    assert (tmp_path / "w1.viperdb").read_bytes() == (tmp_path / "w3.viperdb").read_bytes()


def test_the_stored_first_pass_is_what_the_estimator_would_make(jacksboro_db):
    import dataclasses

    from appliance.locating.position import skyline_grid

    _, db = jacksboro_db
    stored = skyline_grid(db)
    fresh = dataclasses.replace(stored, first_pass=None)
    coarse, partial = fresh.coarse
    assert np.array_equal(coarse, np.asarray(db.coarse_codes))
    assert np.array_equal(partial, np.asarray(db.coarse_partial))
    assert np.array_equal(fresh.coarse_tau2(0.0), np.asarray(db.coarse_tau2))
    assert stored.coarse_tau2(0.0) is db.coarse_tau2



# ---- the build's memory: skylines spilled to an unnamed scratch file, written a chunk at a time ----


def _small_build(dem, out, **kw):
    return build_database(dem, out, INNER, max_range_m=SHORT_REACH_M, n_azimuths=72, **kw)


def test_the_bytes_do_not_depend_on_the_chunks(tmp_path, monkeypatch):
    """Chunks of nodes turned, quantised and written one after the other give the file that every
    node at once (the former whole-array build) gives."""
    from appliance.terrain import database

    dem = load_dem("jacksboro")

    def build(name: str, chunk: int, part: int) -> bytes:
        monkeypatch.setattr(database, "CHUNK_NODES", chunk)
        monkeypatch.setattr(database, "THREAD_NODES", part)
        _small_build(dem, tmp_path / name, progress=None, workers=2)
        return (tmp_path / name).read_bytes()

    whole = build("whole.viperdb", 1 << 40, 1 << 40)
    n = load_database(tmp_path / "whole.viperdb").grid.n_nodes
    assert n == 625
    assert build("chunks.viperdb", 97, 13) == whole  # neither divides the node count
    assert build("one.viperdb", n, 1) == whole


def test_a_build_spills_to_a_file_without_a_name_and_leaves_nothing(tmp_path):
    from tests.test_hardening_atomic import open_files_under

    dem = load_dem("jacksboro")
    out = tmp_path / "x.viperdb"
    seen = []

    def look(done, total, label):
        if done == 10:
            seen.append(([p.name for p in tmp_path.iterdir()], open_files_under(tmp_path)))

    _small_build(dem, out, progress=look)
    (names, files), = seen
    assert len(names) == 1 and names[0].startswith(".x.viperdb.")  # the output's temporary alone
    assert sum(f.endswith("(deleted)") for f in files) == 1  # the spill: open, nameless
    assert [p.name for p in tmp_path.iterdir()] == ["x.viperdb"]
    assert open_files_under(tmp_path) == []  # the spill's disk space is back


@pytest.mark.parametrize("fault", ["interrupt", "read error"])
def test_a_build_failing_while_it_writes_leaves_nothing(tmp_path, monkeypatch, fault):
    """A failure after the sweep, while the spilled skylines are read back and the file written:
    nothing is left, the spill's space is back, and an OSError is one line naming the output."""
    from appliance.terrain import database
    from tests.test_hardening_atomic import open_files_under

    dem = load_dem("jacksboro")
    out = tmp_path / "x.viperdb"
    out.write_bytes(b"previous")
    real, calls = database.pread_into, []

    def failing(fd, arr, offset):
        calls.append(offset)
        if len(calls) == 100:
            if fault == "interrupt":
                raise KeyboardInterrupt
            raise OSError(errno.EIO, "Input/output error")
        real(fd, arr, offset)

    monkeypatch.setattr(database, "pread_into", failing)
    if fault == "interrupt":
        with pytest.raises(KeyboardInterrupt):
            _small_build(dem, out, progress=None, workers=1)
    else:
        with pytest.raises(OutputError, match=r"^\S*x.viperdb: cannot write: input/output error$"):
            _small_build(dem, out, progress=None, workers=1)
    assert len(calls) == 100
    assert [p.name for p in tmp_path.iterdir()] == ["x.viperdb"] and out.read_bytes() == b"previous"
    assert open_files_under(tmp_path) == []


def test_a_build_on_a_full_disk_fails_before_its_sweep(tmp_path):
    """The output and the spill are allocated before the sweep: a disk without room for both is a
    one-line error before any azimuth is swept, and leaves nothing."""
    from tests.test_hardening_atomic import mount_tmpfs, open_files_under, snapshot

    dem = load_dem("jacksboro")
    _small_build(dem, tmp_path / "probe.viperdb", progress=None)
    size = (tmp_path / "probe.viperdb").stat().st_size
    spill = 3 * 72 * load_database(tmp_path / "probe.viperdb").grid.n_nodes
    swept: list = []
    for room, message in ((size + spill // 2, "cannot write its scratch file: no space left on device"),
                          (size // 2, "cannot write: no space left on device")):
        where = tmp_path / f"disk{room}"
        mount_tmpfs(where, size=f"{-(-room // 4096) * 4}k")
        try:
            before = snapshot(where)
            with pytest.raises(OutputError, match=f"x.viperdb: {message}"):
                _small_build(dem, where / "x.viperdb", progress=lambda *a: swept.append(a))
            assert swept == [] and snapshot(where) == before and open_files_under(where) == []
        finally:
            subprocess.run(["umount", str(where)], check=False)


# ---- records of verified databases: a changed file is checked again ----


class _CountingZlib:
    """zlib whose crc32 counts its calls."""

    def __init__(self):
        import zlib

        self.real = zlib
        self.calls = 0

    def crc32(self, data, value=0):
        self.calls += 1
        return self.real.crc32(data, value)


@pytest.fixture
def settled(monkeypatch, tmp_path):
    """A cache folder of the test's own, and files recorded however recently they were written (the
    tests wait for the file system's clock to tick before they change a recorded file)."""
    from appliance.terrain import verified

    monkeypatch.setenv("VIPER_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(verified, "SETTLE_NS", 0)
    return tmp_path / "cache" / verified.RECORD_DIR


def _counted_load(monkeypatch, path, **kw):
    from appliance.terrain import storage

    counter = _CountingZlib()
    monkeypatch.setattr(storage, "zlib", counter)
    db = load_database(path, **kw)
    monkeypatch.setattr(storage, "zlib", counter.real)
    return db, counter.calls


def test_a_verified_unchanged_database_is_not_hashed_again(jacksboro_db, tmp_path, monkeypatch, settled):
    _, db = jacksboro_db
    raw, _, header = _parts(db.path)
    path = tmp_path / "copy.viperdb"
    path.write_bytes(bytes(raw))
    blocks = header["checksum"]["blocks"]
    first, calls = _counted_load(monkeypatch, path)
    assert calls == 1 + blocks  # the header, then every block
    records = list(settled.glob("*.json"))
    assert len(records) == 1
    st = path.stat()
    rec = json.loads(records[0].read_text())
    assert rec["identity"] == {"dev": st.st_dev, "ino": st.st_ino, "size": st.st_size, "mtime_ns": st.st_mtime_ns,
                               "ctime_ns": st.st_ctime_ns}
    again, calls = _counted_load(monkeypatch, path)
    assert calls == 1  # the header only
    np.testing.assert_array_equal(np.asarray(again.codes), np.asarray(first.codes))
    np.testing.assert_array_equal(np.asarray(again.coarse_tau2), np.asarray(db.coarse_tau2))
    _, calls = _counted_load(monkeypatch, path, full_check=True)
    assert calls == 1 + blocks


@pytest.mark.parametrize("keep_times", [False, True])
def test_a_database_modified_after_its_verification_is_refused(jacksboro_db, tmp_path, monkeypatch, settled,
                                                               keep_times):
    """A byte changed in place after a recorded verification (with its modification time put back,
    too) is caught by the full check it brings back."""
    import os

    _, db = jacksboro_db
    raw, hlen, header = _parts(db.path)
    path = tmp_path / "changed.viperdb"
    path.write_bytes(bytes(raw))
    load_database(path)
    assert len(list(settled.glob("*.json"))) == 1
    before = path.stat()
    time.sleep(0.05)
    where = 12 + hlen + (1 << 20) + 5  # in block 1
    with path.open("r+b") as fh:
        fh.seek(where)
        old = fh.read(1)
        fh.seek(where)
        fh.write(bytes([old[0] ^ 0x01]))
    if keep_times:
        os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
        assert path.stat().st_mtime_ns == before.st_mtime_ns and path.stat().st_size == before.st_size
    with pytest.raises(DatabaseError, match=f"block 1 of {header['checksum']['blocks']} .* fails its CRC32"):
        load_database(path)


def test_a_database_copied_over_or_replaced_is_checked_again(jacksboro_db, tmp_path, monkeypatch, settled):
    _, db = jacksboro_db
    raw, hlen, _ = _parts(db.path)
    path = tmp_path / "replaced.viperdb"
    path.write_bytes(bytes(raw))
    load_database(path)
    time.sleep(0.05)
    bad = bytearray(raw)
    bad[12 + hlen + 7] ^= 0x40
    path.write_bytes(bytes(bad))  # the same inode, rewritten
    with pytest.raises(DatabaseError, match="block 0 of"):
        load_database(path)
    other = tmp_path / "other.viperdb"
    other.write_bytes(bytes(bad))
    other.replace(path)  # another inode under the same name
    with pytest.raises(DatabaseError, match="block 0 of"):
        load_database(path)


def test_no_record_for_a_file_just_written_nor_beyond_its_age(jacksboro_db, tmp_path, monkeypatch):
    from appliance.terrain import verified

    monkeypatch.setenv("VIPER_CACHE_DIR", str(tmp_path / "cache"))
    _, db = jacksboro_db
    raw, _, header = _parts(db.path)
    path = tmp_path / "fresh.viperdb"
    path.write_bytes(bytes(raw))
    _, calls = _counted_load(monkeypatch, path)
    _, again = _counted_load(monkeypatch, path)
    assert calls == again == 1 + header["checksum"]["blocks"]  # written under SETTLE_NS ago: no record
    assert not (tmp_path / "cache" / verified.RECORD_DIR).exists() or not any(
        (tmp_path / "cache" / verified.RECORD_DIR).iterdir())
    monkeypatch.setattr(verified, "SETTLE_NS", 0)
    load_database(path)
    with path.open("rb") as fh:
        identity = verified.FileIdentity.of_fd(fh.fileno())
    start = 12 + int(np.frombuffer(bytes(raw[8:12]), np.uint32)[0])
    digest = verified.digest_of(bytes(raw[:start]), bytes(raw[start + header["checksum"]["offset"]:]))
    assert verified.is_verified(identity, digest)
    assert not verified.is_verified(identity, "0" * 64)
    assert not verified.is_verified(identity, digest, now_s=time.time() + verified.MAX_AGE_S + 60)


def test_an_unwritable_cache_folder_costs_only_the_full_check(jacksboro_db, tmp_path, monkeypatch):
    from appliance.terrain import verified

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("VIPER_CACHE_DIR", str(blocker))
    monkeypatch.setattr(verified, "SETTLE_NS", 0)
    _, db = jacksboro_db
    raw, _, header = _parts(db.path)
    path = tmp_path / "db.viperdb"
    path.write_bytes(bytes(raw))
    for _ in range(2):
        loaded, calls = _counted_load(monkeypatch, path)
        assert calls == 1 + header["checksum"]["blocks"]
    assert loaded.grid.n_nodes == db.grid.n_nodes


def test_the_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    from appliance.terrain.verified import cache_root

    for name in ("VIPER_CACHE_DIR", "CACHE_DIRECTORY", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert cache_root() == tmp_path / ".cache" / "viper"
    monkeypatch.setenv("XDG_CACHE_HOME", "/x/cache")
    assert cache_root() == Path("/x/cache/viper")
    monkeypatch.setenv("CACHE_DIRECTORY", "/var/cache/viper:/var/cache/other")  # systemd's CacheDirectory=
    assert cache_root() == Path("/var/cache/viper")
    monkeypatch.setenv("VIPER_CACHE_DIR", str(tmp_path / "own"))
    assert cache_root() == tmp_path / "own"
