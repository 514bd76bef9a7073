"""The horizon sweep's maximum range: a node sees exactly the terrain of its line within range.

The reference for the cut-off is the plain sweep (no cut-off) run once per canonical column u on
terrain whose columns beyond u + range_columns are nodata: every point of a line lies in one
canonical column, and the plain sweep skips nodata points, so for the nodes of column u that
terrain holds exactly the points in range.  It shares the line placement with the code under test
but none of the cut-off's blocks, second hull or tangent search.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.errors import InputError
from appliance.terrain.sweep import (
    MIN_RANGE_CELLS,
    NEAR_FIELD_COLUMNS,
    HorizonSweeper,
    _orient,
    _unorient,
    range_columns,
)

DX_M, DY_M = 30.0, 40.0
HEIGHT_M = 1.7
R_EFF_M = 8.5e6  # a small body, so curvature matters over a few kilometres
AZIMUTHS_DEG = (0.0, 37.0, 90.0, 135.0, 200.0, 315.0)


def _canonical(az_deg: float, dx_m: float = DX_M, dy_m: float = DY_M) -> tuple[tuple[bool, bool, bool], float]:
    """The canonical orientation (transpose, flip_u, flip_v) of an azimuth and the step (m) between
    columns along its lines, worked out as the azimuth's geometry gives them."""
    a = math.radians(az_deg)
    dcol, drow = math.sin(a) / dx_m, -math.cos(a) / dy_m
    du, dv, du_m, dv_m = dcol, drow, dx_m, dy_m
    if abs(drow) > abs(dcol):
        du, dv, du_m, dv_m = drow, dcol, dy_m, dx_m
    key = (abs(drow) > abs(dcol), du < 0, dv < 0)
    tau = abs(dv / du)
    return key, math.hypot(du_m, tau * dv_m)


def _reference(Z: np.ndarray, az_deg: float, max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Tangents and distances with the cut-off, from the plain sweep on terrain cut per column."""
    key, step = _canonical(az_deg)
    rc = range_columns(max_range_m, step)
    W = np.ascontiguousarray(_orient(Z, *key))
    tan_c = np.full(W.shape, np.nan)
    far_c = np.full(W.shape, np.nan)
    for u in range(W.shape[1]):
        cut = W.copy()
        cut[:, u + rc + 1 :] = np.nan
        tan, far = HorizonSweeper(_unorient(cut, *key), DX_M, DY_M, HEIGHT_M, R_EFF_M).horizons(az_deg)
        tan_c[:, u] = _orient(tan, *key)[:, u]
        far_c[:, u] = _orient(far, *key)[:, u]
    return _unorient(tan_c, *key).copy(), _unorient(far_c, *key).copy()


def _random_terrain(seed: int, shape: tuple[int, int] = (60, 80)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    Z = rng.normal(0.0, 30.0, shape)
    # smooth ridges and a few nodata cells, as real maps have
    Z += 200.0 * np.sin(np.arange(shape[1]) / 9.0)[None, :] * np.cos(np.arange(shape[0]) / 7.0)[:, None]
    Z[rng.random(shape) < 0.01] = np.nan
    return Z


def _peaks_terrain(shape: tuple[int, int] = (60, 80)) -> np.ndarray:
    """Flat ground with a few tall narrow peaks: each is the horizon of many nodes, in range or not."""
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    Z = np.zeros(shape)
    for r, c, h in ((5, 70, 900.0), (50, 10, 700.0), (30, 40, 300.0), (2, 3, 1200.0), (55, 75, 1000.0)):
        Z += h * np.exp(-((rr - r) ** 2 + (cc - c) ** 2) / 4.0)
    return Z


@pytest.mark.parametrize("terrain", ["random", "peaks"])
@pytest.mark.parametrize("max_range_m", [MIN_RANGE_CELLS * math.hypot(DX_M, DY_M), 400.0, 1234.5])
def test_the_cut_off_matches_the_plain_sweep_on_terrain_cut_beyond_range(terrain, max_range_m):
    Z = _random_terrain(3) if terrain == "random" else _peaks_terrain()
    sweeper = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=max_range_m)
    uncut = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M)
    changed = 0
    for az in AZIMUTHS_DEG:
        tan, far = (a.copy() for a in sweeper.horizons(az))
        ref_tan, ref_far = _reference(Z, az, max_range_m)
        np.testing.assert_array_equal(np.isnan(tan), np.isnan(ref_tan))
        np.testing.assert_allclose(tan, ref_tan, rtol=1e-12, atol=1e-15, equal_nan=True)
        # the distance is the reference's unless two points give the same tangent
        same_far = np.isclose(far, ref_far, rtol=1e-9, equal_nan=True)
        assert same_far.mean() > 0.999
        _, step = _canonical(az)
        assert np.nanmax(far) <= range_columns(max_range_m, step) * step * (1 + 1e-12) <= max_range_m * (1 + 1e-12)
        changed += int(np.sum(~np.isclose(uncut.horizons(az)[0], tan, rtol=1e-12, equal_nan=True)))
    assert changed > 100  # the range cuts off a real part of these horizons


def test_a_node_depends_only_on_the_terrain_within_range():
    Z = _random_terrain(11)
    max_range_m = 700.0
    sweeper = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=max_range_m)
    for az in AZIMUTHS_DEG:
        key, step = _canonical(az)
        rc = range_columns(max_range_m, step)
        tan = sweeper.horizons(az)[0].copy()
        # raise everything beyond the range of canonical column 20 very high: column 20 is unchanged
        W = np.ascontiguousarray(_orient(Z, *key))
        W[:, 20 + rc + 1 :] += 5000.0
        moved = HorizonSweeper(_unorient(W, *key), DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=max_range_m)
        again = moved.horizons(az)[0]
        col = np.zeros(W.shape, dtype=bool)
        col[:, 20] = True
        col = _unorient(col, *key)
        np.testing.assert_allclose(again[col], tan[col], rtol=1e-12, equal_nan=True)


def _tile_case():
    """A 70 x 90 map, a window of nodes in its middle, and a range that the map's far peaks exceed."""
    shape = (70, 90)
    rng = np.random.default_rng(5)
    Z = rng.normal(0.0, 5.0, shape)
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    for r, c, h in ((2, 2, 3000.0), (2, 88, 3000.0), (68, 45, 3000.0), (35, 1, 3000.0), (35, 88, 2500.0)):
        Z += h * np.exp(-((rr - r) ** 2 + (cc - c) ** 2) / 6.0)
    window = (28, 38, 12, 14)
    max_range_m = 500.0
    return Z, window, max_range_m


@pytest.mark.parametrize("az", AZIMUTHS_DEG + (180.0, 270.0, 45.0, 226.0))
def test_a_tile_with_a_halo_of_the_range_gives_the_whole_maps_horizons_bit_for_bit(az):
    Z, (r0, c0, wr, wc), max_range_m = _tile_case()
    # the halo holds every point within range: range/spacing cells, and one row more for the
    # interpolation between rows and the quarter row between a node and its line
    halo_r = math.ceil(max_range_m / DY_M) + 2
    halo_c = math.ceil(max_range_m / DX_M) + 2
    tr0, tc0 = r0 - halo_r, c0 - halo_c
    tile = Z[tr0 : r0 + wr + halo_r, tc0 : c0 + wc + halo_c]
    assert tr0 > 0 and tc0 > 0 and r0 + wr + halo_r < Z.shape[0] and c0 + wc + halo_c < Z.shape[1]
    whole = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, (r0, c0, wr, wc), max_range_m=max_range_m)
    part = HorizonSweeper(tile, DX_M, DY_M, HEIGHT_M, R_EFF_M, (halo_r, halo_c, wr, wc),
                          lattice_origin=(tr0, tc0), lattice_shape=Z.shape, max_range_m=max_range_m)
    tan_w, far_w = (a.copy() for a in whole.horizons(az))
    tan_p, far_p = part.horizons(az)
    assert np.isfinite(tan_w).all()
    assert np.array_equal(tan_p, tan_w)
    assert np.array_equal(far_p, far_w)
    # without the cut-off the far peaks, out of the tile, set some of these horizons
    uncut = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, (r0, c0, wr, wc)).horizons(az)[0]
    assert (uncut > tan_w + 1e-6).any()


@pytest.mark.parametrize("az", AZIMUTHS_DEG)
def test_an_infinite_or_longer_than_the_map_range_is_the_plain_sweep_bit_for_bit(az):
    Z = _random_terrain(7)
    plain = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M).horizons(az)
    plain = (plain[0].copy(), plain[1].copy())
    for max_range_m in (math.inf, 1e6, math.hypot(80 * DX_M, 60 * DY_M) * 1.01):
        got = HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=max_range_m).horizons(az)
        assert np.array_equal(got[0], plain[0], equal_nan=True)
        assert np.array_equal(got[1], plain[1], equal_nan=True)


def test_a_range_within_the_near_field_is_refused():
    Z = _random_terrain(1)
    diagonal = math.hypot(DX_M, DY_M)
    assert MIN_RANGE_CELLS > NEAR_FIELD_COLUMNS
    for bad in (0.0, -1.0, math.nan, NEAR_FIELD_COLUMNS * diagonal, MIN_RANGE_CELLS * diagonal * 0.999):
        with pytest.raises(InputError, match="maximum range"):
            HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=bad)
    HorizonSweeper(Z, DX_M, DY_M, HEIGHT_M, R_EFF_M, max_range_m=MIN_RANGE_CELLS * diagonal).horizons(37.0)


def test_range_columns_is_the_whole_columns_within_range():
    assert range_columns(1000.0, 10.0) == 100
    assert range_columns(1000.0, 10.000001) == 99
    assert range_columns(math.inf, 10.0) == -1
