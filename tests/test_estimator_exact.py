"""Exactness where near terrain forms the horizon: the renderer's near field, the database's ranges,
the parallax Jacobian, the refinement between nodes, the eye's height per estimate, occluders."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from appliance.estimator import estimate
from appliance.estimator.exact import jacobian, render
from appliance.estimator.likelihood import OCCLUDER_SPAN_DEG, occlusion_cap_deg2
from appliance.estimator.search import ssd_for_shifts
from appliance.locating.position import estimate_status, place, skyline_grid
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.reference_render import reference_skyline

#: A valley of jacksboro: terrain within 1 km forms 86 % of the horizon, 0.37 rows and 0.29 columns
#: away from the nearest database node (found from the database's ranges).
VALLEY = (36.52885833333333, -84.25440833333333)
WINDOW = (-84.275, 36.51, -84.235, 36.545)


@pytest.fixture(scope="module")
def valley_db(tmp_path_factory):
    dem = load_dem("jacksboro")
    path = tmp_path_factory.mktemp("db") / "valley.viperdb"
    build_database(dem, path, search_bounds=WINDOW, progress=None)
    return dem, load_database(path, dem)


def _error_m(dem, pos, lat, lon):
    _, _, d = dem.geod.inv(lon, lat, pos.lon, pos.lat)
    return float(d)


def test_render_matches_a_fiftieth_cell_march_where_the_terrain_is_close():
    # the viewpoint: the old quarter-cell steps left the skyline up to 0.8 deg low here
    dem = load_dem("jacksboro")
    lat, lon = 36.5521, -84.1911
    ours = render_skyline(dem, lat, lon, max_range_m=3000.0)
    ref = reference_skyline(dem, lat, lon, max_range_m=3000.0)
    ok = np.isfinite(ref)
    e = ours.elevation_deg[ok] - ref[ok]
    assert np.mean(ours.distance_m[ok] < 300.0) > 0.05  # close terrain does form part of this horizon
    assert math.sqrt(float(np.mean(e**2))) < 0.02
    assert float(np.max(np.abs(e))) < 0.06


def test_database_ranges_are_those_of_the_renderer(valley_db):
    dem, db = valley_db
    rng = np.random.default_rng(3)
    rel = []
    for node in rng.choice(db.grid.n_nodes, 12, replace=False):
        lon, lat = db.grid.xy_to_lonlat(*db.grid.node_xy(int(node)))
        h = render_skyline(dem, float(lat), float(lon), db.height_m)
        same = np.abs(db.skylines_deg(int(node)) - h.elevation_deg) < 0.05  # the same horizon point
        ours = db.distances_m(int(node))
        ok = same & np.isfinite(ours) & np.isfinite(h.distance_m)
        rel.append(np.abs(ours[ok] / h.distance_m[ok] - 1.0))
    r = np.concatenate(rel)
    assert r.size > 1000
    # log-quantised to 5 % steps (2.5 % at most) on a line sweep whose lines pass within a quarter row
    assert np.median(r) < 0.05 and np.percentile(r, 90) < 0.25


def test_parallax_jacobian_predicts_small_moves(valley_db):
    _, db = valley_db
    g = skyline_grid(db)
    t = g.terrain
    dist = t.distances(min(g.dx_m, g.dy_m))
    az = np.arange(360.0)
    row, col = 10.4, 11.3
    s0, d0, _ = render(t, g.dx_m, g.dy_m, row, col, az, dist, 1.5)
    J = jacobian(t, g.dx_m, g.dy_m, row, col, az, s0, d0)
    eps = 0.01
    for k, (dr, dc) in enumerate(((eps, 0.0), (0.0, eps))):
        s1, _, _ = render(t, g.dx_m, g.dy_m, row + dr, col + dc, az, dist, 1.5)
        numeric = (s1 - s0) / eps
        far = d0 > 3 * max(g.dx_m, g.dy_m)  # away from the horizon points that switch within a step
        assert np.corrcoef(numeric[far], J[far, k])[0, 1] > 0.9
    s_up, _, _ = render(t, g.dx_m, g.dy_m, row, col, az, dist, 1.5 + 0.5)
    assert np.corrcoef((s_up - s0) / 0.5, J[:, 3])[0, 1] > 0.95


def test_a_render_shared_among_threads_is_the_march_of_one(valley_db):
    """A render's azimuths are marched on numba's threads together (raycast.march_shared): each ray by the
    same kernel, so the skyline and the ranges are those of one march over all of them, bit for bit, on
    any count of azimuths (split in unequal parts too) and at any fractional place."""
    import numba

    from appliance.estimator import raycast

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread: nothing is shared")
    _, db = valley_db
    g = skyline_grid(db)
    t = g.terrain
    dist = t.distances(min(g.dx_m, g.dy_m))
    rng = np.random.default_rng(5)
    threads = numba.get_num_threads()
    for n in (raycast.SHARED_MIN_AZIMUTHS * 2, 601, 1681):
        az = np.sort(rng.uniform(0.0, 360.0, n))
        row, col = rng.uniform(2.0, g.n_rows - 3.0), rng.uniform(2.0, g.n_cols - 3.0)
        numba.set_num_threads(2)
        try:
            shared = render(t, g.dx_m, g.dy_m, row, col, az, dist, 1.5)
            numba.set_num_threads(1)
            one = render(t, g.dx_m, g.dy_m, row, col, az, dist, 1.5)
        finally:
            numba.set_num_threads(threads)
        assert np.isfinite(one[0]).sum() > n // 2
        assert shared[0].tobytes() == one[0].tobytes() and shared[1].tobytes() == one[1].tobytes()
    assert raycast._march_pools  # the azimuths were shared


def test_a_forked_child_renders_on_threads_of_its_own(valley_db, tmp_path):
    """The command server forks: a child whose parent shared a render among threads has none of the
    pool's threads, so it makes its own pool (a render that waited on its parent's would never end)."""
    import os

    import numba

    from appliance.estimator import raycast

    if numba.config.NUMBA_NUM_THREADS < 2 or not hasattr(os, "fork"):
        pytest.skip("one numba thread, or no fork: nothing is shared")
    _, db = valley_db
    g = skyline_grid(db)
    dist = g.terrain.distances(min(g.dx_m, g.dy_m))
    az = np.linspace(0.0, 359.5, 720)
    numba.set_num_threads(2)
    parent = render(g.terrain, g.dx_m, g.dy_m, 3.5, 3.5, az, dist, 1.5)[0]
    assert raycast._march_pools
    out = tmp_path / "child.npy"
    pid = os.fork()
    if pid == 0:  # the child: render, write, leave without running the parent's exit handlers
        code = 1
        try:
            np.save(out, render(g.terrain, g.dx_m, g.dy_m, 3.5, 3.5, az, dist, 1.5)[0])
            code = 0
        finally:
            os._exit(code)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        time.sleep(0.05)
    else:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
        pytest.fail("the forked child's render never ended")
    assert os.waitstatus_to_exitcode(status) == 0
    assert np.load(out).tobytes() == parent.tobytes()


def test_a_valley_between_nodes_is_located_exactly(valley_db):
    dem, db = valley_db
    lat, lon = VALLEY
    truth = render_skyline(dem, lat, lon, 1.5)
    assert np.mean(truth.distance_m < 1000.0) >= 0.6
    rng = np.random.default_rng(5)
    compass = 2.5
    az = np.arange(360.0)
    el = np.interp((az + compass) % 360, az, truth.elevation_deg, period=360) + rng.normal(0, 0.2, 360)
    el[rng.choice(360, 36, replace=False)] = np.nan
    res = estimate(skyline_grid(db), az, el, (0.3, 0.8), 4.0)
    pos = place(db, res)
    cell = math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert _error_m(dem, pos, lat, lon) < 0.1 * cell
    assert abs(res.heading_correction_deg - compass) < 0.3
    assert res.rms_residual_deg < 0.3  # the exact render fits down to the sensor's noise
    assert estimate_status(db, pos, (lat, lon)) == "ok"
    # a truth two kilometres away lies outside the region: replay says so
    assert estimate_status(db, pos, (lat + 0.018, lon)) == "ambiguous"


def test_the_camera_height_is_given_per_estimate(valley_db):
    dem, db = valley_db
    lat, lon = VALLEY
    sky = render_skyline(dem, lat, lon, 12.0)  # on a roof the map does not hold
    g = skyline_grid(db)
    right = estimate(g, sky.azimuth_deg, sky.elevation_deg, (0.3, 0.8), 4.0, height_m=12.0)
    assert _error_m(dem, place(db, right), lat, lon) < 5.0
    assert abs(right.eye_offset_m) < 1.0
    # given the database's 1.5 m, the fit at the learned sigma finds the roof: the eye 10.5 m higher
    wrong = estimate(g, sky.azimuth_deg, sky.elevation_deg, (0.3, 0.8), 4.0)
    assert wrong.eye_offset_m == pytest.approx(12.0 - 1.5, abs=1.5)
    assert _error_m(dem, place(db, wrong), lat, lon) < 5.0


def test_the_occlusion_cap_is_where_the_mixture_levels_off():
    sigma = 0.5
    assert occlusion_cap_deg2(0.0, sigma) == math.inf
    for w in (0.01, 0.1, 0.3):
        r = 12 * sigma  # far above the prediction: only the occluder explains it

        def nll(x: float, w: float = w) -> float:
            gauss = (1 - w) * math.exp(-x * x / (2 * sigma * sigma)) / (math.sqrt(2 * math.pi) * sigma)
            return -2 * sigma * sigma * math.log(gauss + w / OCCLUDER_SPAN_DEG)

        assert nll(r) - nll(0.0) == pytest.approx(occlusion_cap_deg2(w, sigma), rel=0.02)
    assert occlusion_cap_deg2(0.3, sigma) < occlusion_cap_deg2(0.01, sigma)


def test_only_measurements_above_the_terrain_are_capped(valley_db):
    _, db = valley_db
    node = 200
    truth = db.skylines_deg(node)
    cap = 1.0
    up, down = truth.copy(), truth.copy()
    up[100:120] += 5.0  # a tree in front of the ridge
    down[100:120] -= 5.0  # a skyline below the terrain: no occluder can do that
    args = (db.codes, db.offset_deg, db.step_deg)

    def score(measured: np.ndarray) -> tuple[float, float]:
        occ = np.empty((1, 1), dtype=np.float32)
        ssd = ssd_for_shifts(*args, measured, np.array([0]), rows=np.array([node]), cap_deg2=cap, occluded=occ)
        return float(ssd[0, 0]), float(occ[0, 0])

    base, base_occ = score(truth)
    raised, raised_occ = score(up)
    lowered, lowered_occ = score(down)
    assert base_occ == 0 and lowered_occ == 0
    assert raised_occ == 20 and raised == pytest.approx(base, abs=0.1)  # the tree is no evidence against
    assert lowered - base == pytest.approx(20 * 25.0, rel=0.05)  # a skyline below the terrain is


def test_trees_in_front_of_the_ridge_leave_the_estimate_in_place(valley_db):
    dem, db = valley_db
    lat, lon = VALLEY
    truth = render_skyline(dem, lat, lon, 1.5)
    rng = np.random.default_rng(9)
    el = truth.elevation_deg + rng.normal(0, 0.2, 360)
    for start in (40, 200):  # two stands of trees, 25 deg wide, 2 to 6 deg above the terrain
        el[start : start + 25] += rng.uniform(2.0, 6.0)
    res = estimate(skyline_grid(db), truth.azimuth_deg, el, (0.3, 0.8), 4.0, occlusion_weight=0.1)
    pos = place(db, res)
    assert _error_m(dem, pos, lat, lon) < 0.25 * math.sqrt(db.grid.dx_m * db.grid.dy_m)
    assert estimate_status(db, pos, (lat, lon)) == "ok"


@pytest.mark.parametrize(("view_deg", "raised_deg", "tolerance_deg"), [(60.0, 0.0, None), (360.0, 3.0, 4.0)])
def test_the_estimate_is_the_same_on_one_thread_as_on_several(valley_db, view_deg, raised_deg, tolerance_deg):
    """The refinement's looks run on numba's threads, beside the best mode's fit; with one thread
    they are made in turn.  Both give the same estimate, bit for bit: on a 60 deg view with no
    compass, and with a sixth of the skyline raised (trees the map does not hold, no occlusion
    weight).  With 0.2 deg of noise neither first fit comes down to the map's precision, so every
    mode is looked at."""
    import numba

    dem, db = valley_db
    lat, lon = VALLEY
    sky = render_skyline(dem, lat, lon, 1.5)
    az = sky.azimuth_deg
    el = sky.elevation_deg + np.random.default_rng(1).normal(0, 0.2, az.size)
    el = np.where(az < view_deg, el + np.where((az >= 100.0) & (az < 160.0), raised_deg, 0.0), np.nan)
    g = skyline_grid(db)
    several = estimate(g, az, el, (0.3, 0.8), tolerance_deg, occlusion_weight=0.0)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one = estimate(g, az, el, (0.3, 0.8), tolerance_deg, occlusion_weight=0.0)
    finally:
        numba.set_num_threads(threads)
    assert (one.row, one.col, one.heading_correction_deg, one.rms_residual_deg) == (
        several.row, several.col, several.heading_correction_deg, several.rms_residual_deg)
    np.testing.assert_array_equal(one.region_nodes, several.region_nodes)
    assert one.notes == several.notes
    # the fit is above the map's precision (CONVERGED_RMS times CONVERGED_SIGMA_DEG): every mode looked at
    assert several.rms_residual_deg > 1.5 * 0.05


def test_a_fit_that_ends_far_worse_than_its_look_promised_is_made_again_from_the_next_nodes():
    # two places looked alike (55.5 and 67.2); the second one's fit stopped in a poor optimum (a residual sum
    # three times the first's); a start one node over finds its own optimum, better than either
    from types import SimpleNamespace

    from appliance.estimator.exact import Fit
    from appliance.estimator.refinement import _RefineContext

    n_cols = 10
    grid = SimpleNamespace(n_rows=10, n_cols=n_cols, offset_deg=np.zeros(100))
    a, b = 2 * n_cols + 2, 6 * n_cols + 6
    sums = {a: 25.5, b: 73.0, b + n_cols: 13.5}
    starts: list[int] = []

    def fit(cand, start, phi):
        starts.append(cand)
        return Fit(float(cand // n_cols), float(cand % n_cols), phi, sums.get(cand, 90.0), 315, 1)

    ctx = _RefineContext.__new__(_RefineContext)
    ctx.grid, ctx._fit = grid, fit
    looks = [(55.5, a, (2.0, 2.0), 0.5), (67.2, b, (6.0, 6.0), 0.7)]
    fits = ctx.fit_looked(looks)
    assert [f.ssd for f in fits] == [25.5, 13.5]
    # the four neighbours of the second node were tried, with its look's heading
    assert sorted(starts[2:]) == sorted([b - n_cols, b + n_cols, b - 1, b + 1])
    assert fits[1].heading_deg == 0.7
    # a fit as good as its look promised (less than twice the best's sum) is left as it is
    sums[b] = 40.0
    starts.clear()
    assert [f.ssd for f in ctx.fit_looked(looks)] == [25.5, 40.0] and starts == [a, b]
    # so is one whose look was not within the margin of the best look (a place that never looked alike)
    sums[b] = 73.0
    starts.clear()
    far = [(55.5, a, (2.0, 2.0), 0.5), (120.0, b, (6.0, 6.0), 0.7)]
    assert [f.ssd for f in ctx.fit_looked(far, beat=100.0)] == [25.5, 73.0] and starts == [a, b]
