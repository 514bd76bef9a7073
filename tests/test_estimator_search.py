"""Grid search, heading search, sub-cell refinement and fusion on synthetic skyline grids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.errors import InputError
from appliance.estimator import SkylineGrid, estimate, resample_to_grid, transport_prior
from appliance.terrain.quantize import quantize

N_AZ = 360


def skyline_field(rows: np.ndarray, cols: np.ndarray, seed: int = 0) -> np.ndarray:
    """Skylines whose harmonics change in amplitude across the map: (len(rows), N_AZ) degrees.

    Linear in position, so the skyline between nodes is exactly the blend of its nodes'."""
    rng = np.random.default_rng(seed)
    az = np.radians(np.arange(N_AZ))
    out = np.zeros((rows.size, N_AZ))
    for k in range(1, 9):
        amp = rng.uniform(0.5, 3.0) / k
        fr, fc, ph = rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), rng.uniform(0, 2 * np.pi)
        out += amp * (1.0 + fr * (rows[:, None] - 20) + fc * (cols[:, None] - 25)) * np.sin(k * az[None, :] + ph)
    return out + 3.0


def make_grid(n_rows: int = 40, n_cols: int = 50, seed: int = 0, cell_m: float = 30.0) -> SkylineGrid:
    r, c = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    codes, off, step = quantize(skyline_field(r.ravel().astype(float), c.ravel().astype(float), seed))
    return SkylineGrid(codes, off, step, n_rows=n_rows, n_cols=n_cols, dx_m=cell_m, dy_m=cell_m)


def reading(true_el: np.ndarray, correction_deg: float, rng, noise=0.0, missing=0):
    az = np.arange(N_AZ, dtype=float)
    el = np.interp((az + correction_deg) % 360, az, true_el, period=360) + rng.normal(0, noise, N_AZ)
    if missing:
        el[rng.choice(N_AZ, missing, replace=False)] = np.nan
    return az, el


def test_every_heading_first_pass_keeps_each_nodes_best_heading_across_blocks(monkeypatch):
    from appliance.estimator import coarse
    from appliance.estimator.coarse_kernels import box_decimate, ssd_coarse

    g = make_grid(6, 7)
    rng = np.random.default_rng(1)
    m = g.skylines_deg(20) + rng.normal(0, 0.3, N_AZ)
    m[rng.choice(N_AZ, 40, replace=False)] = np.nan
    valid = np.isfinite(m)
    w = valid.astype(float)
    monkeypatch.setattr(coarse, "HEADING_BLOCK_NODES", 5)  # 42 nodes in blocks of 5
    score, _, _, band, centre, n_az = coarse._every_heading_first_pass(g, m, valid, w, float(valid.sum()), 0.3,
                                                                      math.inf, 0.0)
    m_dec = box_decimate(m, coarse.COARSE_STRIDE)
    w_dec = np.nan_to_num(box_decimate(np.where(valid, w, np.nan), coarse.COARSE_STRIDE))
    occ = np.empty((g.codes.shape[0], m_dec.size), dtype=np.float32)
    direct, _ = ssd_coarse(g.coarse, g.offset_deg, g.step_deg, m_dec, np.arange(m_dec.size), None, w_dec,
                           math.inf, occ)
    scale = N_AZ / np.nansum(w_dec) * valid.sum() / N_AZ
    assert np.allclose(score[:, 0], direct.min(axis=1) * scale, rtol=1e-5)
    # the band to rescore is centred on the best coarse heading
    best = np.argmin(direct, axis=1) * coarse.COARSE_STRIDE
    assert np.array_equal(centre % n_az, best % N_AZ)
    assert np.array_equal(band, np.arange(-band.size // 2 + 1, band.size // 2 + 1))


def test_node_and_heading_recovered_with_a_compass():
    g = make_grid()
    rng = np.random.default_rng(2)
    node = 17 * g.n_cols + 23
    az, el = reading(g.skylines_deg(node), 3.0, rng, noise=0.2, missing=30)
    res = estimate(g, az, el, (0.15, 0.4), 4.0)
    assert res.node == node
    assert res.heading_correction_deg == pytest.approx(3.0, abs=0.25)
    assert node in res.region_nodes
    assert 0 <= res.lower <= res.upper <= 1


def test_unknown_heading_is_found_anywhere_on_the_circle():
    g = make_grid(seed=4)
    rng = np.random.default_rng(3)
    node = 9 * g.n_cols + 31
    az, el = reading(g.skylines_deg(node), -137.0, rng, noise=0.3, missing=60)
    res = estimate(g, az, el, (0.2, 0.5), None)
    assert res.node == node
    assert res.heading_correction_deg == pytest.approx(-137.0, abs=0.5)


def test_sub_cell_refinement_finds_a_point_between_nodes():
    g = make_grid(seed=5)
    rng = np.random.default_rng(4)
    r, c = 20.3, 14.7
    true_el = skyline_field(np.array([r]), np.array([c]), seed=5)[0]
    az, el = reading(true_el, 0.0, rng, noise=0.05)
    res = estimate(g, az, el, (0.05, 0.3), 2.0)
    assert abs(res.row - r) <= 0.15 and abs(res.col - c) <= 0.15
    node_error = min(np.hypot(rr - r, cc - c) for rr in (20, 21) for cc in (14, 15))
    assert np.hypot(res.row - r, res.col - c) < node_error


def test_ambiguous_skyline_gives_a_large_region_and_says_so():
    g = make_grid()
    flat = np.zeros(N_AZ) + 3.0  # a skyline like none on the map: matches everything about as badly
    res = estimate(g, np.arange(N_AZ, dtype=float), flat, (0.2, 0.6), 4.0)
    assert res.region_nodes.size > 25
    assert res.ambiguous
    assert any("ambiguous" in n for n in res.notes)


def test_a_view_narrower_than_twenty_degrees_is_refused():
    g = make_grid(5, 5)
    el = np.full(N_AZ, np.nan)
    el[:19] = 2.0
    with pytest.raises(InputError, match="less than the 20 deg"):
        estimate(g, np.arange(N_AZ, dtype=float), el)


def test_resampling_keeps_grid_samples_and_never_bridges_gaps():
    az = np.arange(0.0, 360.0, 1.0)
    el = np.sin(np.radians(az))
    el[100:110] = np.nan
    out = resample_to_grid(az, el, 360)
    assert np.array_equal(np.isnan(out), np.isnan(el))
    half = resample_to_grid(az + 0.5, el, 360)
    assert np.isnan(half[101:110]).all()
    assert half[50] == pytest.approx(0.5 * (el[49] + el[50]))


def test_transported_prior_moves_by_the_displacement():
    post = np.zeros((30, 40))
    post[10, 12] = 1.0
    lp = transport_prior(post.ravel(), 30, 40, 20.0, 25.0, east_m=60.0, north_m=50.0, sigma_m=0.0)
    peak = np.unravel_index(np.argmax(lp), (30, 40))
    assert peak == (8, 15)  # 50 m north = 2 rows up, 60 m east = 3 columns right
    blurred = np.exp(transport_prior(post.ravel(), 30, 40, 20.0, 25.0, 60.0, 50.0, 40.0)).reshape(30, 40)
    assert np.unravel_index(np.argmax(blurred), (30, 40)) == (8, 15)
    assert blurred[8, 15] < 0.2 and blurred.sum() == pytest.approx(1.0)


def test_fusion_resolves_what_one_panorama_cannot():
    # two identical halves: the first skyline cannot tell them apart, the prior from a second
    # station (moved by a known step) can
    half = make_grid(20, 20, seed=7)
    codes = np.concatenate([half.codes.reshape(20, 20, N_AZ), half.codes.reshape(20, 20, N_AZ)], axis=1)
    off = np.concatenate([half.offset_deg.reshape(20, 20), half.offset_deg.reshape(20, 20)], axis=1)
    step = np.concatenate([half.step_deg.reshape(20, 20), half.step_deg.reshape(20, 20)], axis=1)
    g = SkylineGrid(codes.reshape(-1, N_AZ), off.ravel(), step.ravel(), n_rows=20, n_cols=40, dx_m=30.0, dy_m=30.0)
    rng = np.random.default_rng(9)
    first = 10 * 40 + 5  # left half; its twin is 10 * 40 + 25
    alone = estimate(g, *reading(g.skylines_deg(first), 0.0, rng, noise=0.2), (0.15, 0.4), 2.0)
    assert {first, first + 20} <= set(alone.region_nodes.tolist())
    # a prior that says "we came from the left half"
    prior = np.zeros((20, 40))
    prior[:, :20] = 1.0
    lp = transport_prior(prior.ravel() / prior.sum(), 20, 40, 30.0, 30.0, 0.0, 0.0, 30.0)
    fused = estimate(g, *reading(g.skylines_deg(first), 0.0, rng, noise=0.2), (0.15, 0.4), 2.0, log_prior=lp)
    assert fused.node == first
    assert round(fused.col) == 5
    # alone the twins are equally likely; with the prior the twin is far less so
    assert abs(alone.log_lower_map[first] - alone.log_lower_map[first + 20]) < 1.0
    assert fused.log_lower_map[first] - fused.log_lower_map[first + 20] > 15.0


def _every_shift_reference(C, off, step, m, w, T, w_lut, p_lut, cap):
    """Every node at every circular shift, in float64 numpy: the residual sums (deg^2) and occluded
    weights as the first pass defines them, and the log-normalisers."""
    n, d = C.shape
    ssd = np.full((n, d), np.inf)
    occ = np.zeros((n, d))
    pen = np.zeros(n)
    n_meas = w.sum()
    for i in range(n):
        if np.isnan(off[i]):
            continue
        v = w_lut[T[i]].astype(float)
        pen[i] = np.sum(w * p_lut[T[i]])
        mt = (m - off[i]) / step[i]
        for k in range(d):
            idx = (np.arange(d) + k) % d
            c = C[i, idx].astype(float)
            ok = (c != 255) & (w > 0)
            e = mt - c
            q = v[idx] * e * e
            hidden = ok & (e > 0) & (q > cap / step[i] ** 2)
            used = ok & ~hidden
            cnt = w[ok].sum()
            if cnt < 0.9 * n_meas or cnt == 0:
                continue
            ssd[i, k] = np.sum((w * q)[used]) * step[i] ** 2 * n_meas / cnt
            occ[i, k] = w[hidden].sum() * n_meas / cnt
    return ssd, occ, pen


@pytest.mark.parametrize("cap", [math.inf, 2.0])
def test_every_shift_kernel_keeps_the_best_shift_of_a_numpy_reference(cap):
    from appliance.estimator.coarse_kernels import ssd_coarse_best

    rng = np.random.default_rng(7)
    n, d = 300, 90
    C = rng.integers(0, 255, (n, d)).astype(np.uint8)
    C[:5, rng.choice(d, 4, replace=False)] = 255  # lacking terrain somewhere, still candidates
    C[5:8, : d // 5] = 255  # lacking too much: not candidates
    off = rng.uniform(-2, 2, n).astype(np.float32)
    off[8] = np.nan
    step = rng.uniform(0.02, 0.1, n).astype(np.float32)
    partial = np.zeros(n, dtype=bool)
    partial[:8] = True
    partial[8] = True
    T = rng.integers(0, 120, (n, d)).astype(np.uint8)
    w_lut = rng.uniform(0.2, 1.0, 256).astype(np.float32)
    p_lut = rng.uniform(0.0, 2.0, 256).astype(np.float32)
    m = (off[20] + step[20] * np.roll(C[20], -7).astype(np.float64) + rng.normal(0, 0.2, d))
    m[rng.choice(d, 6, replace=False)] = np.nan
    w = np.where(np.isfinite(m), rng.uniform(0.5, 1.0, d), 0.0)
    best, occ, arg, pen = ssd_coarse_best((C, partial), off, step, m, (T, w_lut, p_lut), w, cap)
    m0 = np.nan_to_num(m).astype(np.float32).astype(float)
    ref, ref_occ, ref_pen = _every_shift_reference(C, off.astype(float), step.astype(float), m0,
                                                   w.astype(np.float32).astype(float), T, w_lut, p_lut, cap)
    ranked = ref + (ref_occ * cap if math.isfinite(cap) else 0.0)
    k = np.argmin(ranked, axis=1)
    rows = np.arange(n)
    assert np.array_equal(np.isfinite(best), np.isfinite(ref[rows, k]))
    fin = np.isfinite(best)
    assert fin.sum() > n - 10
    # the chosen shift is the reference's wherever the reference's best stands clear of its second
    second = np.sort(ranked, axis=1)[:, 1]
    with np.errstate(invalid="ignore"):
        clear = fin & (second - ranked[rows, k] > 1e-4 * np.abs(ranked[rows, k]))
    assert clear.sum() > n - 20
    assert np.array_equal(arg[clear], k[clear])
    assert np.allclose(best[fin], ref[rows, k][fin], rtol=2e-5)
    assert np.allclose(occ[fin], ref_occ[rows, k][fin], rtol=2e-5, atol=1e-6)
    assert np.allclose(pen[~np.isnan(off)], ref_pen[~np.isnan(off)], rtol=1e-5)


@pytest.mark.parametrize("view", [(0, 24), (37, 69), (80, 97)])
def test_every_shift_kernel_on_a_narrow_view_keeps_the_best_shift_of_a_numpy_reference(view):
    """A view of a few runs of azimuths (one across the circle's seam): the azimuths not measured
    are skipped in pairs, and the sums, best shifts and normalisers are still the reference's."""
    from appliance.estimator.coarse_kernels import ssd_coarse_best

    rng = np.random.default_rng(11)
    n, d = 200, 90
    C = rng.integers(0, 255, (n, d)).astype(np.uint8)
    off = rng.uniform(-2, 2, n).astype(np.float32)
    step = rng.uniform(0.02, 0.1, n).astype(np.float32)
    partial = np.zeros(n, dtype=bool)
    T = rng.integers(0, 120, (n, d)).astype(np.uint8)
    w_lut = rng.uniform(0.2, 1.0, 256).astype(np.float32)
    p_lut = rng.uniform(0.0, 2.0, 256).astype(np.float32)
    seen = np.zeros(d, dtype=bool)
    seen[np.arange(view[0], view[1]) % d] = True
    m = off[40] + step[40] * np.roll(C[40], -31).astype(np.float64) + rng.normal(0, 0.2, d)
    m[~seen] = np.nan
    w = np.where(seen, rng.uniform(0.5, 1.0, d), 0.0)
    best, occ, arg, pen = ssd_coarse_best((C, partial), off, step, m, (T, w_lut, p_lut), w, math.inf)
    m0 = np.nan_to_num(m).astype(np.float32).astype(float)
    ref, _, ref_pen = _every_shift_reference(C, off.astype(float), step.astype(float), m0,
                                             w.astype(np.float32).astype(float), T, w_lut, p_lut, math.inf)
    rows = np.arange(n)
    k = np.argmin(ref, axis=1)
    second = np.sort(ref, axis=1)[:, 1]
    clear = second - ref[rows, k] > 1e-4 * ref[rows, k]
    assert clear.sum() > n - 10
    assert np.array_equal(arg[clear], k[clear])
    assert arg[40] == 31
    assert np.allclose(best, ref[rows, arg], rtol=2e-5)
    assert np.all(occ == 0.0)
    assert np.allclose(pen, ref_pen, rtol=1e-5)


@pytest.mark.parametrize("cap", [math.inf, 2.0])
@pytest.mark.parametrize("shifts", [np.arange(-1, 2), np.arange(-3, 5), np.arange(90)])
def test_compass_kernel_matches_a_numpy_reference(cap, shifts):
    from appliance.estimator.coarse_kernels import ssd_coarse

    rng = np.random.default_rng(8)
    n, d = 200, 90
    C = rng.integers(0, 255, (n, d)).astype(np.uint8)
    C[:5, rng.choice(d, 4, replace=False)] = 255
    C[5:8, : d // 5] = 255
    off = rng.uniform(-2, 2, n).astype(np.float32)
    off[8] = np.nan
    step = rng.uniform(0.02, 0.1, n).astype(np.float32)
    partial = np.zeros(n, dtype=bool)
    partial[:9] = True
    T = rng.integers(0, 120, (n, d)).astype(np.uint8)
    w_lut = rng.uniform(0.2, 1.0, 256).astype(np.float32)
    p_lut = rng.uniform(0.0, 2.0, 256).astype(np.float32)
    m = off[30] + step[30] * np.roll(C[30], 2).astype(np.float64) + rng.normal(0, 0.2, d)
    m[rng.choice(d, 6, replace=False)] = np.nan
    w = np.where(np.isfinite(m), rng.uniform(0.5, 1.0, d), 0.0)
    occ = np.empty((n, shifts.size), dtype=np.float32)
    got, pen = ssd_coarse((C, partial), off, step, m, shifts, (T, w_lut, p_lut), w, cap, occ)
    m0 = np.nan_to_num(m).astype(np.float32).astype(float)
    ref, ref_occ, ref_pen = _every_shift_reference(C, off.astype(float), step.astype(float), m0,
                                                   w.astype(np.float32).astype(float), T, w_lut, p_lut, cap)
    cols = shifts % d
    assert np.array_equal(np.isfinite(got), np.isfinite(ref[:, cols]))
    fin = np.isfinite(got)
    assert np.allclose(got[fin], ref[:, cols][fin], rtol=2e-5)
    assert np.allclose(occ[fin], ref_occ[:, cols][fin], rtol=2e-5, atol=1e-6)
    assert np.allclose(pen[~np.isnan(off)], ref_pen[~np.isnan(off)], rtol=1e-5)


@pytest.mark.parametrize("shape", [(2, 2), (2, 7), (7, 2), (37, 53)])
def test_the_ground_gradient_at_some_nodes_is_the_whole_maps_there(shape):
    """The kernels read the gradient at the nodes they score only: computed there alone it is the
    whole map's, bit for bit, edges and nodata (NaN neighbours give 0) included."""
    from appliance.estimator import parallax

    rng = np.random.default_rng(7)
    n_rows, n_cols = shape
    ground = (rng.normal(0.0, 300.0, n_rows * n_cols) + 1000.0).astype(np.float32)
    ground[rng.choice(ground.size, max(1, ground.size // 10), replace=False)] = np.nan
    dx_m, dy_m = 74.573123, 92.4751
    ge, gn = parallax.ground_gradient(ground, n_rows, n_cols, dx_m, dy_m)
    all_nodes = np.arange(ground.size)
    for nodes in (all_nodes, rng.choice(ground.size, max(1, ground.size // 3), replace=False), all_nodes[::-1]):
        ge_at, gn_at = parallax.ground_gradient_at(ground, n_rows, n_cols, dx_m, dy_m, nodes)
        assert ge_at.dtype == gn_at.dtype == np.float64
        np.testing.assert_array_equal(ge_at[nodes], ge[nodes], strict=True)
        np.testing.assert_array_equal(gn_at[nodes], gn[nodes], strict=True)
        others = np.setdiff1d(all_nodes, nodes)
        assert not ge_at[others].any() and not gn_at[others].any()
    assert (ge != 0).any() and (gn != 0).any()


def test_the_grids_gradient_at_nodes_matches_its_whole_one(window_db):
    from appliance.locating.position import skyline_grid

    grid = skyline_grid(window_db)
    nodes = np.random.default_rng(3).choice(grid.codes.shape[0], 500, replace=False)
    ge_at, gn_at = grid.ground_gradient_at(nodes)
    g2_at = grid.ground_gradient2_at(nodes)
    ge, gn = grid.ground_gradient
    np.testing.assert_array_equal(ge_at[nodes], ge[nodes], strict=True)
    np.testing.assert_array_equal(gn_at[nodes], gn[nodes], strict=True)
    np.testing.assert_array_equal(g2_at[nodes], grid.ground_gradient2[nodes], strict=True)
    assert grid.ground_gradient_at(nodes)[0] is ge  # once the whole map's is made, it is the one used


def test_ranking_shifts_without_the_normalisers_scores_them_the_same(window_db):
    from appliance.estimator.search import TauModel, ssd_for_shifts
    from appliance.locating.position import skyline_grid

    grid = skyline_grid(window_db)
    assert grid.distance_codes is not None
    rng = np.random.default_rng(4)
    rows = np.sort(rng.choice(grid.codes.shape[0], 300, replace=False))
    measured = grid.skylines_deg(int(rows[7])) + rng.normal(0, 0.2, grid.n_azimuths)
    shifts = np.arange(-4, 5)
    out = []
    for wanted in (True, False):
        tau = TauModel(grid.distance_codes, grid.ground_gradient2_at(rows), grid.rho2_m2, grid.inverse_range2, 0.55,
                       with_penalty=wanted)
        occ = np.empty((rows.size, shifts.size), dtype=np.float32)
        ssd = ssd_for_shifts(grid.codes, grid.offset_deg, grid.step_deg, measured, shifts, rows=rows, tau=tau,
                             occluded=occ)
        out.append((ssd, occ, tau.penalty))
    (ssd_w, occ_w, pen_w), (ssd_n, occ_n, pen_n) = out
    np.testing.assert_array_equal(ssd_n, ssd_w, strict=True)
    np.testing.assert_array_equal(occ_n, occ_w, strict=True)
    assert (pen_w > 0).any() and pen_n.size == 0
