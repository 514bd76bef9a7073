"""The interval-valued likelihood and posteriors against brute force and their defining properties."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.estimator.likelihood import log_likelihood, log_likelihood_bounds, posterior_bounds


def test_likelihood_is_the_n_sample_gaussian():
    rng = np.random.default_rng(0)
    m, s = rng.normal(0, 1, 50), rng.normal(0, 1, 50)
    sigma = 0.7
    direct = float(np.sum(-0.5 * np.log(2 * np.pi * sigma**2) - (m - s) ** 2 / (2 * sigma**2)))
    assert log_likelihood(np.array(np.sum((m - s) ** 2)), 50, sigma) == pytest_approx(direct)


def pytest_approx(v, rel=1e-12):
    import pytest

    return pytest.approx(v, rel=rel)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 500.0), st.integers(1, 400), st.floats(0.05, 2.0), st.floats(1.0, 5.0))
def test_bounds_are_the_extremes_over_sigma(ssd, n, lo, ratio):
    hi = lo * ratio
    lower, upper = log_likelihood_bounds(np.array([ssd]), n, lo, hi)
    sigmas = np.linspace(lo, hi, 2001)
    dense = np.array([log_likelihood(np.array(ssd), n, s) for s in sigmas])
    assert lower[0] <= dense.min() + 1e-6 * max(1.0, abs(dense.min()))
    assert lower[0] >= dense.min() - 1e-6 * max(1.0, abs(dense.min()))
    assert upper[0] >= dense.max() - 1e-9 * max(1.0, abs(dense.max()))
    assert upper[0] <= dense.max() + 1e-3 * max(1.0, abs(dense.max())) + 1e-3


def test_posterior_bounds_match_the_closed_form_on_small_numbers():
    lo = np.log(np.array([0.2, 0.5, 0.1]))
    up = np.log(np.array([0.4, 0.9, 0.3]))
    post = posterior_bounds(lo, up)
    L, U = np.exp(lo), np.exp(up)
    for i in range(3):
        rest_u = U.sum() - U[i]
        rest_l = L.sum() - L[i]
        assert post.lower[i] == pytest_approx(L[i] / (L[i] + rest_u))
        assert post.upper[i] == pytest_approx(U[i] / (U[i] + rest_l))


def test_no_underflow_with_360_samples():
    # residuals of 1 deg on 360 azimuths at sigma 0.2: exp() of the log-likelihood is 0 in floats
    ssd = np.array([360 * 1.0, 360 * 1.1, 360 * 3.0])
    lo, up = log_likelihood_bounds(ssd, 360, 0.2, 0.4)
    assert np.all(np.exp(up) == 0.0)
    post = posterior_bounds(lo, up)
    assert np.all(np.isfinite(post.log_lower)) and np.all(np.isfinite(post.log_upper))
    assert post.upper[0] > 0.5
    assert post.log_lower[0] > post.log_lower[1] > post.log_lower[2]  # ordered, though exp() of them underflows
    assert np.all(post.lower <= post.upper)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0.0, 80.0), min_size=2, max_size=30), st.floats(0.0, 1.0), st.integers(5, 120))
def test_every_precise_posterior_lies_between_the_bounds(ssds, t, n):
    ssd = np.array(ssds)
    lo_s, hi_s = 0.3, 0.9
    lo, up = log_likelihood_bounds(ssd, n, lo_s, hi_s)
    post = posterior_bounds(lo, up)
    sigma = lo_s + t * (hi_s - lo_s)
    ll = log_likelihood(ssd, n, sigma)
    precise = np.exp(ll - np.logaddexp.reduce(ll))
    assert np.all(post.lower <= precise * (1 + 1e-9) + 1e-300)
    assert np.all(precise <= post.upper * (1 + 1e-9) + 1e-300)


def test_prior_enters_both_bounds():
    lo = np.log(np.array([0.5, 0.5]))
    up = np.log(np.array([0.6, 0.6]))
    flat = posterior_bounds(lo, up)
    tilted = posterior_bounds(lo, up, np.log(np.array([0.9, 0.1])))
    assert math.isclose(flat.lower[0], flat.lower[1])
    assert tilted.lower[0] > flat.lower[0] > tilted.lower[1]


def test_best_column_bounds_equal_the_numpy_form():
    from appliance.estimator.likelihood import best_column_bounds, mixture_log_likelihood_bounds, occlusion_cap_deg2

    rng = np.random.default_rng(5)
    n_rows = 3000
    for cols, weight in ((1, 0.0), (3, 0.0), (3, 0.2), (7, 0.05)):
        ssd = rng.gamma(2.0, 40.0, (n_rows, cols)).astype(np.float32)
        ssd[rng.random((n_rows, cols)) < 0.02] = np.inf  # nodes that cannot be candidates
        ssd[::97] = ssd[::97, :1]  # ties: the first column wins
        occ = (rng.random((n_rows, cols)) * 5).astype(np.float32)
        pen = rng.normal(0, 3, n_rows)
        lp = rng.normal(0, 1, n_rows)
        cap = occlusion_cap_deg2(weight, 0.55)
        lo, up, scored = best_column_bounds(ssd, occ, pen, lp, cap, 80.0, 0.3, 0.8, weight)
        ranked = ssd if not math.isfinite(cap) else ssd + occ * cap
        k = np.argmin(ranked, axis=1)
        rows = np.arange(n_rows)
        c, o = ssd[rows, k].astype(np.float64), occ[rows, k].astype(np.float64)
        ref_lo, ref_up = mixture_log_likelihood_bounds(c, 80.0, o, 0.3, 0.8, weight)
        assert np.array_equal(lo, ref_lo - 0.5 * pen + lp)
        # where sigma* lies inside the interval the upper bound takes its logarithm: numpy's log is
        # vectorised on some CPUs (AVX-512) and may round its last bit unlike the C library's, which
        # the kernel calls; there the two agree to rounding, elsewhere bit for bit
        n_i = np.maximum(80.0 - o, 1.0) if weight > 0 else np.full(n_rows, 80.0)
        star = np.sqrt(np.maximum(c, 0.0) / n_i)
        inside = np.isfinite(c) & (star > 0.3) & (star < 0.8)
        assert 0 < inside.sum() < n_rows
        ref = ref_up - 0.5 * pen + lp
        assert np.array_equal(up[~inside], ref[~inside])
        np.testing.assert_allclose(up[inside], ref[inside], rtol=1e-14, atol=0)
        assert scored == int(np.isfinite(c).sum())
