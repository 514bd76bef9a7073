"""How sure an estimate says it is: noise and independent azimuths learned from residuals, the
credible region's modes, the covariance in metres, and the fix that carries them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from scipy.stats import chi2

from appliance.estimator import confidence
from appliance.locating.position import altitude_m, fix_status, locate, truth_in_ellipse, truth_in_region
from appliance.logbook.messages import LocationFix
from appliance.skyline import Skyline
from appliance.terrain.horizon import render_skyline
from tests.conftest import data_file


def test_white_residuals_are_all_independent_and_smooth_ones_are_not():
    rng = np.random.default_rng(1)
    white = rng.normal(0.0, 0.2, 360)
    assert confidence.independent_azimuths(white) == pytest.approx(360, rel=0.25)
    # a Gaussian autocorrelation of 6 azimuths: sum over all lags of rho = sqrt(2 pi) 6, so n / (sqrt(2 pi) 6)
    smooth = gaussian_filter1d(rng.normal(0.0, 1.0, 3600), 6.0 / math.sqrt(2.0), mode="wrap")[:360]
    expected = 360 / (math.sqrt(2 * math.pi) * 6.0)
    assert confidence.independent_azimuths(smooth) == pytest.approx(expected, rel=0.5)
    # a tilt left in the residuals: one sinusoid over the circle is worth a handful of azimuths
    tilt = 0.3 * np.cos(np.radians(np.arange(360.0)))
    assert confidence.independent_azimuths(tilt) <= 10
    # missing azimuths are left out, not read as zeros
    holed = white.copy()
    holed[100:200] = np.nan
    assert confidence.independent_azimuths(holed) == pytest.approx(260, rel=0.25)


def test_white_residuals_barely_correlate_from_one_azimuth_to_the_next_and_smooth_ones_do():
    rng = np.random.default_rng(3)
    white = rng.normal(0.0, 0.5, 360)
    # 1 / sqrt(360) = 0.053 is the correlation's standard error
    assert abs(confidence.lag_one_correlation(white)) < 0.2
    # a Gaussian autocorrelation of 6 azimuths: exp(-1 / 72) = 0.986 at one azimuth
    smooth = gaussian_filter1d(rng.normal(0.0, 1.0, 3600), 6.0 / math.sqrt(2.0), mode="wrap")[:360]
    assert confidence.lag_one_correlation(smooth) > 0.9
    # about zero: an offset common to the residuals (a skyline raised by trees) counts as correlated
    assert confidence.lag_one_correlation(white + 1.0) > 0.7
    # missing azimuths are left out, not read as zeros; none left, no correlation
    holed = white + 1.0
    holed[::3] = np.nan
    assert confidence.lag_one_correlation(holed) > 0.7
    assert math.isnan(confidence.lag_one_correlation(np.full(360, np.nan)))


def test_the_sigma_interval_covers_the_true_sigma_at_its_level():
    rng = np.random.default_rng(2)
    hits = 0
    trials = 2000
    for _ in range(trials):
        n = int(rng.integers(20, 200))
        rms = math.sqrt(float(np.mean(rng.normal(0.0, 0.3, n) ** 2)))
        lo, hi = confidence.sigma_interval(rms, n, floor_deg=1e-6)
        hits += lo <= 0.3 <= hi
    assert 0.93 <= hits / trials <= 0.97
    # against the exact chi-square interval (Wilson-Hilferty within a per cent at 30 dof)
    lo, hi = confidence.sigma_interval(1.0, 30, floor_deg=1e-6)
    assert lo == pytest.approx(math.sqrt(30 / chi2.ppf(0.975, 30)), rel=0.01)
    assert hi == pytest.approx(math.sqrt(30 / chi2.ppf(0.025, 30)), rel=0.01)
    assert confidence.sigma_interval(0.001, 300, floor_deg=0.05) == (0.05, 0.05)


def test_the_credible_region_holds_its_level_and_splits_into_modes():
    n_rows, n_cols = 40, 50
    rr, cc = np.mgrid[0:n_rows, 0:n_cols]
    near = np.exp(-((rr - 10) ** 2 + (cc - 12) ** 2) / (2 * 1.5**2))
    far = np.exp(-((rr - 30) ** 2 + (cc - 40) ** 2) / (2 * 1.0**2))
    one = (near / near.sum()).ravel()
    region = confidence.credible_nodes(one)
    assert one[region].sum() >= 0.95
    assert one[region].sum() - one[region].min() < 0.95  # the fewest: one node less falls short
    single = confidence.modes(one, n_rows, n_cols, 10.2, 11.9)
    assert single.rivals.size == 0 and single.main_mass >= 0.95
    # the spread of the mode is the blob's (1.5 cells per axis), plus the cell's own
    assert np.sqrt(np.diag(single.main_covariance_cells)) == pytest.approx([1.5, 1.5], rel=0.15)
    two = (0.7 * near / near.sum() + 0.3 * far / far.sum()).ravel()
    split = confidence.modes(two, n_rows, n_cols, 10.0, 12.0)
    assert split.rival_mass == pytest.approx(0.3, abs=0.03)
    rows, cols = np.divmod(split.rivals, n_cols)
    assert np.all(np.hypot(rows - 30, cols - 40) < 4)
    # a far place holding less than the 5 % a 95 % region leaves out anyway is no rival, though the
    # region (the most probable nodes first) takes its peak in
    faint = (0.97 * near / near.sum() + 0.03 * far / far.sum()).ravel()
    kept = confidence.modes(faint, n_rows, n_cols, 10.0, 12.0)
    assert np.any(np.hypot(*np.divmod(kept.region, n_cols) - np.array([[30], [40]])) < 1.5)
    assert kept.rivals.size == 0 and kept.rival_mass == 0.0
    # more than that inside the region: a rival
    rival = confidence.modes((0.92 * near / near.sum() + 0.08 * far / far.sum()).ravel(), n_rows, n_cols, 10.0, 12.0)
    assert rival.rivals.size > 0 and 0.05 < rival.rival_mass <= 0.08
    # a place within the answer's own ellipse (``reach_cells``) is its spread, not a rival
    assert confidence.modes(two, n_rows, n_cols, 10.0, 12.0, reach_cells=40.0).rivals.size == 0


def test_few_independent_azimuths_widen_the_ellipse_as_students_t():
    from scipy import stats

    # sigma learned from 12 independent azimuths, three taken by the fit: t with 9 degrees of freedom,
    # whose squared radius at 95 % is 2 F(2, 9) against chi-square's 5.99
    nu = 12 - confidence.FITTED_PARAMETERS
    assert confidence.few_azimuths_factor(12) == pytest.approx(2 * stats.f.ppf(0.95, 2, nu) / 5.991465, rel=1e-6)
    assert confidence.few_azimuths_factor(40, level=0.99) == pytest.approx(
        2 * stats.f.ppf(0.99, 2, 40 - confidence.FITTED_PARAMETERS) / stats.chi2.ppf(0.99, 2), rel=1e-6)
    factors = [confidence.few_azimuths_factor(n) for n in (6, 10, 20, 50, 200, 100_000)]
    assert all(a > b for a, b in zip(factors, factors[1:]))
    assert factors[-1] == pytest.approx(1.0, abs=1e-4)


def test_a_fit_with_no_residual_left_still_tempers_by_a_positive_share():
    from appliance.estimator.noise import learned_noise

    # every azimuth taken for an occluder: no residual, the search's sigma, and a tempering that
    # keeps the bounds finite
    lo, hi, temper = learned_noise(np.full(360, np.nan), 0.02, 0.5)
    assert lo < 0.5 < hi and temper == 1.0
    few = np.full(360, np.nan)
    few[[10, 200]] = [0.1, -0.2]
    assert 0.0 < learned_noise(few, 0.02, 0.5)[2] <= 1.0


def test_the_envelope_of_two_covariances_holds_both_along_every_direction():
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = (m @ m.T + 1e-3 * np.eye(2) for m in rng.normal(size=(2, 2, 2)))
        out = confidence.envelope(a, b)
        x = rng.normal(size=(100, 2))
        va, vb, vo = (np.einsum("ij,jk,ik->i", x, c, x) for c in (a, b, out))
        assert np.all(vo >= np.maximum(va, vb) * (1 - 1e-9))
        # and no wider than the two together
        assert np.all(vo <= (va + vb) * (1 + 1e-9))
    a = np.diag([4.0, 1.0])
    np.testing.assert_allclose(confidence.envelope(a, 0.5 * a), a)
    np.testing.assert_allclose(confidence.envelope(a, 3.0 * a), 3.0 * a)


def test_the_sector_jackknife_is_the_spread_of_the_fits_made_without_each_sector():
    """On a linear model (elevations linear in row, col, heading, eye), the jackknife from the fit's
    stored sector pulls and curvatures equals the one made by fitting again without each sector."""
    from appliance.estimator.exact import Fit, _sectors
    from appliance.estimator.noise import sector_jackknife

    rng = np.random.default_rng(5)
    n, sigma = 360, 0.2
    J = rng.normal(size=(n, 4)) * np.array([0.5, 0.5, 1.0, 0.1])
    u = rng.uniform(0.5, 1.0, n)
    explained = rng.uniform(size=n) > 0.1
    # errors that differ by sector: a sector-wide offset plus white noise
    y = np.repeat(rng.normal(0.0, 0.3, 12), 30) + rng.normal(0.0, sigma, n)
    P = np.diag([0.0, 0.0, 0.0, 1.0 / 0.5**2])
    w = np.where(explained, u, 0.0)

    def solve(weights):
        return np.linalg.solve(J.T @ (J * weights[:, None]) / sigma**2 + P, J.T @ (weights * y) / sigma**2)

    theta = solve(w)
    r = np.where(explained, y - J @ theta, 0.0)
    pulls, curvatures = _sectors(J, w, r, explained, 1.0)
    fit = Fit(0.0, 0.0, 0.0, 0.0, n, 1, curvature=J.T @ (J * w[:, None]), prior_information=P,
              sector_pulls=pulls, sector_curvatures=curvatures)
    got = sector_jackknife(fit, sigma)
    moves = np.array([solve(np.where(np.arange(n) // 30 == k, 0.0, w))[:2] - theta[:2] for k in range(12)])
    moves -= moves.mean(axis=0)
    np.testing.assert_allclose(got, 11.0 / 12.0 * moves.T @ moves, rtol=1e-9, atol=1e-15)
    # the sectors disagree far more than the white noise alone would have them
    model = np.linalg.inv(J.T @ (J * w[:, None]) / sigma**2 + P)[:2, :2]
    assert np.trace(got) > 3.0 * np.trace(model)
    # the answer's covariance takes the sectors' spread where it exceeds the curvature's
    from dataclasses import replace

    from appliance.estimator.noise import tempered_covariance

    alone = tempered_covariance(replace(fit, sector_pulls=None, sector_curvatures=None), sigma, 0.5)
    both = tempered_covariance(fit, sigma, 0.5)
    assert alone is not None and both is not None
    x = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])
    widest = np.maximum(np.einsum("ij,jk,ik->i", x, alone, x),
                        np.einsum("ij,jk,ik->i", x, got, x))
    assert np.all(np.einsum("ij,jk,ik->i", x, both, x) >= widest * (1 - 1e-9))
    assert np.trace(both) > 1.2 * np.trace(alone)


def test_grid_covariance_turns_into_east_and_north():
    cov_rc = np.diag([4.0, 1.0])  # rows (south) 2 cells, columns (east) 1 cell, 1 sigma
    en = confidence.grid_to_east_north(cov_rc, dx_m=30.0, dy_m=90.0, convergence_deg=0.0)
    assert en == pytest.approx(np.diag([30.0**2, (2 * 90.0) ** 2]))
    # grid north 90 degrees east of true north: the grid's y axis is true east
    turned = confidence.grid_to_east_north(cov_rc, dx_m=30.0, dy_m=90.0, convergence_deg=90.0)
    assert turned == pytest.approx(np.diag([(2 * 90.0) ** 2, 30.0**2]), abs=1e-6)
    assert confidence.radius_m(en) == pytest.approx(math.sqrt(5.991) * 180.0, rel=1e-3)
    assert confidence.ellipse_area_m2(en) == pytest.approx(math.pi * 5.991 * 30.0 * 180.0, rel=1e-3)
    assert confidence.inside_ellipse(np.array([0.0, 2.4 * 180.0]), en)
    assert not confidence.inside_ellipse(np.array([0.0, 2.5 * 180.0]), en)


def _read(sky: Skyline, rng: np.random.Generator, noise_deg: float, compass_deg: float) -> Skyline:
    az = sky.azimuth_deg
    el = np.interp((az + compass_deg) % 360.0, az, sky.elevation_deg, period=360.0)
    return Skyline(az, el + rng.normal(0.0, noise_deg, az.size))


def test_a_right_answer_says_ok_with_a_covariance_that_holds_the_truth(dem, window_db):
    rng = np.random.default_rng(3)
    lat, lon = 36.5851, -84.2613
    truth = render_skyline(dem, lat, lon, 1.5)
    pos = locate(window_db, _read(truth, rng, 0.1, 1.7), (0.3, 0.8), 4.0)
    r = pos.result
    assert not r.ambiguous and fix_status(pos).startswith("ok ± ")
    # sigma learned from the residuals: near the 0.1 deg of noise, not the search's 0.3-0.8
    assert 0.06 <= r.sigma_deg[0] <= 0.1 <= r.sigma_deg[1] <= 0.16
    assert r.independent_azimuths > 200  # white noise: nearly every azimuth counts
    assert truth_in_ellipse(window_db, pos, (lat, lon)) and truth_in_region(window_db, pos, (lat, lon))
    radius = confidence.radius_m(r.covariance_m2)
    assert radius < 0.5 * math.sqrt(window_db.grid.dx_m * window_db.grid.dy_m)  # well within a cell
    # the altitude: the map's surface under the answer plus the camera's height
    ground = float(dem.sample_lonlat(lon, lat))
    assert altitude_m(window_db, pos) == pytest.approx(ground + 1.5, abs=3.0)
    # a calibrated sensor's sigma is the floor of what is learned, and widens the covariance
    floored = locate(window_db, _read(truth, np.random.default_rng(3), 0.1, 1.7), (0.3, 0.8), 4.0,
                     sigma_floor_deg=0.3).result
    assert floored.sigma_deg[0] == pytest.approx(0.3)
    assert confidence.radius_m(floored.covariance_m2) > 1.5 * radius


def test_a_skyline_from_no_place_on_the_map_never_says_ok(window_db):
    rng = np.random.default_rng(4)
    az = np.arange(360.0)
    foreign = Skyline(az, 4.0 + 3.0 * np.sin(np.radians(2 * az)) + rng.normal(0.0, 0.1, 360))
    pos = locate(window_db, foreign, (0.3, 0.8), 4.0)
    assert pos.result.ambiguous and fix_status(pos) == "ambiguous"
    assert any(n.startswith("ambiguous") for n in pos.result.notes)  # and says why


def test_the_fix_carries_the_covariance_and_the_altitude(dem, window_db):
    from appliance.outputs.records import estimate_fix

    lat, lon = 36.5851, -84.2613
    pos = locate(window_db, render_skyline(dem, lat, lon, 1.5), (0.3, 0.8), 4.0)
    fix = estimate_fix(window_db, pos, 123, "estimate")
    assert fix.position_covariance_type == LocationFix.KNOWN
    cov = np.array(fix.position_covariance).reshape(3, 3)
    assert cov[:2, :2] == pytest.approx(pos.result.covariance_m2)
    assert cov[2, 2] > 0 and fix.altitude == pytest.approx(altitude_m(window_db, pos))
    rec = pos.to_json(window_db, truth=(lat, lon))
    assert np.array(rec["covariance_m2"]) == pytest.approx(pos.result.covariance_m2, abs=1e-3)
    assert rec["status"] == "ok" and rec["truth"]["error_m"] < rec["radius95_m"] + 5.0


def _fixture_skyline(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A measured skyline kept in tests/data (azimuth_deg,elevation_deg rows under four comment and header
    lines) on the whole-degree azimuths, NaN where nothing was measured."""
    rows = np.loadtxt(Path(__file__).parent / "data" / name, delimiter=",", comments="#", skiprows=4)
    az = np.arange(360.0)
    el = np.full(360, np.nan)
    el[np.round(rows[:, 0]).astype(int) % 360] = rows[:, 1]
    return az, el


@pytest.fixture(scope="module")
def forest_db(tmp_path_factory):
    """The database of bench/world_gap.py's forest window, built from the bare SRTM tile N44W072."""
    from appliance.terrain.database import build_database, load_database
    from appliance.terrain.dem import load_dem

    tile = load_dem(data_file("dem_srtm_hgt/N44W072.hgt"))
    path = tmp_path_factory.mktemp("forest") / "forest.viperdb"
    build_database(tile, path, search_bounds=(-71.35, 44.20, -71.20, 44.35), progress=None)
    return load_database(path, tile)


def test_a_skyline_raised_by_trees_the_map_lacks_never_says_ok_at_the_wrong_place(forest_db):
    """A camera in a forest clearing sees treetops over much of its skyline; fitted as terrain, the
    skyline matches a place 280 m away with the compass's error at its bound.  Searched again with half of
    the skyline allowed to stand above the map, the best place moves: the answer is ambiguous, never ok."""
    from appliance.estimator import estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m

    db = forest_db
    az, el = _fixture_skyline("forest_clearing_skyline.csv")
    res = estimate(skyline_grid(db), az, el)
    truth = (44.21750349, -71.27563203)
    pos = place(db, res)
    cells = truth_error_m(db, pos, truth) / math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert res.ambiguous or cells <= 2.0
    assert res.ambiguous and any("what the map lacks decides" in n for n in res.notes)
    # the same skyline with a forest's share of occluders as the prior: the place the trees allow
    hidden = estimate(skyline_grid(db), az, el, occlusion_weight=0.5)
    assert math.hypot(hidden.row - res.row, hidden.col - res.col) > 2.0


def test_a_clean_skyline_is_not_lost_to_a_place_that_fits_it_poorly_everywhere(dem, tmp_path):
    """A skyline detected under cumulus (211 of 360 azimuths, within a hundredth of a degree of the truth's)
    whose place lies between nodes where the skyline swings by degrees: the search at the default interval
    (0.3-0.8 deg) weighs every azimuth loosely and settles 16 km away on a fit of 0.4 deg RMS, which used to say
    ok.  Searched again narrower, the true place fits to the noise and is the answer."""
    from appliance.estimator import estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m
    from appliance.terrain.database import build_database, load_database

    path = tmp_path / "north.viperdb"
    build_database(dem, path, search_bounds=(-84.40, 36.58, -84.20, 36.74), progress=None)
    db = load_database(path, dem)
    az, el = _fixture_skyline("cumulus_skyline.csv")
    truth = (36.711339, -84.254391)
    grid = skyline_grid(db)
    res = estimate(grid, az, el)
    assert truth_error_m(db, place(db, res), truth) < 10.0 and not res.ambiguous
    assert res.rms_residual_deg < 0.05
    # the search at the default interval alone (the narrower one is what finds the place)
    wide = estimate(grid, az, el, learn_noise=False)
    assert truth_error_m(db, place(db, wide), truth) > 1000.0


def test_a_better_fit_at_the_same_place_found_by_the_narrower_search_is_the_answer(dem, tmp_path):
    """A levelled head's skyline (residual tilt, compass error, correlated noise, occluders) whose search at
    the default interval settles 1.6 cells from the truth on a fit of 0.61 deg RMS.  The narrower search
    finds the true place's fit, about five times closer, within two cells of the first: being that near
    does not make the poorer fit the answer."""
    from appliance.estimator import estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m
    from appliance.terrain.database import build_database, load_database

    path = tmp_path / "west.viperdb"
    build_database(dem, path, search_bounds=(-84.47, 36.54, -84.34, 36.64), progress=None)
    db = load_database(path, dem)
    grid = skyline_grid(db)
    az, el = _fixture_skyline("levelled_head_skyline.csv")
    truth = (36.59032114, -84.40465454)
    res = estimate(grid, az, el)
    assert truth_error_m(db, place(db, res), truth) < 10.0 and not res.ambiguous
    assert res.rms_residual_deg < 0.2
    # the search at the default interval alone: a poor fit over a hundred metres off
    wide = estimate(grid, az, el, learn_noise=False)
    assert truth_error_m(db, place(db, wide), truth) > 100.0 and wide.rms_residual_deg > 0.4


def test_rival_places_the_first_search_found_stand_when_the_narrower_one_fits_better_there(forest_db):
    """A forest camera whose skyline fits best 350 m from the truth (the trees and the map's height noise
    move it).  The search at the default interval finds exact renders at another place that fit as well:
    ambiguous.  The narrower search fits the same place better but never looks at that rival; the answer is
    its fit, still ambiguous, with the rival's cells in its region."""
    from appliance.estimator import estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m

    db = forest_db
    grid = skyline_grid(db)
    az, el = _fixture_skyline("forest_rival_skyline.csv")
    res = estimate(grid, az, el)
    cell_m = math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert truth_error_m(db, place(db, res), (44.254957, -71.321851)) > 2.0 * cell_m
    assert res.ambiguous and any("exact renders at another place" in n for n in res.notes)
    assert res.rival_nodes.size and np.all(np.isin(res.rival_nodes, res.region_nodes))
    # the wide search alone: the same place, its fit poorer
    wide = estimate(grid, az, el, learn_noise=False)
    assert math.hypot(wide.row - res.row, wide.col - res.col) <= 2.0


def test_rival_places_the_occluder_check_finds_at_the_same_place_stand(forest_db):
    """A summit camera in the forest world whose skyline fits a place 1.2 km (15 cells) from the truth at
    0.46 deg RMS, the truth's own place at 0.45.  The truth's place looks as good as the other, but its
    first fit stops in a poor optimum; made again from the next nodes it finds the truth.  The place 1.2 km
    away fits as well: it stands as a rival, and the answer is ambiguous with the truth inside its region,
    never ok."""
    from appliance.estimator import estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m, truth_in_region

    db = forest_db
    az, el = _fixture_skyline("summit_rival_skyline.csv")
    truth = (44.254035, -71.326704)
    res = estimate(skyline_grid(db), az, el)
    pos = place(db, res)
    cell_m = math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert truth_error_m(db, pos, truth) < cell_m
    assert res.ambiguous and res.rival_nodes.size
    assert truth_in_region(db, pos, truth)


def test_a_poor_fit_that_leaves_white_noise_is_the_answer_without_searching_again(dem, tmp_path):
    """A skyline read at an unknown heading with 0.5 deg of white noise: its best fit, at the truth, stays above
    the search's lower sigma (0.3 deg), but what it leaves is the sensor's noise, uncorrelated from one azimuth to
    the next.  Searched again narrower, the skyline fitted a place 170 cells away more closely by leaving most of
    it to occluders, and the answer said ambiguous; no place fits white noise more closely than the truth does,
    and the answer is the first search's, ok."""
    from appliance.estimator.estimate import SIGMA_DEG, estimate
    from appliance.locating.position import place, skyline_grid, truth_error_m
    from appliance.terrain.database import build_database, load_database

    path = tmp_path / "jacksboro.viperdb"
    build_database(dem, path, progress=None)
    db = load_database(path, dem)
    grid = skyline_grid(db)
    az, el = _fixture_skyline("white_noise_skyline.csv")
    truth = (36.67708055, -84.15429494)
    res = estimate(grid, az, el, heading_tolerance_deg=None)
    cell_m = math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert truth_error_m(db, place(db, res), truth) < 2.0 * cell_m and not res.ambiguous
    assert res.rms_residual_deg > SIGMA_DEG[0] and res.sigma_deg_searched == SIGMA_DEG


def test_a_place_is_weighed_against_the_answer_fitted_as_the_answer_was():
    # the answer was fitted again with the head's tilt (its residual RMS 0.280 -> 0.249 deg); another
    # place 4.5 cells away fitted as well before that (0.281 deg), and with the tilt fits better still
    from types import SimpleNamespace

    from appliance.estimator.exact import Fit
    from appliance.estimator.measurement import Measurement
    from appliance.estimator.noise import rival_fits

    n = 300
    grid = SimpleNamespace(n_rows=20, n_cols=20)
    lp = np.zeros(400)
    meas = Measurement(np.zeros(n), np.ones(n), np.ones(n, dtype=bool), n, float(n), 0.19, 0.34, 0.26, 1.0, 0.05, 0.0)
    temper = 0.074

    def fit(row: float, col: float, rms: float) -> Fit:
        return Fit(row, col, 0.0, n * rms**2, n, 1)

    unpolished, answer = fit(5.0, 5.0, 0.280), fit(5.1, 5.0, 0.249)
    other, worse = fit(9.5, 5.5, 0.281), fit(15.0, 15.0, 0.60)
    fitted_again = fit(9.6, 5.4, 0.245)
    asked: list[Fit] = []

    def polish(f: Fit) -> Fit:
        asked.append(f)
        return fitted_again

    fits = [unpolished, other, worse]
    # against the polished answer alone, the other place's unpolished fit is no rival
    assert rival_fits(fits, answer, grid, lp, meas, temper, None) == []
    # fitted as the answer was, it is; a place that fits far worse is not fitted again at all
    assert rival_fits(fits, answer, grid, lp, meas, temper, None, unpolished, polish) == [fitted_again]
    assert asked == [other]
    # fitted again onto the answer's own place (within two cells), it is the answer's, not a rival
    assert rival_fits(fits, answer, grid, lp, meas, temper, None, unpolished, lambda f: fit(6.0, 5.5, 0.2)) == []
    # fitted again and still worse than the answer, no rival either
    assert rival_fits(fits, answer, grid, lp, meas, temper, None, unpolished, lambda f: fit(9.5, 5.5, 0.33)) == []
