"""The second pass on a narrow view: the parallax weights made only where the shifts read."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.estimator import parallax
from appliance.estimator.search import TauModel, _shift_reach, _ssd_shifts, ssd_for_shifts

N_AZ = 360


def _synthetic(rng: np.random.Generator, n: int = 300) -> tuple[np.ndarray, ...]:
    codes = rng.integers(0, 255, (n, N_AZ)).astype(np.uint8)
    codes[:4, rng.choice(N_AZ, 30, replace=False)] = 255  # some azimuths without terrain
    off = rng.uniform(-2, 2, n).astype(np.float32)
    off[5] = np.nan
    step = rng.uniform(0.02, 0.1, n).astype(np.float32)
    # ranges from tens of metres to tens of km: weights from near 0 to near 1
    dist = rng.integers(0, 200, (n, N_AZ)).astype(np.uint8)
    dist[6, ::7] = 255
    g2 = rng.uniform(0.0, 0.3, n).astype(np.float32)
    return codes, off, step, dist, g2


def _whole_circle(codes, off, step, m, w, rows, shifts, dist, g2, rho2, inv_d2, sig_ref, cap, map_sigma_m):
    """The kernel with every azimuth's weight made, as before the arcs: out, occluded, normalisers."""
    jj = np.nonzero(np.isfinite(m))[0].astype(np.int64)
    out = np.empty(shifts.shape, dtype=np.float32)
    occ = np.empty(shifts.shape, dtype=np.float32)
    pen = np.empty(rows.size)
    _ssd_shifts(codes, off, step, jj, m[jj].astype(np.float32), rows, shifts, out, dist, g2, rho2, inv_d2,
                sig_ref**2, True, pen, True, w[jj].astype(np.float32), float(min(cap, 1e30)), map_sigma_m**2, occ, 0, 0,
                -1)
    return out, occ, pen


@pytest.mark.parametrize("view", [(100, 55), (340, 55), (0, 20), (200, 80)])
@pytest.mark.parametrize("per_row", [True, False])
@pytest.mark.parametrize("cap", [math.inf, 2.0])
def test_the_weights_made_on_the_arcs_give_the_whole_circles_numbers(view, per_row, cap):
    """A narrow view (one across the circle's seam, one with gaps inside it), each row turned to its
    own heading or all to one band: every sum, occluded weight and normaliser is the same number as
    with every azimuth's weight made."""
    rng = np.random.default_rng(view[0] + 7 * per_row)
    codes, off, step, dist, g2 = _synthetic(rng)
    n = codes.shape[0]
    m = np.full(N_AZ, np.nan)
    arc = (view[0] + np.arange(view[1])) % N_AZ
    m[arc] = off[40] + step[40] * np.roll(codes[40], -31)[arc] + rng.normal(0, 0.3, arc.size)
    if view[1] == 80:
        m[arc[rng.choice(view[1], 12, replace=False)]] = np.nan
    w = np.where(np.isfinite(m), rng.uniform(0.3, 1.0, N_AZ), 0.0)
    rows = np.sort(rng.choice(n, 250, replace=False)).astype(np.int64)
    rows[:6] = np.arange(6)
    if per_row:
        shifts = (rng.integers(0, N_AZ, rows.size)[:, None] + np.arange(-3, 4)[None, :]) % N_AZ
    else:
        shifts = np.broadcast_to(np.arange(-4, 5), (rows.size, 9))
    shifts = np.ascontiguousarray(shifts, dtype=np.int64)
    inv_d2 = parallax.inverse_range2_table(20.0, 0.05)
    rho2 = parallax.offset_variance_m2(30.0, 30.0)
    jj = np.nonzero(np.isfinite(m))[0]
    assert _shift_reach(jj, shifts, N_AZ)[2] >= 0  # the arcs are taken
    tau = TauModel(dist, g2, rho2, inv_d2, 0.5, 3.0)
    occ = np.empty(shifts.shape, dtype=np.float32)
    got = ssd_for_shifts(codes, off, step, m, shifts, rows=rows, tau=tau, weights=w, cap_deg2=cap, occluded=occ)
    ref, ref_occ, ref_pen = _whole_circle(codes, off, step, m, w, rows, shifts, dist, g2, rho2, inv_d2, 0.5, cap, 3.0)
    assert np.isfinite(got).sum() > 0.9 * got.size
    assert np.array_equal(got, ref)
    assert np.array_equal(occ, ref_occ)
    assert np.array_equal(tau.penalty, ref_pen)
    # the sums alone (the estimator's second pass): the same sums, no normaliser made
    bare = TauModel(dist, g2, rho2, inv_d2, 0.5, 3.0, with_penalty=False)
    occ_bare = np.empty(shifts.shape, dtype=np.float32)
    got_bare = ssd_for_shifts(codes, off, step, m, shifts, rows=rows, tau=bare, weights=w, cap_deg2=cap,
                              occluded=occ_bare)
    assert np.array_equal(got_bare, ref)
    assert np.array_equal(occ_bare, ref_occ)
    assert bare.penalty.size == 0


def test_the_arcs_of_a_view():
    shifts = (np.array([[10], [350], [0]]) + np.arange(-3, 4)[None, :]) % N_AZ
    # one arc across the seam: 350..359 and 0..19, 30 azimuths; the shifts spread it by 6
    jj = np.concatenate([np.arange(0, 20), np.arange(350, 360)])
    assert _shift_reach(jj, shifts, N_AZ) == (350, 30, 36)
    # a gap inside the view is part of its arc
    assert _shift_reach(np.array([40, 41, 60, 70]), shifts, N_AZ) == (40, 31, 37)
    # a wide view, or rows shifted in different patterns: the whole circle
    assert _shift_reach(np.arange(0, 120), shifts, N_AZ) == (0, 0, -1)
    odd = shifts.copy()
    odd[1, 3] += 1
    assert _shift_reach(jj, odd, N_AZ) == (0, 0, -1)
    assert _shift_reach(np.arange(0, 60), np.broadcast_to(np.arange(-4, 5), (3, 9)), N_AZ) == (0, 60, 68)
