"""The map a photo is located on (appliance.locating.map_source): a database file, a tiled folder, or a
DEM whose database is built for the search area at a spacing the area's size decides and kept in a
cache folder, on the real DEMs of ../shared/data."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from pyproj import Geod

from appliance.bodies import EARTH
from appliance.errors import DemError, InputError
from appliance.locating.map_source import (
    CACHE_SUBDIR,
    OpenedMap,
    SearchArea,
    area_log_prior,
    default_cache_dir,
    open_map,
)
from appliance.terrain.database import load_database
from appliance.terrain.dem import demo_dem_path, load_dem
from tests.conftest import data_file
from tests.tiled_build import build_tiled

FINSE = "photo_pose_dem/finse/time_lapse_finse_DSM_midfilled.tif"  # 4 m DSM, no CRS tag: EPSG:32632
FINSE_CRS = "EPSG:32632"
MATTERHORN = "dem_geotiff/gmted2010_clips/matterhorn.tiff"  # 24 x 19 cells of 7.5 arc-seconds, EPSG:4326
# the centre of Matterhorn pixel (row 0, col 0), from rasterio's own ds.xy(0, 0)
MATTERHORN_NODE0 = (7.650902777777888, 46.019652777777836)
# a point of the Finse DSM's north-east corner, 80 m from any cell with a height (pixel row 40, col 540)
FINSE_VOID = (60.60928889082653, 7.556000739339257)


def one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def listing(folder) -> list[str]:
    return sorted(os.listdir(folder)) if folder.exists() else []


@pytest.fixture(scope="module")
def matterhorn_map(tmp_path_factory) -> OpenedMap:
    """The whole Matterhorn clip built once (456 nodes) into a cache folder of its own."""
    cache = tmp_path_factory.mktemp("matterhorn-cache")
    return open_map(data_file(MATTERHORN), area=None, cache_dir=cache)


# --- SearchArea ---------------------------------------------------------------------------------


def test_a_circle_holds_the_points_within_its_radius_along_the_geodesic():
    area = SearchArea(circle=(60.6, 7.5, 600.0))
    geod = Geod(ellps="WGS84")
    lon, lat, _ = geod.fwd([7.5] * 4, [60.6] * 4, [0.0, 90.0, 0.0, 225.0], [599.0, 599.0, 601.0, 601.0])
    assert area.contains(np.asarray(lon), np.asarray(lat), EARTH).tolist() == [True, True, False, False]
    assert not area.contains(np.array([np.nan]), np.array([60.6]), EARTH)[0]
    w, s, e, n = area.bounds_lonlat(EARTH)
    assert s < 60.6 - 599 / 111_400 and n > 60.6 + 599 / 111_400  # a degree of latitude is 111.4 km here
    assert w < min(lon) and e > max(lon)


def test_a_box_holds_longitudes_in_any_turn():
    area = SearchArea(box=(350.0, 10.0, 370.0, 20.0))
    inside = area.contains(np.array([5.0, -5.0, 355.0, 20.0, 5.0]), np.array([15.0, 15.0, 15.0, 15.0, 21.0]), EARTH)
    assert inside.tolist() == [True, True, True, False, False]
    assert area.bounds_lonlat(EARTH) == (350.0, 10.0, 370.0, 20.0)


@pytest.mark.parametrize("kwargs, words", [
    ({}, "one of the two"),
    ({"circle": (60.0, 7.0, 100.0), "box": (7.0, 60.0, 8.0, 61.0)}, "one of the two"),
    ({"box": (8.0, 60.0, 7.0, 61.0)}, "--search-bounds 8,60,7,61"),
    ({"circle": (95.0, 7.0, 100.0)}, "--near 95,7,100"),
    ({"circle": (60.0, 7.0, 0.0)}, "radius must be positive"),
    ({"circle": (60.0, math.nan, 10.0)}, "finite"),
])
def test_a_malformed_area_is_one_line_naming_it(kwargs, words):
    with pytest.raises(InputError) as exc:
        SearchArea(**kwargs)
    assert words in one_line(exc)


def test_the_default_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("VIPER_CACHE_DIR", str(tmp_path / "own"))
    assert default_cache_dir() == tmp_path / "own" / CACHE_SUBDIR
    monkeypatch.delenv("VIPER_CACHE_DIR")
    monkeypatch.delenv("CACHE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "viper" / CACHE_SUBDIR
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "viper" / CACHE_SUBDIR


# --- a DEM: spacing, cache, reuse -----------------------------------------------------------------


def test_a_dem_area_is_built_at_the_coarsest_needed_multiple_of_its_cell_and_then_reused(tmp_path):
    """A 600 m box of the 4 m DSM holds about 150 x 150 nodes at 4 m: over a budget of 8,000 it is
    built at 8 m (two cells).  A smaller area inside it (whose own spacing, 4 m, is half that) takes
    that database from the cache untouched; another camera height builds another one."""
    finse = data_file(FINSE)
    cache = tmp_path / "cache"
    first = open_map(finse, area=SearchArea(circle=(60.5990, 7.5400, 300.0)), crs=FINSE_CRS, cache_dir=cache,
                     max_nodes=8000)
    assert first.database is not None and first.tiled is None
    assert first.spacing_m == 8.0
    g = first.database.grid
    assert (g.dx, g.dy) == (8.0, 8.0) and 4000 < g.n_nodes <= 8000
    assert first.built_s is not None and first.built_s > 0
    assert first.cache_path is not None and first.cache_path.parent == cache
    assert first.cache_path.name.startswith("time_lapse_finse_DSM_midfilled-7.53")
    assert "-8m-" in first.cache_path.name and first.cache_path.suffix == ".viperdb"
    assert first.database.height_m == 1.5 and first.database.n_azimuths == 360
    assert listing(cache) == [first.cache_path.name]
    mtime = first.cache_path.stat().st_mtime_ns

    again = open_map(finse, area=SearchArea(circle=(60.5995, 7.5405, 150.0)), crs=FINSE_CRS, cache_dir=cache,
                     max_nodes=8000)
    assert again.built_s is None
    assert again.cache_path == first.cache_path and again.spacing_m == 8.0
    assert again.database is not None and again.database.grid == g
    assert first.cache_path.stat().st_mtime_ns == mtime
    assert listing(cache) == [first.cache_path.name]

    taller = open_map(finse, area=SearchArea(circle=(60.5995, 7.5405, 150.0)), crs=FINSE_CRS, cache_dir=cache,
                      max_nodes=8000, height_m=2.5)
    assert taller.built_s is not None and taller.cache_path != first.cache_path
    assert taller.database is not None and taller.database.height_m == 2.5
    assert taller.spacing_m == 4.0  # the smaller area's own spacing: its DSM cells
    assert listing(cache) == sorted([first.cache_path.name, taller.cache_path.name])


def test_the_whole_dem_is_built_on_its_own_pixels_when_they_fit(matterhorn_map):
    db = matterhorn_map.database
    assert db is not None
    assert (db.grid.n_rows, db.grid.n_cols) == (19, 24)
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(0))
    assert (float(lon), float(lat)) == pytest.approx(MATTERHORN_NODE0, abs=1e-9)
    assert matterhorn_map.spacing_m == pytest.approx(231.6, abs=0.1)  # 7.5" of latitude; 161.4 m of longitude
    assert matterhorn_map.built_s is not None


def test_the_whole_dem_is_coarsened_up_to_four_cells_then_refused(tmp_path):
    matterhorn = data_file(MATTERHORN)
    rx, ry = load_dem(matterhorn).resolution_m()
    cell_m = math.sqrt(rx * ry)  # 193.3 m: the side of a square of a pixel's ground area
    # 456 nodes on its own pixels; at two cells (387 m) the 3.9 x 4.4 km map holds 11 x 12
    opened = open_map(matterhorn, area=None, cache_dir=tmp_path / "c", max_nodes=150)
    assert opened.spacing_m == pytest.approx(2 * cell_m, rel=1e-6)
    assert opened.database is not None and opened.database.grid.n_nodes <= 150
    with pytest.raises(InputError) as exc:
        open_map(matterhorn, area=None, cache_dir=tmp_path / "d", max_nodes=20)
    text = one_line(exc)
    assert "at 4 cells (773.3 m), more than 20" in text and "--near" in text and "--search-bounds" in text
    assert not (tmp_path / "d").exists()


def test_an_area_off_the_dem_is_refused_before_anything_is_built(tmp_path):
    finse = data_file(FINSE)
    cache = tmp_path / "cache"
    with pytest.raises(InputError) as exc:
        open_map(finse, area=SearchArea(circle=(60.70, 7.54, 500.0)), crs=FINSE_CRS, cache_dir=cache)
    text = one_line(exc)
    assert "does not cover --near 60.7,7.54,500" in text
    assert "longitude 7.51646 to 7.56101, latitude 60.58568 to 60.61079" in text
    # its box meets the DSM's north-east corner, the circle does not: the corner is 626 m from its centre
    corner = SearchArea(circle=(60.61079 + 0.004, 7.56101 + 0.008, 600.0))
    with pytest.raises(InputError) as exc:
        open_map(finse, area=corner, crs=FINSE_CRS, cache_dir=cache)
    assert "does not cover --near" in one_line(exc)
    with pytest.raises(InputError) as exc:
        open_map(finse, area=SearchArea(box=(7.0, 60.0, 7.4, 60.5)), crs=FINSE_CRS, cache_dir=cache)
    assert "does not cover --search-bounds 7,60,7.4,60.5" in one_line(exc)
    assert not cache.exists()


def test_a_failed_or_interrupted_build_leaves_the_cache_folder_as_it_was(tmp_path):
    finse = data_file(FINSE)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "notes.txt").write_text("kept\n")
    before = listing(cache)
    with pytest.raises(DemError) as exc:  # every candidate node on nodata
        open_map(finse, area=SearchArea(circle=(*FINSE_VOID, 60.0)), crs=FINSE_CRS, cache_dir=cache)
    assert "nodata" in one_line(exc)
    assert listing(cache) == before

    def interrupt(done: int, total: int, what: str) -> None:
        if done == 10:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        open_map(finse, area=SearchArea(circle=(60.5990, 7.5400, 40.0)), crs=FINSE_CRS, cache_dir=cache,
                 progress=interrupt)
    assert listing(cache) == before


def test_a_damaged_cached_database_is_left_unused_and_built_again(tmp_path):
    matterhorn = data_file(MATTERHORN)
    first = open_map(matterhorn, area=None, cache_dir=tmp_path)
    assert first.cache_path is not None and first.database is not None
    size = first.cache_path.stat().st_size
    data = bytearray(first.cache_path.read_bytes())
    data[size // 2] ^= 0xFF  # a flipped bit in the skylines
    first.cache_path.write_bytes(bytes(data))
    again = open_map(matterhorn, area=None, cache_dir=tmp_path)
    assert again.built_s is not None and again.cache_path == first.cache_path
    assert load_database(first.cache_path, full_check=True).grid == first.database.grid
    assert listing(tmp_path) == [first.cache_path.name]


def test_a_cache_folder_that_cannot_be_made_is_one_line_naming_it(tmp_path):
    (tmp_path / "plain").write_text("a file, not a folder\n")
    with pytest.raises(InputError) as exc:
        open_map(data_file(MATTERHORN), area=None, cache_dir=tmp_path / "plain" / "maps")
    assert f"cache folder {tmp_path / 'plain' / 'maps'}" in one_line(exc)
    with pytest.raises(InputError) as exc:
        open_map(data_file(MATTERHORN), area=None, cache_dir=tmp_path / "plain")
    assert "not a folder" in one_line(exc)


def test_a_map_that_is_not_there_is_one_line(tmp_path):
    with pytest.raises(InputError) as exc:
        open_map(tmp_path / "nowhere.tif", area=None, cache_dir=tmp_path)
    assert "nowhere.tif: no such map" in one_line(exc)


# --- databases given as they are ----------------------------------------------------------------------


def test_a_database_file_is_opened_as_it_is_and_checked_to_cover_the_area(matterhorn_map, tmp_path):
    path = matterhorn_map.cache_path
    assert path is not None
    mtime = path.stat().st_mtime_ns
    opened = open_map(path, area=SearchArea(circle=(46.0, 7.67, 500.0)), crs="EPSG:4326", cache_dir=tmp_path / "x")
    assert opened.database is not None and opened.tiled is None
    assert opened.database.path == str(path) and opened.database.grid == load_database(path).grid
    assert (opened.built_s, opened.cache_path) == (None, None)
    assert opened.spacing_m == pytest.approx(231.6, abs=0.1)
    assert path.stat().st_mtime_ns == mtime and not (tmp_path / "x").exists()
    with pytest.raises(InputError) as exc:
        open_map(path, area=SearchArea(circle=(46.1, 7.6, 100.0)))
    text = one_line(exc)
    assert text.startswith(f"{path} does not cover --near 46.1,7.6,100: its nodes span longitude 7.65090")


def test_a_tiled_folder_is_opened_and_checked_to_meet_the_area(tmp_path):
    dem = load_dem(data_file(MATTERHORN))
    folder = build_tiled(dem, tmp_path / "tiled", dem.bounds_lonlat(), (1, 2), max_range_m=3000.0)
    opened = open_map(folder, area=SearchArea(circle=(46.0, 7.67, 500.0)))
    assert opened.database is None and opened.tiled is not None
    assert len(opened.tiled.tiles) == 2 and opened.tiled.folder == folder
    assert opened.spacing_m == pytest.approx(231.6, abs=0.1)
    assert (opened.built_s, opened.cache_path) == (None, None)
    with pytest.raises(InputError) as exc:
        open_map(folder, area=SearchArea(circle=(46.1, 7.6, 100.0)))
    assert "meet no tile" in one_line(exc)


# --- the area as a prior over a database's nodes ------------------------------------------------------


def test_the_area_prior_is_zero_on_the_nodes_inside_and_minus_infinity_elsewhere(matterhorn_map):
    db = matterhorn_map.database
    assert db is not None
    assert area_log_prior(db, None) is None
    lon0, lat0 = MATTERHORN_NODE0
    # 100 m around node 0: its neighbours lie 161 m east and 232 m south
    prior = area_log_prior(db, SearchArea(circle=(lat0, lon0, 100.0)))
    assert prior is not None and prior.shape == (19 * 24,)
    assert prior[0] == 0.0 and np.isneginf(prior[1:]).all()
    # a box around the first column of nodes (half a cell each side): its 19 nodes, every 24th
    half = 7.5 / 3600 / 2
    prior = area_log_prior(db, SearchArea(box=(lon0 - half, 45.9, lon0 + half, 46.1)))
    assert prior is not None
    assert np.flatnonzero(prior == 0.0).tolist() == list(range(0, 19 * 24, 24))
    with pytest.raises(InputError) as exc:
        area_log_prior(db, SearchArea(box=(8.0, 46.0, 8.1, 46.1)))
    text = one_line(exc)
    assert "does not cover --search-bounds 8,46,8.1,46.1" in text
    assert "longitude 7.65090 to 7.69882, latitude 45.98215 to 46.01965" in text


def test_a_coarse_dem_is_built_finer_than_its_posts_for_a_search_area(tmp_path):
    """jacksboro's posts are about 75 x 92 m: a 1 km circle holds some 500 of them, fewer than a
    search needs when the camera stands near the ground.  The nodes are set twice as fine (the
    first multiple that reaches ``min_nodes``); with no minimum the DEM's own lattice is kept."""
    area = SearchArea(circle=(36.55, -84.25, 1000.0))
    native = open_map(demo_dem_path(), area=area, cache_dir=tmp_path / "a", min_nodes=0)
    assert native.database is not None
    n0 = native.database.grid.n_nodes
    cell = math.sqrt(native.database.grid.dx_m * native.database.grid.dy_m)
    assert 300 < n0 < 1500
    finer = open_map(demo_dem_path(), area=area, cache_dir=tmp_path / "b", min_nodes=2 * n0)
    assert finer.database is not None
    assert finer.spacing_m == pytest.approx(cell / 2, rel=0.02)
    assert 3.0 * n0 < finer.database.grid.n_nodes < 5.0 * n0
