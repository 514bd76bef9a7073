"""The estimator on a tiled skyline database: placement, the combination across tiles, Dask, errors."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import threading
from collections import Counter

import numba
import numpy as np
import pytest

from appliance.bodies import body_named, geodesic_distance_m
from appliance.cli.main import main
from appliance.errors import DatabaseError, EstimationError
from appliance.estimator import first_pass
from appliance.estimator.likelihood import log_upper_with_others
from appliance.estimator.rescore import MIN_RESCORE, RESCORE_MARGIN_NATS
from appliance.locating import surface_fit, tile_cache, tile_combination, tile_search, tiled_answer, tiled_search
from appliance.locating.position import locate, skyline_grid
from appliance.locating.tile_cache import SearchParams
from appliance.locating.tiled_index import box_around, open_tiled
from appliance.locating.tiled_search import locate_tiled
from appliance.skyline import Skyline, write_skyline_csv
from appliance.terrain.database import load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.tiled_build import build_tiled

AREA = (-84.30, 36.55, -84.26, 36.58)
MAX_RANGE_M = 10_000.0
PARAMS = SearchParams((0.3, 1.2), 4.0)
INTERIOR = (36.5731, -84.2887)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A 2 x 2 tiled database of AREA and the single-file database of the same area."""
    root = tmp_path_factory.mktemp("tiled")
    whole = root / "whole.viperdb"
    folder = build_tiled(load_dem("jacksboro"), root / "db", AREA, (2, 2), MAX_RANGE_M, whole=whole)
    return folder, whole


def _skyline(lat: float, lon: float, seed: int = 0) -> Skyline:
    el = render_skyline(load_dem("jacksboro"), lat, lon, max_range_m=MAX_RANGE_M).elevation_deg
    return Skyline(np.arange(360.0), el + np.random.default_rng(seed).normal(0.0, 0.2, 360))


def _cell_m(path) -> float:
    g = load_database(path).grid
    return math.hypot(g.dx_m, g.dy_m)


def _tile_holding(index, lat: float, lon: float) -> str:
    inside = [t.file for t in index.tiles if t.bounds_lonlat[0] <= lon <= t.bounds_lonlat[2]
              and t.bounds_lonlat[1] <= lat <= t.bounds_lonlat[3]]
    assert len(inside) == 1
    return inside[0]


def test_index_partitions_the_whole_area(built):
    folder, whole = built
    index = open_tiled(folder)
    assert len(index.tiles) == 4
    assert sum(t.n_rows * t.n_cols for t in index.tiles) == load_database(whole).grid.n_nodes


def test_interior_estimate_in_the_right_tile_and_as_the_single_file(built):
    folder, whole = built
    index = open_tiled(folder)
    lat, lon = INTERIOR
    sky = _skyline(lat, lon)
    res = locate_tiled(index, sky, PARAMS)
    cell = _cell_m(whole)
    assert res.tiled.tile == _tile_holding(index, lat, lon)
    assert res.tiled.truth_error_m((lat, lon)) <= 2 * cell
    assert res.tiled.status(index, (lat, lon)) == "ok"
    assert sorted(res.tiled.tiles_searched) == sorted(t.file for t in index.tiles)
    assert math.isclose(sum(res.tiled.tile_share.values()), 1.0, rel_tol=1e-9)
    assert res.tiled.tile_share[res.tiled.tile] > 0.99
    assert res.tiled.log_lower <= res.tiled.log_upper <= 0.0
    # the single-file database over the same area: the same node, the same place
    wdb = load_database(whole)
    single = locate(wdb, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg)
    tdb = load_database(index.path(next(t for t in index.tiles if t.file == res.tiled.tile)))
    node_tiled = tdb.grid.xy_to_lonlat(*tdb.grid.node_xy(res.tiled.best.node))
    node_single = wdb.grid.xy_to_lonlat(*wdb.grid.node_xy(single.result.node))
    assert np.allclose(node_tiled, node_single, atol=1e-9)
    body = body_named(wdb.header["body"])
    assert geodesic_distance_m(res.lat, res.lon, single.lat, single.lon, body) <= 0.1 * cell
    assert res.tiled.ambiguous == single.result.ambiguous


def test_one_tile_combines_to_its_own_estimate(built):
    """Global normalisation over one tile is that tile's own: the same bounds and region."""
    folder, _ = built
    index = open_tiled(folder)
    lat, lon = INTERIOR
    sky = _skyline(lat, lon)
    name = _tile_holding(index, lat, lon)
    tile = next(t for t in index.tiles if t.file == name)
    box = (lon - 1e-4, lat - 1e-4, lon + 1e-4, lat + 1e-4)
    db = load_database(index.path(tile))
    # without learning, a tiled search keeps the sigma it is given on every tile
    given = locate_tiled(index, sky, PARAMS, box=box, learn_noise=False)
    assert given.tiled.tiles_searched == (name,) and given.tiled.noise is None
    own = locate(db, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg, occlusion_weight=PARAMS.occlusion_weight,
                 learn_noise=False)
    assert given.tiled.log_lower == pytest.approx(own.result.log_lower, abs=1e-9)
    assert given.tiled.log_upper == pytest.approx(math.log(own.result.upper), abs=1e-9)
    assert sorted(c.node for c in given.tiled.region) == sorted(int(v) for v in own.result.region_nodes)
    assert given.tiled.ambiguous == own.result.ambiguous
    # learning, its second round is the tile's own search at the noise the first round learned
    res = locate_tiled(index, sky, PARAMS, box=box)
    assert res.tiled.tiles_searched == (name,) and res.tiled.noise is not None
    lo, hi, temper = res.tiled.noise
    learned = locate(db, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg, occlusion_weight=PARAMS.occlusion_weight)
    assert (lo, hi) == pytest.approx(learned.result.sigma_deg, rel=1e-6)
    assert temper == pytest.approx(learned.result.temper, rel=1e-6)
    own = locate(db, sky, (lo, hi), PARAMS.heading_tolerance_deg, occlusion_weight=PARAMS.occlusion_weight,
                 learn_noise=False, temper=temper, allowed_sigma_deg=PARAMS.sigma_deg[1], polish=True)
    assert res.tiled.log_lower == pytest.approx(own.result.log_lower, abs=1e-9)
    assert res.tiled.log_upper == pytest.approx(math.log(own.result.upper), abs=1e-9)
    assert sorted(c.node for c in res.tiled.region) == sorted(int(v) for v in own.result.region_nodes)
    assert res.tiled.ambiguous == own.result.ambiguous
    assert res.tiled.covariance_m2 == pytest.approx(own.result.covariance_m2, abs=1e-4)  # as the record rounds it
    assert (res.lat, res.lon) == (pytest.approx(own.lat, abs=1e-8), pytest.approx(own.lon, abs=1e-8))


def test_near_a_tile_border(built):
    folder, whole = built
    index = open_tiled(folder)
    cell = _cell_m(whole)
    lat, lon = 36.5652, -84.2795
    border_lat = max(t.bounds_lonlat[1] for t in index.tiles)
    body = body_named(load_database(whole).header["body"])
    assert geodesic_distance_m(lat, lon, border_lat, lon, body) < cell  # within a cell of the border
    res = locate_tiled(index, _skyline(lat, lon, seed=1), PARAMS)
    assert res.tiled.truth_error_m((lat, lon)) <= 2 * cell
    # never 'ok' when the truth lies outside the region (its cells and the answer's 95 % ellipse)
    if res.tiled.status(index, (lat, lon)) == "ok":
        assert res.tiled.truth_in_region(index, (lat, lon)) or res.tiled.truth_in_ellipse((lat, lon))
    rec = res.to_json(index, (lat, lon))
    assert rec["tile"] == res.tiled.tile and rec["status"] in ("ok", "ambiguous")
    assert 0.0 <= rec["lower"] <= rec["upper"] <= 1.0


def test_the_first_round_weighs_every_tile_at_the_given_noise(built):
    """The best tile's refinement learns the noise, which puts its posteriors on another scale than
    the other tiles' grid searches: the first round still picks its answer and the tiles to search
    again at the given noise (here, on a tile border, the refined tile weighed at the noise it
    learned would fall below its neighbour, whose grid search carries no region)."""
    folder, whole = built
    index = open_tiled(folder)
    lat, lon = 36.5653, -84.2638
    sky = _skyline(lat, lon)
    res = locate_tiled(index, sky, PARAMS)
    assert res.tiled.noise is not None
    assert res.tiled.truth_error_m((lat, lon)) <= 2 * _cell_m(whole)
    assert res.tiled.status(index, (lat, lon)) == "ok"
    # the learned interval is the noise added (0.2 deg) and the tempering a share
    lo, hi, temper = res.tiled.noise
    assert lo < 0.2 < hi < 0.3 and 0.0 < temper <= 1.0


def test_a_skyline_noisier_than_the_sigma_given_is_a_poor_match_as_on_one_file(built):
    """A skyline with three times the noise the sigma given allows fits no place as it should: the
    second round, weighed at the wider noise the first round learned, still judges the fit by the
    interval given, as the single file's estimate does."""
    folder, whole = built
    index = open_tiled(folder)
    lat, lon = INTERIOR
    el = render_skyline(load_dem("jacksboro"), lat, lon, max_range_m=MAX_RANGE_M).elevation_deg
    sky = Skyline(np.arange(360.0), el + np.random.default_rng(0).normal(0.0, 0.3, 360))
    narrow = SearchParams((0.05, 0.1), 4.0)
    single = locate(load_database(whole), sky, narrow.sigma_deg, narrow.heading_tolerance_deg)
    res = locate_tiled(index, sky, narrow)
    assert res.tiled.noise is not None and res.tiled.noise[1] > 0.2  # learned: about the noise added
    for notes, ambiguous in ((single.result.notes, single.result.ambiguous), (res.tiled.notes, res.tiled.ambiguous)):
        assert ambiguous and any(n.startswith("ambiguous: poor match: residual") for n in notes)
    assert res.to_json(index, (lat, lon))["status"] == "ambiguous"


def test_a_tilted_heads_answer_is_the_single_files(built):
    """A levelled head's errors (a residual tilt of 0.28 deg, noise correlated over 6 deg): the second
    round polishes its best fit at the noise learned, with the tilt, as the single file's search
    does; its answer and covariance are then the single file's, and the truth lies in its ellipse."""
    folder, whole = built
    index = open_tiled(folder)
    lat, lon = 36.5543, -84.2840
    az = np.arange(360.0)
    el = render_skyline(load_dem("jacksboro"), lat, lon, max_range_m=MAX_RANGE_M).elevation_deg
    noise = np.convolve(np.random.default_rng(101).normal(0.0, 0.12, 366), np.ones(6) / math.sqrt(6.0), "valid")[:360]
    sky = Skyline(az, el + noise - 0.055 * np.cos(np.radians(az)) - 0.273 * np.sin(np.radians(az)))
    wdb = load_database(whole)
    single = locate(wdb, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg)
    res = locate_tiled(index, sky, PARAMS)
    body = body_named(wdb.header["body"])
    assert not res.tiled.ambiguous and not single.result.ambiguous
    assert geodesic_distance_m(res.lat, res.lon, single.lat, single.lon, body) < 1.0
    assert res.tiled.covariance_m2 == pytest.approx(single.result.covariance_m2, rel=0.1, abs=0.5)
    assert res.tiled.truth_in_ellipse((lat, lon))


def test_dask_and_in_process_answers_are_identical(built, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    folder, _ = built
    lat, lon = INTERIOR
    sky_path = tmp_path / "s.csv"
    write_skyline_csv(_skyline(lat, lon), sky_path)
    assert main(["estimate", str(folder), str(sky_path), "--json", "--sigma", "0.3,1.2",
                 "--heading-tolerance", "4"]) == 0
    serial = json.loads(capsys.readouterr().out.strip())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        with distributed.Client(cluster) as client:
            index = open_tiled(folder)
            direct = locate_tiled(index, _skyline(lat, lon), PARAMS, client=client).to_json(index)
        assert main(["estimate", str(folder), str(sky_path), "--json", "--sigma", "0.3,1.2",
                     "--heading-tolerance", "4", "--scheduler", cluster.scheduler_address]) == 0
        parallel = json.loads(capsys.readouterr().out.strip())
    in_process = locate_tiled(open_tiled(folder), _skyline(lat, lon), PARAMS).to_json(open_tiled(folder))
    # a local cluster the command makes itself
    assert main(["estimate", str(folder), str(sky_path), "--json", "--sigma", "0.3,1.2",
                 "--heading-tolerance", "4", "--workers", "2"]) == 0
    local = json.loads(capsys.readouterr().out.strip())
    for rec in (serial, parallel, direct, in_process, local):
        rec.pop("elapsed_ms")
    assert parallel == serial
    assert local == serial
    assert direct == in_process
    assert serial["tile"] == direct["tile"]


def test_a_search_box_opens_only_the_tiles_it_meets(built, monkeypatch):
    folder, _ = built
    index = open_tiled(folder)
    opened: list[str] = []
    real = tile_cache.open_tile

    def recording(folder, tile, *a, **k):
        opened.append(tile.file)
        return real(folder, tile, *a, **k)

    monkeypatch.setattr(tile_cache, "open_tile", recording)
    lat, lon = INTERIOR
    sky = _skyline(lat, lon)
    # a box well inside one tile
    box = box_around(lat, lon, 200.0, index.body)
    holding = _tile_holding(index, lat, lon)
    t = next(t for t in index.tiles if t.file == holding)
    assert t.bounds_lonlat[0] < box[0] and box[2] < t.bounds_lonlat[2]
    assert t.bounds_lonlat[1] < box[1] and box[3] < t.bounds_lonlat[3]
    res = locate_tiled(index, sky, PARAMS, box=box)
    assert set(opened) == {holding} and res.tiled.tiles_searched == (holding,)
    # a box across the northern tiles only
    opened.clear()
    north = [t for t in index.tiles if t.bounds_lonlat[1] > min(u.bounds_lonlat[1] for u in index.tiles)]
    s = min(u.bounds_lonlat[1] for u in north)
    locate_tiled(index, sky, PARAMS, box=(AREA[0], s + 1e-4, AREA[2], AREA[3]))
    assert set(opened) == {u.file for u in north}


def test_near_searches_only_the_tiles_within_the_radius(built, tmp_path, capsys):
    folder, _ = built
    index = open_tiled(folder)
    lat, lon = INTERIOR
    sky_path = tmp_path / "s.csv"
    write_skyline_csv(_skyline(lat, lon), sky_path)
    assert main(["estimate", str(folder), str(sky_path), "--json", "--near", f"{lat},{lon},200",
                 "--truth", f"{lat},{lon}"]) == 0
    rec = json.loads(capsys.readouterr().out.strip())
    assert rec["tiles_searched"] == [_tile_holding(index, lat, lon)]
    assert rec["tile"] == _tile_holding(index, lat, lon)
    assert rec["status"] == "ok" and rec["truth"]["error_m"] <= 2 * rec["region"]["cell_size_m"][1]
    # the line a person reads says how sure, as for one file: "ok ± R m", R the record's 95 % radius
    assert main(["estimate", str(folder), str(sky_path), "--near", f"{lat},{lon},200"]) == 0
    line = capsys.readouterr().out.strip()
    assert f"ok ± {rec['radius95_m']:.1f} m" in line and rec["radius95_m"] > 0.0, line


def test_global_upper_bound_is_exact_for_one_heading_and_never_below():
    """Against the bounds computed over the pooled candidates of two made-up tiles."""
    rng = np.random.default_rng(3)
    lo_a = rng.normal(-10, 3, 30)
    up_a = lo_a + rng.uniform(0, 4, 30)
    lo_b = rng.normal(-12, 3, 20)
    s_lo_a = np.logaddexp.reduce(lo_a)
    others = np.logaddexp.reduce(lo_b)
    rest_a = np.array([np.logaddexp.reduce(np.delete(lo_a, i)) for i in range(lo_a.size)])
    u_tile = up_a - np.logaddexp(up_a, rest_a)
    exact = up_a - np.logaddexp(up_a, np.logaddexp(rest_a, others))
    bound = log_upper_with_others(u_tile, up_a, others)
    assert np.allclose(bound, exact, atol=1e-12)
    assert np.array_equal(log_upper_with_others(u_tile, up_a, -math.inf), np.minimum(u_tile, 0.0))
    assert s_lo_a > -math.inf
    # a node of two headings holds the larger u and b of them: a bound on both
    pair_bound = log_upper_with_others(np.array([u_tile[:2].max()]), np.array([up_a[:2].max()]), others)[0]
    assert pair_bound >= exact[:2].max() - 1e-12


def _cli_error(args, capsys) -> tuple[int, str]:
    code = main(args)
    err = capsys.readouterr().err.strip()
    return code, err


def test_bad_folders_fail_in_one_line(built, tmp_path, capsys):
    folder, whole = built
    sky = tmp_path / "s.csv"
    write_skyline_csv(_skyline(*INTERIOR), sky)
    empty = tmp_path / "empty"
    empty.mkdir()
    missing = tmp_path / "missing"
    shutil.copytree(folder, missing)
    gone = open_tiled(folder).tiles[2].file
    (missing / gone).unlink()
    garbled = tmp_path / "garbled"
    shutil.copytree(folder, garbled)
    (garbled / "index.json").write_text("{not json")
    future = tmp_path / "future"
    shutil.copytree(folder, future)
    idx = json.loads((folder / "index.json").read_text())
    (future / "index.json").write_text(json.dumps({**idx, "format_version": 99}))
    foreign = tmp_path / "foreign"
    shutil.copytree(folder, foreign)
    (foreign / "index.json").write_text(json.dumps({**idx, "format": "something-else"}))
    endless = tmp_path / "endless"
    shutil.copytree(folder, endless)
    (endless / "index.json").write_text(json.dumps({**idx, "n_azimuths": math.inf}))
    halved = tmp_path / "halved"
    shutil.copytree(folder, halved)
    (halved / "index.json").write_text(json.dumps({**idx, "n_azimuths": idx["n_azimuths"] + 0.5}))
    cases = {empty: "index.json", missing: gone, garbled: "not valid JSON", future: "version 99", foreign: "format",
             endless: "non-finite 'n_azimuths'", halved: "non-integral 'n_azimuths'"}
    for path, word in cases.items():
        with pytest.raises(DatabaseError):
            open_tiled(path)
        code, err = _cli_error(["estimate", str(path), str(sky)], capsys)
        assert code != 0 and len(err.splitlines()) == 1 and word in err, err
    # an index whose tiles were built otherwise: found when the tile is opened
    other = tmp_path / "other"
    shutil.copytree(folder, other)
    (other / "index.json").write_text(json.dumps({**idx, "n_azimuths": idx["n_azimuths"] // 2}))
    code, err = _cli_error(["estimate", str(other), str(sky)], capsys)
    assert code != 0 and len(err.splitlines()) == 1 and "azimuths" in err, err
    code, err = _cli_error(["estimate", str(whole), str(sky), "--workers", "2"], capsys)
    assert code != 0 and len(err.splitlines()) == 1 and "tiled" in err
    code, err = _cli_error(["estimate", str(folder), str(sky), "--search-bounds", "1,2,3"], capsys)
    assert code != 0 and len(err.splitlines()) == 1
    code, err = _cli_error(["estimate", str(folder), str(sky), "--search-bounds", "10,10,11,11"], capsys)
    assert code != 0 and len(err.splitlines()) == 1 and "no tile" in err


def _made_up_tile(name: str, lon: float, lo: float, up: float) -> tiled_answer.TileOutcome:
    """A tile of one candidate at (lon, 0) with unnormalised log lower and upper posterior lo, up."""
    return tiled_answer.TileOutcome(
        name, None, {"notes": [], "heading_correction_deg": 0.0, "covariance_m2": [[1.0, 0.0], [0.0, 1.0]]}, 0,
        0.0, lon, 0.0, 0.0, lo, up, lo, up, lo,
        math.log(100.0 * 100.0), (100.0, 100.0), False, np.array([0]), np.array([[lon, 0.0]]), np.array([0]),
        np.array([0.0]), np.array([up]), np.array([[lon, 0.0]]))


def test_a_rival_in_another_tile_makes_the_answer_ambiguous():
    """A second tile's mode far away whose upper bound reaches the best's lower one: ambiguous, never ok;
    the same mode far less likely: ok."""
    best = _made_up_tile("a.viperdb", 0.0, -10.0, -8.0)
    rival = _made_up_tile("b.viperdb", 0.01, -11.0, -9.0)
    res = tile_combination.combine([best, rival], "earth")
    assert res.tiled.tile == "a.viperdb" and res.tiled.ambiguous and res.tiled.status() == "ambiguous"
    assert {c.tile for c in res.tiled.region} == {"a.viperdb", "b.viperdb"}
    # the best's bounds over both tiles: lower lo / (lo + the rival's up), upper up / (up + the rival's lo)
    assert res.tiled.log_lower == pytest.approx(-10.0 - np.logaddexp(-10.0, -9.0))
    assert res.tiled.log_upper == pytest.approx(-8.0 - np.logaddexp(-8.0, -11.0))
    assert sum(res.tiled.tile_share.values()) == pytest.approx(1.0)
    weak = _made_up_tile("b.viperdb", 0.01, -40.0, -38.0)
    res = tile_combination.combine([weak, best], "earth")
    assert res.tiled.tile == "a.viperdb" and not res.tiled.ambiguous and res.tiled.status() == "ok"
    # never ok without a covariance that can be formed
    for cov in (None, [[math.nan, 0.0], [0.0, 1.0]]):
        blind = dataclasses.replace(best, record={**best.record, "covariance_m2": cov})
        res = tile_combination.combine([weak, blind], "earth")
        assert not res.tiled.ambiguous and res.tiled.status() == "ambiguous"
    assert [c.tile for c in res.tiled.region] == ["a.viperdb"]
    # as likely but within two cells (200 m) of the best: the same place, not a rival
    near = _made_up_tile("b.viperdb", 0.001, -11.0, -9.0)
    res = tile_combination.combine([best, near], "earth")
    assert {c.tile for c in res.tiled.region} == {"a.viperdb", "b.viperdb"}
    assert not any("holds a place" in n for n in res.tiled.notes)
    assert res.tiled.region_area_m2 == pytest.approx(2 * 100.0 * 100.0)
    failed = tiled_answer.TileOutcome("c.viperdb", "no candidate node has terrain along the measured azimuths")
    assert tile_combination.combine([best, failed], "earth").tiled.tiles_failed == ("c.viperdb",)
    with pytest.raises(EstimationError):
        tile_combination.combine([failed], "earth")


def test_a_fit_on_the_maps_surface_keeps_no_note_of_the_grid_fits_it_overrules():
    """Where the fit on the map's own surface learned the noise, the best tile's own verdicts (its
    grid fit's match, its rival fits on the facets' grid) no longer decide whether the answer is
    ambiguous: an answer that says ok carries none of their 'ambiguous' notes; the combination's
    own (a rival tile) still decide, with their note."""
    rival_note = "ambiguous: exact renders at another place, more than 2 cells away, fit as well as the best"
    best = _made_up_tile("a.viperdb", 0.0, -10.0, -9.0)
    best = dataclasses.replace(best, ambiguous=True,
                               record={**best.record, "notes": ["occluded: 3 of 360", rival_note]})
    weak = _made_up_tile("b.viperdb", 0.01, -40.0, -38.0)
    est = tile_combination.combine_tiles([best, weak], "earth")
    assert est.ambiguous and rival_note in est.notes
    fit = tiled_answer.SurfaceFit(0.0, 0.0, 0.0, 0.0, "EPSG:4326", "a.viperdb", 0, 0.0, 0.2, 24, 0.0, 40,
                                  np.eye(2), (0.18, 0.22, 0.5), 24)
    index = dataclasses.make_dataclass("Index", ["body"])("earth")
    res = surface_fit.with_surface_fit(index, est, fit, 1.2)
    assert not res.ambiguous and res.status() == "ok"
    assert "occluded: 3 of 360" in res.notes and not any(n.startswith("ambiguous") for n in res.notes)
    # a rival tile's note stays with its verdict
    rival = _made_up_tile("b.viperdb", 0.01, -11.0, -9.0)
    res = surface_fit.with_surface_fit(index, tile_combination.combine_tiles([best, rival], "earth"), fit, 1.2)
    assert res.ambiguous and rival_note not in res.notes
    assert any(n.startswith("ambiguous: tile b.viperdb holds a place") for n in res.notes)


def test_refining_only_the_best_tile_gives_the_answer_of_refining_all(built):
    """The second round refines only the best tile; refining every tile must not change the
    combined answer."""
    folder, _ = built
    index = open_tiled(folder)
    for k, (lat, lon) in enumerate((INTERIOR, (36.5652, -84.2795))):
        sky = _skyline(lat, lon, seed=k)
        every = [tile_search.search_tile(str(folder), t, sky, PARAMS, refine=True) for t in index.tiles]
        all_refined = tile_combination.combine(every, index.body).to_json(index, (lat, lon))
        two_rounds = locate_tiled(index, sky, PARAMS, learn_noise=False).to_json(index, (lat, lon))
        all_refined.pop("elapsed_ms")
        two_rounds.pop("elapsed_ms")
        assert two_rounds == all_refined


def test_each_tile_rescores_what_one_search_of_the_whole_lattice_would(built):
    """The floor is the whole lattice's best first-pass bound, and against it the tiles rescore
    the single file's nodes (each at least MIN_RESCORE), not each its own best's neighbourhood."""
    folder, whole = built
    index = open_tiled(folder)
    lat, lon = INTERIOR
    sky = _skyline(lat, lon)
    floors = [tile_search.tile_floor(str(folder), t, sky, PARAMS) for t in index.tiles]
    wdb = load_database(whole)
    sg = skyline_grid(wdb)
    whole_best = first_pass(sg, sky.azimuth_deg, sky.elevation_deg, PARAMS.sigma_deg,
                            PARAMS.heading_tolerance_deg).best_lower
    # these tiles are ordinary builds of parts of the area (tests/tiled_build.py), whose sweeps
    # interpolate the terrain a little differently from the whole's: the bounds agree to well
    # within the rescoring's margin, not to the last digit
    assert abs(max(floors) - whole_best) < 0.01 * RESCORE_MARGIN_NATS
    single = locate(wdb, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg, grid=sg, refine=False)
    alone, floored = [], []
    for t in index.tiles:
        tdb = load_database(index.path(t))
        for out, floor in ((alone, None), (floored, max(floors))):
            pos = locate(tdb, sky, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg, refine=False, rescore_floor=floor)
            out.append(pos.result.rescored)
    assert all(f <= a for f, a in zip(floored, alone, strict=True))
    assert sum(floored) < sum(alone)
    assert single.result.rescored <= sum(floored) <= single.result.rescored + MIN_RESCORE * len(index.tiles)


def _record_loads(monkeypatch) -> list[str]:
    """The names of the tile files the tiled search loads from now on, with none kept mapped yet."""
    loads: list[str] = []
    real = tile_cache.load_database

    def recording(path, *a, **k):
        loads.append(path.name)
        return real(path, *a, **k)

    monkeypatch.setattr(tile_cache, "load_database", recording)
    monkeypatch.setattr(tile_cache, "_open_tiles", {})
    return loads


def test_a_tile_is_mapped_once_per_process_until_it_changes(built, monkeypatch):
    folder, _ = built
    index = open_tiled(folder)
    loads = _record_loads(monkeypatch)
    sky = _skyline(*INTERIOR)
    first = locate_tiled(index, sky, PARAMS).to_json(index, INTERIOR)
    assert sorted(loads) == sorted(t.file for t in index.tiles)
    again = locate_tiled(index, sky, PARAMS).to_json(index, INTERIOR)
    assert len(loads) == len(index.tiles)
    first.pop("elapsed_ms")
    again.pop("elapsed_ms")
    assert again == first
    # a tile written again (a rebuild) is mapped again
    path = index.path(index.tiles[0])
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    locate_tiled(index, sky, PARAMS)
    assert loads[len(index.tiles):] == [index.tiles[0].file]


def test_the_tiles_kept_mapped_stay_within_their_node_budget(built, monkeypatch):
    folder, _ = built
    index = open_tiled(folder)
    loads = _record_loads(monkeypatch)
    a, b = index.tiles[0], index.tiles[1]
    # room for one tile: the second evicts the first, which is then mapped again
    monkeypatch.setattr(tile_cache, "OPEN_TILE_NODES", max(a.n_rows * a.n_cols, b.n_rows * b.n_cols))
    for t in (a, a, b, a):
        tile_cache.open_tile(str(folder), t, None)
    assert loads == [a.file, b.file, a.file]
    assert len(tile_cache._open_tiles) == 1


def test_each_tile_scores_its_first_pass_once_per_search(built, monkeypatch):
    """The floor, the grid search and the refinement all start from a tile's first pass: a search
    makes it once per tile and noise (the given sigma, then the learned one on the tiles searched
    again), and the answer is the one made from scratch in each step."""
    folder, _ = built
    index = open_tiled(folder)
    sky = _skyline(*INTERIOR)
    monkeypatch.setattr(tile_cache, "_first_passes", {})
    made: list[int] = []
    real = tile_cache.first_pass

    def counting(grid, *a, **k):
        made.append(id(grid))
        return real(grid, *a, **k)

    monkeypatch.setattr(tile_cache, "first_pass", counting)
    kept = locate_tiled(index, sky, PARAMS).to_json(index, INTERIOR)
    assert len(set(made)) == len(index.tiles) and len(index.tiles) < len(made) <= 2 * len(index.tiles)
    assert max(Counter(made).values()) == 2
    # with no room to keep any first pass, every round makes its own
    monkeypatch.setattr(tile_cache, "FIRST_PASS_BYTES", 0)
    monkeypatch.setattr(tile_cache, "_first_passes", {})
    made.clear()
    remade = locate_tiled(index, sky, PARAMS).to_json(index, INTERIOR)
    assert len(made) > len(index.tiles)
    kept.pop("elapsed_ms")
    remade.pop("elapsed_ms")
    assert kept == remade


def test_a_first_pass_serves_only_the_skyline_and_grid_it_was_made_for(built):
    from appliance.estimator import estimate

    folder, _ = built
    index = open_tiled(folder)
    db = load_database(index.path(index.tiles[0]))
    grid = skyline_grid(db)
    sky, other = _skyline(*INTERIOR), _skyline(INTERIOR[0] + 0.01, INTERIOR[1])
    args = (grid, sky.azimuth_deg, sky.elevation_deg, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg)
    made = first_pass(*args)
    given = estimate(*args, first=made)
    fresh = estimate(*args)
    assert (given.node, given.row, given.col, given.log_lower) == (fresh.node, fresh.row, fresh.col, fresh.log_lower)
    assert np.array_equal(given.region_nodes, fresh.region_nodes)
    with pytest.raises(ValueError, match="another grid, skyline or search"):
        estimate(grid, other.azimuth_deg, other.elevation_deg, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg,
                 first=made)
    with pytest.raises(ValueError, match="another grid, skyline or search"):
        estimate(*args[:4], None, first=made)  # no compass: another search


def test_tiles_searched_on_threads_give_the_records_of_one_tile_after_the_other(built, monkeypatch):
    """In process the tiles are searched on a pool of threads, each running the compiled kernels on
    its own thread: the records are those of the tiles searched one after the other in this thread,
    and each tile's first pass is still made once per search."""
    folder, _ = built
    index = open_tiled(folder)
    made: list[tuple[int, str, int]] = []
    real = tile_cache.first_pass

    def counting(grid, *a, **k):
        made.append((id(grid), threading.current_thread().name, numba.get_num_threads()))
        return real(grid, *a, **k)

    monkeypatch.setattr(tile_cache, "first_pass", counting)
    records = {}
    for threads in (1, 3):
        monkeypatch.setattr(tiled_search, "TILE_THREADS", threads)
        monkeypatch.setattr(tile_cache, "_first_passes", {})
        made.clear()
        records[threads] = []
        for k, (lat, lon) in enumerate((INTERIOR, (36.5652, -84.2795))):
            rec = locate_tiled(index, _skyline(lat, lon, seed=k), PARAMS).to_json(index, (lat, lon))
            rec.pop("elapsed_ms")
            records[threads].append(rec)
        per_tile = Counter(g for g, _, _ in made)  # once per noise searched at, at each of two places
        assert len(per_tile) == len(index.tiles) and set(per_tile.values()) <= {2, 3, 4}
        assert len(tile_cache._first_passes) == len(made)  # each kept for the search's later steps
        # the rounds over several tiles on the pool (a round over one tile runs in the caller)
        on_pool = {name.startswith("viper-tile") and n == 1 for _, name, n in made}
        assert (True in on_pool) == (threads > 1 and numba.threading_layer() != "workqueue")
    assert records[3] == records[1]


def test_the_best_tile_needs_no_region_but_the_combination_does(built):
    """The grid round leaves every tile's region out: enough to find the best tile, whose refined
    search then brings its region; combining without it is refused, not answered wrongly."""
    folder, _ = built
    index = open_tiled(folder)
    sky = _skyline(*INTERIOR)
    floor = max(tile_search.tile_floor(str(folder), t, sky, PARAMS) for t in index.tiles)
    bare = [tile_search.search_tile(str(folder), t, sky, PARAMS, refine=False, rescore_floor=floor, region=False)
            for t in index.tiles]
    full = [tile_search.search_tile(str(folder), t, sky, PARAMS, refine=False, rescore_floor=floor)
            for t in index.tiles]
    assert all(o.region_nodes.size == 0 and not o.has_region for o in bare)
    best = tile_combination.best_tile(bare)
    assert best == tile_combination.combine(full, index.body).tiled.tile == _tile_holding(index, *INTERIOR)
    with pytest.raises(ValueError, match="without its region"):
        tile_combination.combine(bare, index.body)
    mixed = [f if f.file == best else b for b, f in zip(bare, full, strict=True)]
    combined = tile_combination.combine(mixed, index.body).to_json(index)
    assert combined == tile_combination.combine(full, index.body).to_json(index)
