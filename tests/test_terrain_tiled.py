"""Several DEM files as one mosaic, and the tiled database built on a real Dask cluster.

The test map (two adjacent lon/lat GeoTIFFs sharing an edge column) spans about 31 x 22 km, less
than the horizon's reach: every tile's terrain window is then the whole map, as the single-process
build's is, so every tile node must equal the single build's node exactly.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")
distributed = pytest.importorskip("distributed")

from affine import Affine  # noqa: E402

from appliance.atomic import TMP_MARK  # noqa: E402
from appliance.errors import DemError, OutputError  # noqa: E402
from appliance.terrain.database import build_database, load_database  # noqa: E402
from appliance.terrain.mosaic import open_map, write_vrt  # noqa: E402
from appliance.terrain.tiled import INDEX, build_tiled  # noqa: E402

PIXEL_DEG = 0.005
SIDE = 41  # pixels per tile side; adjacent tiles share one column
NODATA = -9999.0
N_AZ = 32
TILE_NODES = (16, 30)
WEST, NORTH = 10.0, 46.2


def _heights(rows: int, cols: int) -> np.ndarray:
    """Hills and a ridge over the whole mosaic (so both tiles agree on their shared column)."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    z = 800.0 + 400.0 * np.sin(c / 9.0) * np.cos(r / 7.0) + 6.0 * c + 300.0 * np.exp(-((r - 20) ** 2) / 30.0)
    return z.astype(np.float32)


def _write_tile(path: Path, z: np.ndarray, west_centre: float, crs: str = "EPSG:4326") -> Path:
    transform = Affine(PIXEL_DEG, 0.0, west_centre - PIXEL_DEG / 2, 0.0, -PIXEL_DEG, NORTH + PIXEL_DEG / 2)
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=transform, nodata=NODATA) as ds:
        ds.write(z, 1)
    return path


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray]:
    """Two adjacent tiles and the mosaic they make (NaN where both are void)."""
    folder = tmp_path_factory.mktemp("mosaic")
    whole = _heights(SIDE, 2 * SIDE - 1)
    whole[10:13, SIDE - 2 : SIDE + 1] = NODATA  # a void across the seam
    left = _write_tile(folder / "left.tif", whole[:, :SIDE], WEST)
    right = _write_tile(folder / "right.tif", whole[:, SIDE - 1 :], WEST + (SIDE - 1) * PIXEL_DEG)
    expect = whole.astype(np.float64)
    expect[whole == NODATA] = np.nan
    return left, right, expect


@pytest.fixture(scope="module")
def single(tiles, tmp_path_factory):
    """The single-process build of the whole mosaic."""
    folder = tmp_path_factory.mktemp("single")
    source = open_map([str(tiles[0]), str(tiles[1])], folder / "mosaic.vrt")
    build_database(source.load(), folder / "single.viperdb", n_azimuths=N_AZ, progress=None)
    return load_database(folder / "single.viperdb")


def _assert_tiles_equal_single(out: Path, single) -> int:
    index = json.loads((out / INDEX).read_text())
    g = single.grid
    assert index["lattice"] == {k: getattr(g, k) for k in index["lattice"]}
    covered = np.zeros((g.n_rows, g.n_cols), bool)
    for t in index["tiles"]:
        db = load_database(out / t["file"])
        assert (db.grid.n_rows, db.grid.n_cols) == (t["n_rows"], t["n_cols"])
        rows = np.arange(t["row0"], t["row0"] + t["n_rows"])
        cols = np.arange(t["col0"], t["col0"] + t["n_cols"])
        idx = (rows[:, None] * g.n_cols + cols[None, :]).ravel()
        np.testing.assert_array_equal(db.codes, single.codes[idx])
        np.testing.assert_array_equal(db.distance_codes, single.distance_codes[idx])
        np.testing.assert_array_equal(db.offset_deg, single.offset_deg[idx])
        np.testing.assert_array_equal(db.step_deg, single.step_deg[idx])
        assert db.grid.dx_m == g.dx_m and db.grid.dy_m == g.dy_m
        covered[np.ix_(rows, cols)] = True
    assert covered.all()
    return len(index["tiles"])


def test_mosaic_is_one_map_with_the_shared_column_once(tiles, tmp_path):
    left, right, expect = tiles
    dem = open_map([str(left), str(right)], tmp_path / "m.vrt").load()
    assert dem.shape == (SIDE, 2 * SIDE - 1)
    np.testing.assert_array_equal(dem.elevation_m, expect)
    assert np.isnan(dem.elevation_m[11, SIDE - 1])  # the void at the seam stays a void
    window = open_map([str(tmp_path / "m.vrt")], None).window(5, 30, 10, 20)
    np.testing.assert_array_equal(window.elevation_m, expect[5:15, 30:50])


def test_different_crs_refused_naming_both_files(tiles, tmp_path):
    other = _write_tile(tmp_path / "utm.tif", _heights(SIDE, SIDE), 500_000.0, crs="EPSG:32632")
    with pytest.raises(DemError) as err:
        write_vrt([tiles[0], other], tmp_path / "bad.vrt")
    text = str(err.value)
    assert "left.tif" in text and "utm.tif" in text and "\n" not in text
    assert not (tmp_path / "bad.vrt").exists()


def test_tiled_build_equals_single_build_and_resumes(tiles, client, single, tmp_path):
    out = tmp_path / "tiled"
    out.mkdir()
    source = open_map([str(tiles[0]), str(tiles[1])], out / "mosaic.vrt")
    first = build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    n_tiles = _assert_tiles_equal_single(out, single)
    assert n_tiles >= 6 and len(first.built) == n_tiles and not first.kept
    assert first.peak_rss_bytes > 0
    # resume: only the missing tile is built again, the others are left untouched
    gone = out / sorted(first.built)[n_tiles // 2]
    gone.unlink()
    mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("tile_*.viperdb")}
    again = build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    assert again.built == (gone.name,) and len(again.kept) == n_tiles - 1
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("tile_*.viperdb") if p.name != gone.name} == mtimes
    _assert_tiles_equal_single(out, single)
    # other parameters: refused in one line unless forced
    with pytest.raises(OutputError, match="other parameters"):
        build_tiled(source, out, n_azimuths=N_AZ, height_m=5.0, tile_nodes=TILE_NODES, client=client)


def test_tiled_build_from_a_vrt_equals_single_build(tiles, client, single, tmp_path):
    vrt = write_vrt([tiles[0], tiles[1]], tmp_path / "user.vrt")
    out = tmp_path / "tiled"
    out.mkdir()
    build_tiled(open_map([str(vrt)], None), out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    _assert_tiles_equal_single(out, single)


def test_interrupted_build_leaves_no_temporary_files_and_resumes(tiles, client, single, tmp_path):
    out = tmp_path / "tiled"
    out.mkdir()
    source = open_map([str(tiles[0]), str(tiles[1])], out / "mosaic.vrt")

    def interrupt(done: int, total: int, label: str) -> None:
        if done >= 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client, progress=interrupt)
    # a task already running when the build was interrupted finishes its own atomic write
    deadline = time.monotonic() + 30
    while [p for p in out.iterdir() if TMP_MARK in p.name] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not (out / INDEX).exists()
    assert not [p for p in out.iterdir() if TMP_MARK in p.name]
    for tile in out.glob("tile_*.viperdb"):
        load_database(tile)  # every tile under its final name is complete
    # a temporary file left by a killed worker is removed by the next run
    stale = out / f".tile_r000_c000.viperdb.0badf00d{TMP_MARK}.viperdb"
    stale.write_bytes(b"partial")
    result = build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    assert result.kept and result.built
    assert not [p for p in out.iterdir() if TMP_MARK in p.name]
    _assert_tiles_equal_single(out, single)


def test_cli_tiled_build_on_a_running_scheduler(tiles, client, single, tmp_path, capsys):
    from appliance.cli.main import main

    out = tmp_path / "cli"
    argv = ["precompute", str(tiles[0]), str(tiles[1]), "--out", str(out), "--tiles", "--azimuths", str(N_AZ),
            "--tile-nodes", f"{TILE_NODES[0]},{TILE_NODES[1]}", "--scheduler", client.scheduler_info()["address"]]
    assert main(argv) == 0
    _assert_tiles_equal_single(out, single)
    assert "0 kept" in capsys.readouterr().out
    assert main(argv) == 0  # a rerun keeps every tile
    assert "(0 built" in capsys.readouterr().out


def test_cli_refuses_different_crs_in_one_line(tiles, tmp_path, capsys):
    from appliance.cli.main import main

    other = _write_tile(tmp_path / "utm.tif", _heights(SIDE, SIDE), 500_000.0, crs="EPSG:32632")
    code = main(["precompute", str(tiles[0]), str(other), "--out", str(tmp_path / "db.viperdb")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "different CRSs" in err
    assert "left.tif" in err and "utm.tif" in err


def test_tile_wholly_on_nodata_is_left_out_of_the_index(client, tmp_path):
    # one map whose north-west corner, a whole tile of candidates and more, is a void
    z = _heights(SIDE, 2 * SIDE - 1)
    z[: TILE_NODES[0] + 2, : TILE_NODES[1] + 2] = NODATA
    path = _write_tile(tmp_path / "void_corner.tif", z, WEST)
    source = open_map([str(path)], None)
    build_database(source.load(), tmp_path / "single.viperdb", n_azimuths=N_AZ, progress=None)
    single = load_database(tmp_path / "single.viperdb")
    out = tmp_path / "tiled"
    out.mkdir()
    result = build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    index = json.loads((out / INDEX).read_text())
    names = [t["file"] for t in index["tiles"]]
    assert "tile_r000_c000.viperdb" not in names and not (out / "tile_r000_c000.viperdb").exists()
    assert sorted(result.built) == sorted(names) and len(names) >= 5
    assert result.void == ("tile_r000_c000.viperdb",)
    g = single.grid
    for t in index["tiles"]:
        db = load_database(out / t["file"])
        rows = np.arange(t["row0"], t["row0"] + t["n_rows"])
        cols = np.arange(t["col0"], t["col0"] + t["n_cols"])
        idx = (rows[:, None] * g.n_cols + cols[None, :]).ravel()
        np.testing.assert_array_equal(db.codes, single.codes[idx])
        np.testing.assert_array_equal(db.offset_deg, single.offset_deg[idx])
    # the nodes the index leaves out are nodata in the single build too
    assert np.isnan(single.offset_deg.reshape(g.n_rows, g.n_cols)[: TILE_NODES[0], : TILE_NODES[1]]).all()
    # a rerun finds the void tile void again and keeps the others
    again = build_tiled(source, out, n_azimuths=N_AZ, tile_nodes=TILE_NODES, client=client)
    assert not again.built and sorted(again.kept) == sorted(names) and again.void == result.void
    assert json.loads((out / INDEX).read_text())["tiles"] == index["tiles"]


def test_cli_names_the_tiles_left_out_on_nodata(client, tmp_path, capsys):
    from appliance.cli.main import main

    z = _heights(SIDE, 2 * SIDE - 1)
    z[: TILE_NODES[0] + 2, : TILE_NODES[1] + 2] = NODATA
    path = _write_tile(tmp_path / "void_corner.tif", z, WEST)
    argv = ["precompute", str(path), "--out", str(tmp_path / "cli"), "--tiles", "--azimuths", str(N_AZ),
            "--tile-nodes", f"{TILE_NODES[0]},{TILE_NODES[1]}", "--scheduler", client.scheduler_info()["address"]]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "1 wholly on nodata left out" in out
    n_tiles = len(json.loads((tmp_path / "cli" / INDEX).read_text())["tiles"])
    assert f"{n_tiles} tiles ({n_tiles} built, 0 kept, 1 wholly" in out


def test_tiled_build_of_a_map_wholly_on_nodata_fails_in_one_line(client, tmp_path):
    z = np.full((SIDE, SIDE), NODATA, dtype=np.float32)
    z[0, 0] = 500.0  # one valid pixel, so the map itself opens
    path = _write_tile(tmp_path / "void.tif", z, WEST)
    out = tmp_path / "tiled"
    out.mkdir()
    with pytest.raises(DemError, match="nodata") as err:
        build_tiled(open_map([str(path)], None), out, n_azimuths=N_AZ, tile_nodes=(4, 4), client=client,
                    search_bounds=(WEST + 0.05, NORTH - 0.15, WEST + 0.15, NORTH - 0.05))
    assert "\n" not in str(err.value)
    assert not (out / INDEX).exists()
