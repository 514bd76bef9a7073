"""Fusion between nodes: an exact fit's covariance, its transport by the odometry, and the
Gaussian prior it becomes for the next fit."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from appliance.estimator import PositionPrior, estimate, transport_fix
from appliance.locating.position import Move, place, skyline_grid, transported_fix
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.test_estimator_exact import VALLEY, WINDOW  # a valley whose near terrain forms most of the horizon


@pytest.fixture(scope="module")
def valley(tmp_path_factory):
    dem = load_dem("jacksboro")
    path = tmp_path_factory.mktemp("db") / "valley.viperdb"
    build_database(dem, path, search_bounds=WINDOW, progress=None)
    db = load_database(path, dem)
    return dem, db, skyline_grid(db)


def _reading(dem, lat, lon, rng, noise_deg=0.3):
    truth = render_skyline(dem, lat, lon, 1.5)
    el = truth.elevation_deg + rng.normal(0.0, noise_deg, truth.elevation_deg.size)
    return truth.azimuth_deg, el


def _truth_rc(db, lat, lon):
    r, c = db.grid.xy_to_rc(*db.grid.lonlat_to_xy(lon, lat))
    return float(r), float(c)


def test_the_fit_covariance_matches_its_scatter(valley):
    # over noisy readings at one place, the fits' errors are distributed as their covariance says:
    # the mean squared Mahalanobis error of a 2-d Gaussian is 2
    dem, db, g = valley
    lat, lon = VALLEY
    rng = np.random.default_rng(11)
    r0, c0 = _truth_rc(db, lat, lon)
    d2, spread = [], []
    for _ in range(16):
        az, el = _reading(dem, lat, lon, rng)
        res = estimate(g, az, el, (0.3, 0.3), 4.0)
        cov = res.covariance_cells
        assert cov is not None and cov.shape == (2, 2)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        e = np.array([res.row - r0, res.col - c0])
        d2.append(float(e @ np.linalg.solve(cov, e)))
        spread.append(math.sqrt(float(np.trace(cov))))
    assert 0.5 < float(np.mean(d2)) < 6.0
    # and a fit this good claims far less than a cell
    assert float(np.median(spread)) < 0.2


def test_a_prior_pulls_the_fit_between_nodes_towards_it(valley):
    dem, db, g = valley
    lat, lon = VALLEY
    rng = np.random.default_rng(4)
    az, el = _reading(dem, lat, lon, rng, noise_deg=0.5)
    alone = estimate(g, az, el, (0.5, 0.5), 4.0)
    assert alone.covariance_cells is not None
    # a prior half a cell east of the fit, as sure of itself as the fit: the answer moves part way
    pr = PositionPrior(alone.row, alone.col + 0.5, np.linalg.inv(alone.covariance_cells))
    mid = estimate(g, az, el, (0.5, 0.5), 4.0, position_prior=pr)
    assert alone.col + 0.1 < mid.col < alone.col + 0.45
    # a prior far surer than the skyline holds the answer at its centre
    firm = PositionPrior(alone.row, alone.col + 0.5, np.eye(2) / 0.001**2)
    held = estimate(g, az, el, (0.5, 0.5), 4.0, position_prior=firm)
    assert abs(held.col - (alone.col + 0.5)) < 0.03 and abs(held.row - alone.row) < 0.03
    # the fit's own cost is still the measurements': the prior moved it off their best
    assert held.rms_residual_deg >= alone.rms_residual_deg - 1e-9
    # and fused, the covariance is tighter than the fit's alone
    assert np.trace(mid.covariance_cells) < np.trace(alone.covariance_cells)


def test_the_odometry_moves_the_fix_and_widens_it():
    cov = np.array([[0.04, 0.01], [0.01, 0.09]])
    pr = transport_fix(10.0, 20.0, cov, dx_m=50.0, dy_m=80.0, east_m=100.0, north_m=-40.0, sigma_m=20.0)
    assert (pr.row, pr.col) == pytest.approx((10.5, 22.0))  # rows run south
    widened = np.linalg.inv(pr.information)
    assert widened == pytest.approx(cov + np.diag([(20.0 / 80.0) ** 2, (20.0 / 50.0) ** 2]))


def test_an_ambiguous_fix_is_not_carried_as_a_gaussian(valley):
    dem, db, g = valley
    lat, lon = VALLEY
    az, el = _reading(dem, lat, lon, np.random.default_rng(2))
    res = estimate(g, az, el, (0.3, 0.8), 4.0)
    pos = place(db, res)
    move = Move(30.0, -10.0, 15.0)
    fix = transported_fix(db, g, pos, move)
    assert fix is not None
    # the same fix flagged ambiguous: its posterior has another place a Gaussian would hide
    amb = dataclasses.replace(pos, estimate=dataclasses.replace(res, ambiguous=True))
    assert transported_fix(db, g, amb, move) is None



def test_an_odometry_prior_lowers_the_errors_of_fits_between_nodes(valley):
    """Thirty places in the valley, each read with 0.3 deg of noise, each with a prior as a rover's
    odometry gives it (15 m per axis, its centre drawn that far from the truth).  Fused, the mean
    error must fall below the skyline's alone and the 90th percentile must not grow beyond noise: a
    prior that is right on average helps on average.  (A fit that followed the prior's early pull alone settled now and
    then in a worse basin between two nodes, and fusion raised both.)"""
    dem, db, g = valley
    rng = np.random.default_rng(5)
    lat0, lon0 = VALLEY
    sd_r, sd_c = 15.0 / g.dy_m, 15.0 / g.dx_m
    alone_m, fused_m = [], []
    for _ in range(30):
        lat, lon = lat0 + rng.normal(0.0, 0.002), lon0 + rng.normal(0.0, 0.002)
        r0, c0 = _truth_rc(db, lat, lon)
        az, el = _reading(dem, lat, lon, rng)
        off = rng.normal(0.0, 1.0, 2)
        pp = PositionPrior(r0 + off[0] * sd_r, c0 + off[1] * sd_c, np.diag([sd_r**-2, sd_c**-2]))
        for out, prior in ((alone_m, None), (fused_m, pp)):
            res = estimate(g, az, el, (0.3, 0.8), 4.0, position_prior=prior)
            out.append(math.hypot((res.row - r0) * g.dy_m, (res.col - c0) * g.dx_m))
    assert np.mean(fused_m) < np.mean(alone_m)
    # the likelihood tempered by the skyline's independent azimuths gives the prior (15 m) a larger
    # say than before: the tail may grow a little (3.0 to 3.5 m here), never by a prior's worth
    assert np.percentile(fused_m, 90) < 1.25 * np.percentile(alone_m, 90)
