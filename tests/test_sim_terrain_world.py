"""The world generator of bench/world_gap.py: canopy, clearings, correlated noise, decimation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from affine import Affine

from appliance.sim import terrain_world as tw
from appliance.terrain.elevation import affine_apply

CELL_M = (30.0, 30.0)


def _hills(n_rows: int = 160, n_cols: int = 200) -> np.ndarray:
    r, c = np.mgrid[0:n_rows, 0:n_cols]
    return 800.0 + 300.0 * np.sin(r / 17.0) * np.cos(c / 23.0) + 2.0 * r


def test_canopy_only_raises_heights_and_covers_the_requested_share() -> None:
    ground = _hills()
    eligible = ground < 1000.0
    canopy = tw.forest_canopy_m(eligible, CELL_M, np.random.default_rng(3), cover_fraction=0.65,
                                semi_axis_range_m=(100.0, 300.0))
    assert canopy.min() >= 0.0
    assert canopy.max() <= 25.0
    assert np.all(canopy[~eligible] == 0.0)
    covered = canopy > tw.COVER_THRESHOLD_M
    assert 0.65 <= covered[eligible].mean() <= 0.72
    world = ground + canopy
    assert np.all(world >= ground)
    # flat tops: most covered cells sit at a patch height of 15-25 m
    assert np.mean(canopy[covered] >= 15.0) > 0.5


def test_noise_has_the_stated_rms_and_correlation_length() -> None:
    cell_m = (20.0, 25.0)
    correlation_m = 100.0
    noise = tw.correlated_noise_m((600, 600), 4.0, correlation_m, cell_m, np.random.default_rng(7))
    assert np.std(noise) == pytest.approx(4.0, rel=0.06)
    assert abs(np.mean(noise)) < 0.4
    # autocorrelation exp(-(r / L)^2): 1/e at one correlation length, along both axes
    assert tw.autocorrelation(noise, 5, axis=1) == pytest.approx(math.exp(-1.0), abs=0.05)
    assert tw.autocorrelation(noise, 4, axis=0) == pytest.approx(math.exp(-1.0), abs=0.05)
    assert tw.autocorrelation(noise, 10, axis=1) == pytest.approx(math.exp(-4.0), abs=0.05)


def test_decimation_keeps_the_georeferencing() -> None:
    t = Affine(10.0, 0.0, 561_195.0, 0.0, -10.0, 5_119_475.0)
    r, c = np.mgrid[0:31, 0:44]
    x, y = affine_apply(t, c + 0.5, r + 0.5)  # world pixel centres
    plane = 0.3 * x - 0.7 * y
    for method in ("mean", "subsample"):
        z, t3 = tw.decimate(plane, t, 3, method)
        assert z.shape == (10, 14)
        assert (t3.a, t3.e, t3.c, t3.f) == (30.0, -30.0, t.c, t.f)
        rr, cc = np.mgrid[0 : z.shape[0], 0 : z.shape[1]]
        xm, ym = affine_apply(t3, cc + 0.5, rr + 0.5)
        # a plane keeps its value at the map's pixel centres: the map cell sits on its block's centre
        np.testing.assert_allclose(z, 0.3 * xm - 0.7 * ym, atol=1e-6)
    with pytest.raises(ValueError):
        tw.decimate(plane, t, 2, "subsample")


def test_decimation_mean_is_the_block_mean_and_nodata_spreads() -> None:
    z = np.arange(36, dtype=float).reshape(6, 6)
    z[5, 5] = np.nan
    out, _ = tw.decimate(z, Affine.identity(), 3, "mean")
    assert out[0, 0] == pytest.approx(np.mean(z[:3, :3]))
    assert np.isnan(out[1, 1])


def test_clearings_really_have_no_canopy() -> None:
    ground = _hills()
    eligible = np.ones(ground.shape, bool)
    rng = np.random.default_rng(11)
    canopy = tw.forest_canopy_m(eligible, CELL_M, rng, cover_fraction=0.8)
    carved, clearings = tw.carve_clearings(canopy, CELL_M, rng, 6, radius_range_m=(90.0, 150.0))
    assert len(clearings) == 6
    assert np.all(carved <= canopy)
    r, c = np.mgrid[0 : ground.shape[0], 0 : ground.shape[1]]
    for cl in clearings:
        assert canopy[int(cl.row), int(cl.col)] > tw.COVER_THRESHOLD_M  # it was forest
        d_m = np.hypot((r - cl.row) * CELL_M[1], (c - cl.col) * CELL_M[0])
        assert np.all(carved[d_m <= cl.radius_m] == 0.0)
    # away from every clearing's rim the forest is untouched
    far = np.ones(ground.shape, bool)
    for cl in clearings:
        far &= np.hypot((r - cl.row) * CELL_M[1], (c - cl.col) * CELL_M[0]) > cl.radius_m + 60.0
    np.testing.assert_array_equal(carved[far], canopy[far])


def test_buildings_stand_on_the_ground_and_leave_the_site_free() -> None:
    ground = _hills()
    sites = [(80.0, 100.0), (40.0, 40.0)]
    world = tw.add_buildings_m(ground, CELL_M, sites, np.random.default_rng(5), per_site=4,
                               distance_range_m=(120.0, 300.0), footprint_cells=(2, 4))
    added = world - ground
    assert added.min() >= 0.0
    assert added.max() <= 30.0 + (ground.max() - ground.min())
    built = added > 0
    assert built.any()
    r, c = np.mgrid[0 : ground.shape[0], 0 : ground.shape[1]]
    for r0, c0 in sites:
        near = np.hypot((r - r0) * CELL_M[1], (c - c0) * CELL_M[0]) < 120.0
        np.testing.assert_array_equal(world[near], ground[near])
