"""The whole-body tiled database of the LOLA Moon map: facets, the 0/360 seam and the poles.

Only a few facets are built here (a search box chooses them), on a real two-worker Dask
LocalCluster: the facet straddling lon 0 at the equator's north and the north polar cap.  The
whole body's build and its accuracy over twenty places belong to bench/moon_whole_body.py.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from appliance.bodies import MOON, geodesic_distance_m
from appliance.cli.main import main
from appliance.errors import DatabaseError, InputError
from appliance.estimator import confidence
from appliance.locating.tile_cache import SearchParams
from appliance.locating.tiled_index import TiledIndex, open_surface, open_tiled, select_tiles
from appliance.locating.tiled_search import locate_tiled
from appliance.locating.verification import FitSettings, Place, PlaceSearch, distinct_places, fit_place, screen_places
from appliance.skyline import Skyline, write_skyline_csv
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from appliance.terrain.mosaic import open_map
from appliance.terrain.whole_body import (
    build_whole_body,
    default_max_range_m,
    facet_grids,
    facet_keep,
    facets_meeting,
    plan_facets,
)
from tests.conftest import data_file

distributed = pytest.importorskip("distributed")

LOLA = "dem_planetary/LDEM_4.LBL"
N_AZ = 360  # the default: with fewer, the first pass averages runs of four azimuths over too wide an arc
HEIGHT_M = 1.5
PARAMS = SearchParams((0.3, 1.2), 4.0)
SEAM_BOX = (-1.0, 2.0, 1.0, 3.0)  # meets only the band [0, 15) facet centred on lon 0
CAP_BOX = (10.0, 79.0, 11.0, 80.0)  # meets only the north cap


@pytest.fixture(scope="module")
def moon():
    path = data_file(LOLA)
    return open_map([str(path)], None), load_dem(path)


@pytest.fixture(scope="module")
def seam_db(moon, client, tmp_path_factory):
    source, _ = moon
    out = tmp_path_factory.mktemp("seam")
    res = build_whole_body(source, out, SEAM_BOX, n_azimuths=N_AZ, client=client)
    assert len(res.built) == 1 and not res.kept
    return out


@pytest.fixture(scope="module")
def cap_db(moon, tmp_path_factory):
    """The north cap, built by the command line (its own local cluster of two workers)."""
    out = tmp_path_factory.mktemp("cap") / "db"
    assert main(["precompute", str(data_file(LOLA)), "--tiles", "--whole-body", "--out", str(out),
                 "--search-bounds", ",".join(str(v) for v in CAP_BOX), "--azimuths", str(N_AZ),
                 "--workers", "2"]) == 0
    return out


def _rng_points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lon = rng.uniform(-180.0, 540.0, n)
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    return lon, lat


def test_facets_cover_every_point_once():
    facets = plan_facets(MOON.radius_m)
    lon, lat = _rng_points(200_000)
    # and the edges themselves: box edges, band edges, the cap edges, the poles and the seam
    edges_lon = np.unique(np.concatenate([[f.box[0], f.box[2]] for f in facets]))
    edges_lat = np.unique(np.concatenate([[f.box[1], f.box[3]] for f in facets]))
    g_lon, g_lat = np.meshgrid(np.concatenate([edges_lon, edges_lon + 360.0, [0.0, 360.0, -180.0]]), edges_lat)
    lon = np.concatenate([lon, g_lon.ravel()])
    lat = np.concatenate([lat, g_lat.ravel()])
    count = sum(f.contains(lon, lat).astype(int) for f in facets)
    assert count.min() == 1 and count.max() == 1
    kinds = [f.kind for f in facets]
    assert kinds[0] == "south-cap" and kinds[-1] == "north-cap" and kinds.count("band") == len(facets) - 2
    # boxes about as wide on the ground as high: more near the equator than near the caps
    per_band = {f.box[1]: 0 for f in facets if f.kind == "band"}
    for f in facets:
        if f.kind == "band":
            per_band[f.box[1]] += 1
    assert per_band[0.0] == 24 and per_band[60.0] == 12 and per_band[-75.0] == 12
    # the first box of every band straddles the 0/360 seam
    assert all(f.box[0] < 0.0 < f.box[2] for f in facets if f.file.endswith("_c000.viperdb") and f.kind == "band")


def test_facet_nodes_partition_the_body(moon):
    """Every facet keeps only its box's nodes: summed over the facets, the node count is the body's
    area over a cell's, and the cap keeps the pole."""
    _, dem = moon
    spacing = min(dem.resolution_m())
    facets = plan_facets(dem.body.radius_m)
    kept = 0
    for f in facets:
        cand, _, _ = facet_grids(dem, f, spacing, 50_000.0)
        keep = facet_keep(cand, f)
        lon, lat = cand.xy_to_lonlat(*cand.node_xy(np.nonzero(keep)[0]))
        assert f.contains(lon, lat).all()
        kept += int(keep.sum())
        if f.kind == "north-cap":
            pole = cand.n_nodes // 2  # odd rows and columns: the middle node is the grid's origin, the pole
            assert cand.n_rows % 2 == 1 and keep[pole]
            assert cand.xy_to_lonlat(*cand.node_xy(pole))[1] == pytest.approx(90.0, abs=1e-9)
    area = 4.0 * math.pi * dem.body.radius_m**2
    assert kept == pytest.approx(area / spacing**2, rel=0.01)


def test_map_is_read_across_the_seam_and_the_poles(moon):
    _, dem = moon
    assert dem.whole_body
    # across the seam: both sides of lon 0 (= 360) are the same place
    lat = np.linspace(-80.0, 80.0, 17)
    a = dem.sample_lonlat(np.full_like(lat, -0.05), lat)
    b = dem.sample_lonlat(np.full_like(lat, 359.95), lat)
    assert np.isfinite(a).all() and np.allclose(a, b)
    # beyond the last row of pixel centres (0.125 deg from the pole) the map still has heights, and
    # two points facing each other across the pole, 0.05 deg from it, are read from the same pixels
    lon = np.arange(0.0, 360.0, 15.0)
    for pole in (90.0, -90.0):
        near = dem.sample_lonlat(lon, np.full_like(lon, pole - math.copysign(0.01, pole)))
        assert np.isfinite(near).all()
        z1 = dem.sample_lonlat(np.array([30.0]), np.array([pole - math.copysign(0.05, pole)]))
        z2 = dem.sample_lonlat(np.array([210.0]), np.array([pole - math.copysign(0.05, pole)]))
        edge = dem.elevation_m[0 if pole > 0 else -1]
        assert abs(float(z1[0] - z2[0])) < float(np.ptp(edge))
    assert default_max_range_m(dem) == 260_000.0  # sqrt(2 x 1737.4 km x 19.4 km of relief)


def test_select_tiles_compares_longitudes_modulo_360(seam_db):
    index = open_tiled(seam_db)
    (tile,) = index.tiles
    assert tile.bounds_lonlat[0] < 0.0 < tile.bounds_lonlat[2]
    for box in ((-1.0, 5.0, 1.0, 6.0), (355.0, 5.0, 356.0, 6.0), (6.0, 5.0, 8.0, 6.0), (-365.0, 5.0, -364.0, 6.0)):
        assert select_tiles(index, box) == [tile]
    with pytest.raises(InputError, match="meet no tile"):
        select_tiles(index, (10.0, 5.0, 20.0, 6.0))
    with pytest.raises(InputError, match="meet no tile"):
        select_tiles(index, (-1.0, 20.0, 1.0, 21.0))


def _rms_vs_exact(dem, db, nodes, reach: float) -> np.ndarray:
    """RMS (deg) of each node's stored skyline against the exact renderer's."""
    out = []
    for i in nodes:
        lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(int(i)))
        exact = render_skyline(dem, float(lat), float(lon), HEIGHT_M, db.azimuths_deg, reach).elevation_deg
        out.append(float(np.sqrt(np.mean((db.skylines_deg(int(i)) - exact) ** 2))))
    return np.asarray(out)


def test_seam_facet_sees_both_sides(moon, seam_db, tmp_path):
    """Nodes either side of lon 0 have full skylines, equal to those of a single build centred on
    the facet's centre (same CRS, same nodes), whose terrain is the map read across the seam."""
    _, dem = moon
    index = open_tiled(seam_db)
    db = load_database(index.path(index.tiles[0]))
    reach = index.max_range_m
    assert reach == 260_000.0 and db.header["grid"]["dx"] == pytest.approx(min(dem.resolution_m()) / 2.0)
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(np.arange(db.grid.n_nodes)))
    lon = (lon + 180.0) % 360.0 - 180.0
    valid = db.valid_nodes
    assert valid.sum() > 0.8 * db.grid.n_nodes and not valid.all()  # the rectangle's corners are left out
    assert np.array_equal(valid, (lat >= 0.0) & (lat < 15.0) & (lon >= -7.5) & (lon < 7.5))
    single = tmp_path / "single.viperdb"
    build_database(dem, single, (-0.3, 7.35, 0.3, 7.65), db.grid.dx, HEIGHT_M, N_AZ, None, reach, workers=2)
    sdb = load_database(single)
    assert sdb.grid.crs == db.grid.crs and sdb.grid.dx == pytest.approx(db.grid.dx)
    sx, sy = sdb.grid.node_xy(np.arange(sdb.grid.n_nodes))
    fr, fc = db.grid.xy_to_rc(sx, sy)
    assert np.allclose(fr, np.round(fr), atol=1e-6) and np.allclose(fc, np.round(fc), atol=1e-6)
    f_nodes = (np.round(fr) * db.grid.n_cols + np.round(fc)).astype(int)
    s_lon = (sdb.grid.xy_to_lonlat(sx, sy)[0] + 180.0) % 360.0 - 180.0
    assert (s_lon < 0.0).any() and (s_lon > 0.0).any()  # both sides of the seam
    mine, theirs = db.skylines_deg(f_nodes), sdb.skylines_deg(np.arange(sdb.grid.n_nodes))
    assert np.isfinite(mine).all() and np.isfinite(theirs).all()
    # equal up to the codes' quantisation (about 0.1 deg steps here): the two sweeps run on different
    # lattices (the facet's rectangle, the single build's), so a horizon may round the other way
    diff = np.abs(mine - theirs)
    step = float(np.max(db.step_deg[f_nodes]))
    assert np.sqrt(np.mean(diff**2)) < step and np.percentile(diff, 99) <= 3.0 * step and diff.max() < 1.0
    # and the facet's nodes just west and east of the seam agree with the exact renderer as well as
    # a single build's do on this map (its 7.6 km cells make the near field coarse)
    near = np.nonzero(valid & (np.abs(lon) < 0.3))[0]
    assert near.size >= 10 and ((lon[near] < 0).any() and (lon[near] > 0).any())
    assert np.median(_rms_vs_exact(dem, db, near[:: max(1, near.size // 12)], reach)) < 0.8


def test_polar_cap_covers_the_pole(moon, cap_db):
    _, dem = moon
    index = open_tiled(cap_db)
    (tile,) = index.tiles
    assert tile.bounds_lonlat == (-180.0, 75.0, 180.0, 90.0)
    assert json.loads((cap_db / "index.json").read_text())["whole_body"]["cap_deg"] == 75.0
    db = load_database(index.path(tile))
    pole = int(np.argmin(np.hypot(*db.grid.node_xy(np.arange(db.grid.n_nodes)))))
    assert db.grid.xy_to_lonlat(*db.grid.node_xy(pole))[1] == pytest.approx(90.0, abs=1e-9)
    assert np.isfinite(db.skylines_deg(pole)).all()
    assert abs(float(db.ground_m[pole]) - float(dem.sample_lonlat(np.array([0.0]), np.array([90.0]))[0])) < \
        float(np.ptp(dem.elevation_m[0]))
    lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(np.arange(db.grid.n_nodes)))
    assert np.array_equal(db.valid_nodes, lat >= 75.0)
    assert np.isfinite(db.skylines_deg(np.nonzero(lat >= 89.0)[0])).all()  # around the pole: terrain every way
    # nodes around the 80th parallel, every way from the pole: their skylines face the right way
    # (the grid's convergence there is as large as the longitude); the 7.6 km grid smooths the map's
    # east-west detail (its pixels are 1.3 km wide at 80 deg), so they stand a degree or two below
    # the exact renderer's, as a single build's nodes there do
    ring = np.nonzero(np.abs(lat - 80.0) < 0.1)[0]
    shifts, rms = [], []
    for i in ring[:: max(1, ring.size // 12)]:
        exact = render_skyline(dem, float(lat[i]), float(lon[i]), HEIGHT_M, db.azimuths_deg,
                               index.max_range_m).elevation_deg
        mine = db.skylines_deg(int(i))
        by_shift = [float(np.mean((np.roll(mine, k) - exact) ** 2)) for k in range(-N_AZ // 4, N_AZ // 4)]
        shifts.append(math.sqrt(by_shift[N_AZ // 4] / min(by_shift)))  # turning them would not help
        rms.append(math.sqrt(by_shift[N_AZ // 4]))
    assert np.median(shifts) < 1.1 and np.median(rms) < 2.5


def _read(az: np.ndarray, truth: np.ndarray, seed: int) -> Skyline:
    """A skyline read by a compass off by up to 4 deg, with 0.2 deg of noise, at 1-deg azimuths."""
    rng = np.random.default_rng(seed)
    out = np.arange(360.0)
    err = rng.uniform(-4.0, 4.0)
    el = np.interp((out + err) % 360.0, az, truth, period=360.0) + rng.normal(0.0, 0.2, out.size)
    return Skyline(out, el)


def test_estimate_near_the_seam_within_two_cells(moon, seam_db):
    """The exact renderer's skyline just west of lon 0, read with compass error and noise."""
    _, dem = moon
    lat, lon = 6.3, -0.4
    index = open_tiled(seam_db)
    az = np.arange(360.0)
    sky = _read(az, render_skyline(dem, lat, lon, HEIGHT_M, az, index.max_range_m).elevation_deg, seed=3)
    res = locate_tiled(index, sky, PARAMS)
    cell = load_database(index.path(index.tiles[0])).grid.dx_m  # the facet's spacing
    assert res.tiled.truth_error_m((lat, lon)) <= 2.0 * cell
    assert res.tiled.tile == index.tiles[0].file


def test_estimate_in_the_cap_within_two_cells(moon, cap_db):
    """Near 80 deg, where the cap's grid north turns with longitude: a node's own skyline, read
    with compass error and noise, is found again at its place, on either side of lon 180.

    (On the grid alone the exact renderer's skyline there is not: the cap's 3.8 km grid smooths the
    map's east-west detail, 1.3 km pixels at 80 deg, and its skylines stand 0.3-1 deg RMS off the
    renderer's; fitted on the map's own surface it is, test below.  Places whose horizon lies
    mostly within a cell, such as 79 N 135 E, are ambiguous by design: their skyline moves too
    much within a cell to single one out.)"""
    _, dem = moon
    index = open_tiled(cap_db)
    db = load_database(index.path(index.tiles[0]))
    for lat, lon, seed in ((80.0, 200.3, 3), (80.0, 20.0, 4), (82.0, 300.0, 5)):
        r, c = db.grid.xy_to_rc(*db.grid.lonlat_to_xy(lon, lat))
        node = int(round(float(r))) * db.grid.n_cols + int(round(float(c)))
        n_lon, n_lat = db.grid.xy_to_lonlat(*db.grid.node_xy(node))
        res = locate_tiled(index, _read(db.azimuths_deg, db.skylines_deg(node), seed), PARAMS)
        assert res.tiled.truth_error_m((float(n_lat), float(n_lon))) <= 2.0 * db.grid.dx_m
        assert geodesic_distance_m(lat, lon, res.lat, res.lon, dem.body) <= 3.0 * db.grid.dx_m


def test_index_records_the_map_for_fits_on_its_surface(moon, seam_db, tmp_path):
    source, dem = moon
    index = open_tiled(seam_db)
    rec = index.raw["surface"]
    assert rec["path"] == str(data_file(LOLA).resolve()) and rec["sha256"] == source.sha256
    surface, why_not = open_surface(index)
    assert why_not is None and surface is not None and surface.shape == dem.shape
    # a map moved away or changed since the build: the search stays on the grid, and says why
    moved = TiledIndex(index.folder, index.tiles, index.n_azimuths, index.height_m, index.max_range_m, index.body,
                       {**index.raw, "surface": {**rec, "path": str(tmp_path / "gone.LBL")}})
    assert open_surface(moved) == (None, f"its map {tmp_path / 'gone.LBL'} is not there")
    changed = TiledIndex(index.folder, index.tiles, index.n_azimuths, index.height_m, index.max_range_m, index.body,
                         {**index.raw, "surface": {**rec, "sha256": "0" * 64}})
    surface, why_not = open_surface(changed)
    assert surface is None and "has changed since the build" in str(why_not)
    folder_map = TiledIndex(index.folder, index.tiles, index.n_azimuths, index.height_m, index.max_range_m,
                            index.body, {**index.raw, "surface": {**rec, "path": str(tmp_path)}})
    assert open_surface(folder_map) == (None, f"its map {tmp_path} is not there")
    bad = TiledIndex(index.folder, index.tiles, index.n_azimuths, index.height_m, index.max_range_m, index.body,
                     {**index.raw, "surface": {"path": 3}})
    with pytest.raises(DatabaseError, match="malformed 'surface'"):
        open_surface(bad)
    regional = TiledIndex(index.folder, index.tiles, index.n_azimuths, index.height_m, index.max_range_m,
                          index.body, {k: v for k, v in index.raw.items() if k != "surface"})
    assert open_surface(regional) == (None, None)


def test_fit_on_the_maps_surface_finds_the_renderers_skyline_in_the_cap(moon, cap_db):
    """The exact renderer's skyline near 80 deg, where the cap's grid smooths the map's 1.3 km
    east-west pixels and its own skylines stand 0.3-1 deg off the renderer's: fitted on the map
    itself, the answer lands within two cells, the compass's error is recovered, and the fit's
    residual is the noise's."""
    _, dem = moon
    index = open_tiled(cap_db)
    surface, why_not = open_surface(index)
    assert why_not is None
    cell = load_database(index.path(index.tiles[0])).grid.dx_m
    az = np.arange(360.0)
    for lat, lon, seed in ((80.0, 200.3, 3), (79.6, 20.0, 4), (81.0, 300.0, 5)):
        sky = _read(az, render_skyline(dem, lat, lon, HEIGHT_M, az, index.max_range_m).elevation_deg, seed)
        err_deg = np.random.default_rng(seed).uniform(-4.0, 4.0)
        res = locate_tiled(index, sky, PARAMS, surface=surface)
        assert res.tiled.fit is not None
        assert res.tiled.truth_error_m((lat, lon)) <= 2.0 * cell
        assert abs(res.heading_correction_deg - err_deg) < 0.5
        assert res.tiled.fit.rms_deg < 0.3
        rec = res.to_json(index, (lat, lon))
        assert (rec["lat"], rec["lon"]) == (round(res.lat, 8), round(res.lon, 8))
        assert rec["surface_fit"]["places"] == res.tiled.fit.places >= 1
        assert rec["surface_fit"]["screened"] == res.tiled.fit.screened >= res.tiled.fit.places
        inside = res.tiled.truth_in_ellipse((lat, lon)) or res.tiled.truth_in_region(index, (lat, lon))
        assert rec["status"] == ("ok" if not res.tiled.ambiguous and inside else "ambiguous")
        # the noise learned from the fit on the map (0.2 deg read, the renderers' own difference
        # besides) and the covariance at it, whose 99.9 % ellipse holds the truth (the renderers'
        # difference moves the fit a little beyond what the residuals tell: bench/results/moon_whole_body.md
        # gives the 95 % ellipse's share)
        lo, hi, temper = res.tiled.noise
        assert 0.1 < lo <= hi < 1.0 and 0.0 < temper <= 1.0
        assert rec["covariance_m2"] == [[round(float(v), 4) for v in row] for row in res.tiled.fit.covariance_m2]
        assert rec["radius95_m"] > 0.0
        body = dem.body
        az_deg, _, dist = body.geod.inv(res.lon, res.lat, lon, lat)
        offset = dist * np.array([np.sin(np.radians(az_deg)), np.cos(np.radians(az_deg))])
        assert confidence.inside_ellipse(offset, res.tiled.fit.covariance_m2, level=0.999)


def test_fit_on_the_maps_surface_gives_the_same_answer_on_dask(moon, cap_db, client):
    _, dem = moon
    index = open_tiled(cap_db)
    surface, _ = open_surface(index)
    az = np.arange(360.0)
    sky = _read(az, render_skyline(dem, 79.6, 20.0, HEIGHT_M, az, index.max_range_m).elevation_deg, 4)
    here = locate_tiled(index, sky, PARAMS, surface=surface).to_json(index)
    there = locate_tiled(index, sky, PARAMS, client=client, surface=surface).to_json(index)
    for rec in (here, there):
        rec.pop("elapsed_ms")
    assert "surface_fit" in here and here == there


def test_estimate_command_fits_on_the_recorded_map_or_warns(moon, cap_db, tmp_path, capsys):
    _, dem = moon
    lat, lon = 80.0, 200.3
    index = open_tiled(cap_db)
    az = np.arange(360.0)
    sky_path = tmp_path / "sky.csv"
    write_skyline_csv(_read(az, render_skyline(dem, lat, lon, HEIGHT_M, az, index.max_range_m).elevation_deg, 3),
                      sky_path)
    assert main(["estimate", str(cap_db), str(sky_path), "--json", "--sigma", "0.3,1.2",
                 "--heading-tolerance", "4"]) == 0
    fitted = json.loads(capsys.readouterr().out.strip())
    assert "surface_fit" in fitted
    assert geodesic_distance_m(lat, lon, fitted["lat"], fitted["lon"], dem.body) <= 2.0 * fitted["region"][
        "cell_size_m"][0]
    # the same database after its map went away: the grid's answer, with a warning
    moved = tmp_path / "moved"
    moved.mkdir()
    for t in index.tiles:
        (moved / t.file).symlink_to(index.path(t))
    raw = dict(index.raw, surface={**index.raw["surface"], "path": str(tmp_path / "gone.LBL")})
    (moved / "index.json").write_text(json.dumps(raw))
    assert main(["estimate", str(moved), str(sky_path), "--json", "--sigma", "0.3,1.2",
                 "--heading-tolerance", "4"]) == 0
    out = capsys.readouterr()
    grid = json.loads(out.out.strip())
    assert "surface_fit" not in grid and "not fitted on the map's own surface" in out.err
    assert f"{tmp_path / 'gone.LBL'} is not there" in out.err


def test_fit_on_the_maps_surface_without_a_compass(moon):
    """A skyline turned by 40 deg, with no compass to bound the heading: the fit near a place 2 km
    off finds the position and the turn."""
    _, dem = moon
    lat, lon, turn = -15.06, 162.69, 40.0
    az = np.arange(360.0)
    truth = render_skyline(dem, lat, lon, HEIGHT_M, az, 150_000.0).elevation_deg
    rng = np.random.default_rng(8)
    sky = Skyline(az, np.interp((az + turn) % 360.0, az, truth, period=360.0) + rng.normal(0.0, 0.2, az.size))
    settings = FitSettings(HEIGHT_M, 360, 150_000.0, 0.0, 3790.42, (0.3, 1.2), None)
    start = Place("t", 0, lat + math.degrees(2000.0 / MOON.radius_m), lon)
    fit = fit_place(dem, sky, start, settings)
    assert fit is not None
    assert geodesic_distance_m(lat, lon, fit.lat, fit.lon, dem.body) < 500.0
    assert abs(fit.heading_correction_deg - turn) < 0.5 and fit.rms_deg < 0.3


def test_distinct_places_keep_the_likeliest_of_each_neighbourhood(moon):
    _, dem = moon
    # along the equator, 1 deg of longitude is 30.3 km on the Moon
    ranked = [Place("a", 0, 0.0, 10.0), Place("a", 1, 0.0, 10.1), Place("b", 2, 0.0, 12.0), Place("a", 3, 0.0, 9.95),
              Place("b", 4, 0.0, 12.05), Place("c", 5, 0.0, 14.0)]
    assert [p.node for p in distinct_places(ranked, 5, 5000.0, dem)] == [0, 2, 5]
    assert [p.node for p in distinct_places(ranked, 2, 5000.0, dem)] == [0, 2]
    assert [p.node for p in distinct_places(ranked, 9, 1000.0, dem)] == [0, 1, 2, 3, 4, 5]
    assert distinct_places([], 3, 1000.0, dem) == []


def test_distinct_places_match_the_plain_greedy_choice(moon):
    """The places kept, found on the sphere first and from a prefix of the ranking, are those of
    the plain greedy choice measuring every place on the body, also when the first 5,000 places
    crowd into one neighbourhood (the prefix then has to grow)."""
    _, dem = moon
    rng = np.random.default_rng(11)
    crowd_lat, crowd_lon = rng.normal(30.0, 0.02, 5000), rng.normal(100.0, 0.02, 5000)
    spread_lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, 6000)))
    spread_lon = rng.uniform(0.0, 360.0, 6000)
    near_lat, near_lon = rng.normal(-10.0, 0.5, 3000), rng.normal(200.0, 0.5, 3000)
    lat = np.concatenate([crowd_lat, spread_lat, near_lat])
    lon = np.concatenate([crowd_lon, spread_lon, near_lon])
    ranked = [Place("t", i, float(a), float(b)) for i, (a, b) in enumerate(zip(lat, lon))]

    def plain(count: int, apart_m: float) -> list[int]:
        alive = np.ones(lat.size, dtype=bool)
        kept: list[int] = []
        while len(kept) < count and alive.any():
            k = int(np.argmax(alive))
            kept.append(k)
            _, _, d = dem.body.geod.inv(np.full(lat.size, lon[k]), np.full(lat.size, lat[k]), lon, lat)
            alive &= np.asarray(d) > apart_m
        return kept

    for count, apart_m in ((30, 7580.8), (400, 7580.8), (60, 40_000.0)):
        got = [p.node for p in distinct_places(ranked, count, apart_m, dem)]
        assert got == plain(count, apart_m)
        assert len(got) == count
        assert got[0] == 0 and got[1] >= 5000  # the crowd, within 3 km, gives one place


def test_screen_ranks_the_place_seen_from_first(moon):
    """Places of a whole-body search screened on the map: the skyline seen 1.5 m above
    15.06 S 162.69 E, read with a compass off by up to 4 deg, screens lowest at a place 1.5 km from
    where it was seen, below places three to twelve node spacings away and far ones, and its cost
    is that of residuals within twice the noise (0.2 deg): the compass's error is turned away,
    though the nearest look lies 1.5 km from where it was seen."""
    _, dem = moon
    lat, lon = -15.06, 162.69
    az = np.arange(360.0)
    sky = _read(az, render_skyline(dem, lat, lon, HEIGHT_M, az, 150_000.0).elevation_deg, 6)
    spacing = 3790.42
    settings = FitSettings(HEIGHT_M, 360, 150_000.0, 0.0, spacing, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg)
    deg = math.degrees(spacing / MOON.radius_m)
    truth = Place("t", 0, lat + math.degrees(1500.0 / MOON.radius_m), lon)
    others = [Place("t", k, lat + dy * deg, lon + dx * deg / math.cos(math.radians(lat)))
              for k, (dy, dx) in enumerate(((3, 0), (0, -3), (-4, 4), (6, 6), (-12, 0), (0, 12)), start=1)]
    others += [Place("t", 10, 42.82, 59.37), Place("t", 11, -41.89, 166.3), Place("t", 12, 6.53, 204.12)]
    screened = screen_places(dem, sky, others[:3] + [truth] + others[3:], settings)
    assert [p.node for _, p in screened][0] == 0
    cost, _ = screened[0]
    sig_ref = 0.5 * sum(PARAMS.sigma_deg)
    assert math.sqrt(cost * sig_ref**2 / 360.0) < 0.4  # RMS residual, deg
    assert screened[1][0] > 1.5 * cost
    # the same look without a compass: the heading is found over the whole circle
    free = FitSettings(HEIGHT_M, 360, 150_000.0, 0.0, spacing, PARAMS.sigma_deg, None)
    turned = Skyline(sky.azimuth_deg, np.roll(sky.elevation_deg, 40))
    look = PlaceSearch(dem, turned, truth, free, screening=True)
    assert min(look.quick_look(dr, dc) for dr in (-0.5, 0.0, 0.5) for dc in (-0.5, 0.0, 0.5)) == pytest.approx(
        min(PlaceSearch(dem, sky, truth, free, screening=True).quick_look(dr, dc) for dr in (-0.5, 0.0, 0.5)
            for dc in (-0.5, 0.0, 0.5)), rel=1e-6)


def test_whole_body_refusals(moon, tmp_path, capsys):
    source, _ = moon
    assert main(["precompute", str(data_file(LOLA)), "--whole-body", "--out", str(tmp_path / "x")]) == 2
    assert "give --tiles too" in capsys.readouterr().err
    jack = open_map(["jacksboro"], None)
    with pytest.raises(InputError, match="not a map of the whole body"):
        build_whole_body(jack, tmp_path)
    assert facets_meeting(plan_facets(MOON.radius_m), (170.0, -1.0, 190.0, 1.0))
