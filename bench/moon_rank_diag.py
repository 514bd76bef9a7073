# ruff: noqa: B023
# (the scoring closures are called within the loop iteration that defines them)
"""Where the true place ranks among a whole-body Moon search's contending places, under the ranking
the search uses and under alternatives computed from the same grid search.

For each chosen position of bench/moon_whole_body.py (same seed, same skylines) the grid search runs
over every facet (in process), the facets are combined, and the region's cells are re-scored:

* ``upper``: the unnormalised upper posterior (what fit_on_surface ranks by), recomputed;
* ``lower``: the unnormalised lower posterior;
* ``lin=S``: the linearised parallax fit with the model's spread scaled by S (LINEARISED_SCALE is 0.3);
* ``far=D``: azimuths whose horizon lies nearer than D km left out of the residual sum;
* ``cauchy=C``: the linearised fit's residuals (in sigma's midpoint units) under a Cauchy cost of scale C;
* ``map=M``: the map's height error M m (the search's map_sigma_m) in the linearised fit's variance;
* ``tile``: the upper posterior normalised by the best of its own facet (round robin over facets);
* ``screen``: the SCREEN_PLACES first distinct places by ``upper`` screened on the map's own surface
  (appliance.verification.screen_places), lowest cost first.

A place's rank is that of the first distinct place (two cells apart, greedy in score order, as
appliance.verification.distinct_places) within two node spacings of the truth.

    python bench/moon_rank_diag.py [--positions 0,1,13,15]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.estimator import parallax  # noqa: E402
from appliance.estimator.estimate import _rescore  # noqa: E402
from appliance.numerics import FAST_FINITE  # noqa: E402
from appliance.terrain.mosaic import open_map  # noqa: E402
from appliance.terrain.whole_body import default_spacing_m  # noqa: E402
from appliance.tiled_search import (  # noqa: E402
    SCREEN_PLACES,
    _run,
    _tile_first_pass,
    best_tile,
    combine,
    open_tiled,
    search_tile,
    tile_floor,
)
from appliance.verification import FitSettings, Place, distinct_places, screen_places  # noqa: E402
from bench.moon_whole_body import LOLA, MAX_LAT, PARAMS, measured  # noqa: E402


@numba.njit(cache=True, parallel=True, fastmath=FAST_FINITE)
def linearised_residuals(codes, dist, offset, step, ge, gn, gamma_deg, jj, mj, rows, shifts, rho2, inv_d2, sig2,
                         lin2, offset_prior_m2, heading_prior_deg2, min_d2inv, map2, resid, wout, pen):
    """parallax.linearised_fit's move, and each azimuth's residual after it (deg, NaN where missing
    or, with min_d2inv > 0, where the horizon lies nearer than 1 / sqrt(min_d2inv) m), its weight."""
    n_az = codes.shape[1]
    n_t = jj.size
    az_step = 360.0 / n_az
    for r in numba.prange(rows.size):
        i = rows[r]
        o = offset[i]
        for t in range(n_t):
            resid[r, t] = np.nan
            wout[r, t] = 0.0
        pen[r] = 0.0
        if math.isnan(o):
            continue
        st = step[i]
        sh = shifts[r] % n_az
        sg = math.sin(gamma_deg[i] / parallax.DEG)
        cg = math.cos(gamma_deg[i] / parallax.DEG)
        A = np.zeros((4, 4))
        b = np.zeros(4)
        rows4 = np.zeros((n_t, 4))
        g2 = ge[i] * ge[i] + gn[i] * gn[i]
        p = 0.0
        for t in range(n_t):
            idx = jj[t] + sh
            if idx >= n_az:
                idx -= n_az
            c = codes[i, idx]
            if c == 255:
                continue
            dc = dist[i, idx]
            if min_d2inv > 0.0 and (dc == 255 or inv_d2[dc] > min_d2inv * parallax.DEG * parallax.DEG):
                continue
            e_deg = o + st * c
            res = mj[t] - e_deg
            t2 = lin2 * parallax.tau2_at(codes, dist, i, idx, n_az, o, st, az_step, g2, rho2, inv_d2)
            if dc != 255:
                t2 += map2 * inv_d2[dc]
            w = sig2 / (sig2 + t2)
            p += math.log1p(t2 / sig2)
            jp = idx + 1 if idx + 1 < n_az else 0
            jm = idx - 1 if idx > 0 else n_az - 1
            slope = 0.0
            if codes[i, jp] != 255 and codes[i, jm] != 255:
                slope = (np.float64(codes[i, jp]) - np.float64(codes[i, jm])) * st / (2.0 * az_step)
            row = rows4[t]
            row[2] = slope
            if dc != 255:
                inv_d = math.sqrt(inv_d2[dc])
                e = e_deg / parallax.DEG
                se = e * (1.0 - 0.6666667 * e * e)
                ce = 1.0 - e * e
                az = idx * az_step / parallax.DEG
                sb = math.sin(az) * cg - math.cos(az) * sg
                cb = math.cos(az) * cg + math.sin(az) * sg
                row[0] = inv_d * (se * sb - ce * ge[i] + slope * cb)
                row[1] = inv_d * (se * cb - ce * gn[i] - slope * sb)
                row[3] = -inv_d * ce
            for u in range(4):
                b[u] += w * row[u] * res
                for v in range(4):
                    A[u, v] += w * row[u] * row[v]
            resid[r, t] = res
            wout[r, t] = w
        height_prior_m2 = 0.25 * g2 * offset_prior_m2 + 0.25
        A[0, 0] += sig2 / offset_prior_m2
        A[1, 1] += sig2 / offset_prior_m2
        A[2, 2] += sig2 / heading_prior_deg2
        A[3, 3] += sig2 / height_prior_m2
        x = np.linalg.solve(A, b)
        for t in range(n_t):
            if not math.isnan(resid[r, t]):
                row = rows4[t]
                resid[r, t] -= row[0] * x[0] + row[1] * x[1] + row[2] * x[2] + row[3] * x[3]
        pen[r] = p


def unit(lat, lon):
    la, lo = np.radians(lat), np.radians(lon)
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)


def truth_rank(score, xyz, truth_xyz, apart_rad, near_rad, limit=3000):
    """The rank (1-based) among distinct places (greedy, in ``score`` order) of the first within
    ``near_rad`` of the truth; None beyond ``limit`` places."""
    order = np.argsort(-score, kind="stable")
    order = order[np.isfinite(score[order])][:100000]
    pts = xyz[order]
    near = pts @ truth_xyz >= math.cos(near_rad)
    alive = np.ones(order.size, bool)
    cos_apart = math.cos(apart_rad)
    k = 0
    for n in range(1, limit + 1):
        while k < order.size and not alive[k]:
            k += 1
        if k >= order.size:
            return None
        if near[k]:
            return n
        alive &= pts @ pts[k] < cos_apart
    return None


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--positions", default="0,1,13,15")
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--seed", type=int, default=17)
    args = ap.parse_args()
    source = open_map([str(LOLA)], None)
    dem = source.load()
    spacing = default_spacing_m(dem)
    index = open_tiled(HERE / "cache" / f"moon_whole_body_{spacing:.0f}m_150km")
    radius = dem.body.radius_m
    rng = np.random.default_rng(args.seed)
    s = np.sin(np.radians(MAX_LAT))
    lats = np.degrees(np.arcsin(rng.uniform(-s, s, args.count)))
    lons = rng.uniform(0.0, 360.0, args.count)
    variants = ["upper", "lower", "lin=0.6", "lin=1.0", "far=10", "far=20", "map=30", "map=100", "map=300",
                "map=100+lower", "cauchy=4", "tile"]
    print("pos lat lon cells " + " ".join(variants) + " screen", flush=True)
    print("load:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), flush=True)
    for k in (int(v) for v in args.positions.split(",")):
        lat, lon = float(lats[k]), float(lons[k])
        sky = measured(dem, lat, lon, index.max_range_m, np.random.default_rng(args.seed * 1000 + k))
        t0 = time.perf_counter()
        tiles = list(index.tiles)
        floor = max(_run(index, tile_floor, tiles, None, sky, PARAMS))
        first = _run(index, search_tile, tiles, None, sky, PARAMS, "", False, rescore_floor=floor, region=False)
        best = best_tile(first)
        grid_o = _run(index, search_tile, [t for t in tiles if t.file == best], None, sky, PARAMS, "", False,
                      rescore_floor=floor)
        est = combine(grid_o + [o for o in first if o.file != best], index.body)
        t_grid = time.perf_counter() - t0
        cells = est.region
        by_tile: dict[str, list[int]] = {}
        for i, c in enumerate(cells):
            by_tile.setdefault(c.tile, []).append(i)
        n = len(cells)
        scores = {v: np.full(n, -np.inf) for v in variants}
        sig = 0.5 * (PARAMS.sigma_deg[0] + PARAMS.sigma_deg[1])
        for tname, idx in by_tile.items():
            tile = next(t for t in tiles if t.file == tname)
            db, grid, fp = _tile_first_pass(str(index.folder), tile, sky, PARAMS, None)
            idx = np.array(idx)
            nodes = np.array([cells[i].node for i in idx], dtype=np.int64)
            order = np.argsort(nodes)
            nodes, idx = nodes[order], idx[order]
            meas = fp.meas
            rs = _rescore(grid, meas, nodes, fp.scores.shifts(nodes))
            log_area = math.log(grid.dx_m * grid.dy_m)
            from appliance.estimator.likelihood import log_likelihood_bounds
            lo, up = log_likelihood_bounds(rs.ssd[:, 0], meas.n_eff, *PARAMS.sigma_deg)
            scores["upper"][idx] = up - rs.half_penalty[:, 0] + log_area
            scores["lower"][idx] = lo - rs.half_penalty[:, 0] + log_area
            valid = np.isfinite(meas.elevation_deg)
            jj = np.nonzero(valid)[0].astype(np.int64)
            mj = meas.elevation_deg[jj].astype(np.float64)
            ge, gn = grid.ground_gradient
            half = 0.5 * max(grid.dx_m, grid.dy_m)
            sh = rs.shifts[:, 0].astype(np.int64)

            def run(lin: float, rows: np.ndarray, min_d_km: float = 0.0, map_m: float = 0.0):
                res = np.empty((rows.size, jj.size))
                w = np.empty((rows.size, jj.size))
                pen = np.empty(rows.size)
                d2inv = 0.0 if min_d_km <= 0 else 1.0 / (min_d_km * 1e3) ** 2
                linearised_residuals(grid.codes, grid.distance_codes, grid.offset_deg, grid.step_deg, ge, gn,
                                     grid.convergence_deg, jj, mj, nodes[rows], sh[rows], grid.rho2_m2,
                                     grid.inverse_range2, sig * sig, lin * lin, half * half, grid.az_step_deg ** 2,
                                     d2inv, map_m * map_m, res, w, pen)
                return res, w, pen

            def gauss(res, w, pen, n_eff, lower=False):
                cnt = np.isfinite(res).sum(axis=1)
                scale = n_eff / np.maximum(cnt, 1)
                ssd = np.nansum(w * res * res, axis=1) * scale
                lo_, up_ = log_likelihood_bounds(ssd, n_eff, *PARAMS.sigma_deg)
                return (lo_ if lower else up_) - 0.5 * pen * scale + log_area

            def cauchy(res, w, pen, c):
                cnt = np.isfinite(res).sum(axis=1)
                scale = meas.n_eff / np.maximum(cnt, 1)
                z2 = w * res * res / (sig * sig)
                cost = np.nansum(np.log1p(z2 / (c * c)), axis=1) * c * c * scale
                return -0.5 * cost - 0.5 * pen * scale + log_area

            for a in range(0, nodes.size, 20000):
                rows = np.arange(a, min(a + 20000, nodes.size))
                ix = idx[rows]
                for mm in (30, 100, 300):
                    scores[f"map={mm}"][ix] = gauss(*run(parallax.LINEARISED_SCALE, rows, 0.0, mm), meas.n_eff)
                scores["map=100+lower"][ix] = gauss(*run(parallax.LINEARISED_SCALE, rows, 0.0, 100), meas.n_eff, True)
                for lin in (0.6, 1.0):
                    scores[f"lin={lin}"][ix] = gauss(*run(lin, rows), meas.n_eff)
                for dkm in (10, 20):
                    scores[f"far={dkm}"][ix] = gauss(*run(parallax.LINEARISED_SCALE, rows, dkm), meas.n_eff)
                r03 = run(parallax.LINEARISED_SCALE, rows)
                scores["cauchy=4"][ix] = cauchy(*r03, 4)
            scores["tile"][idx] = scores["upper"][idx] - np.max(scores["upper"][idx])
        stored = np.array([c.log_upper_unnormalised for c in cells])
        agree = np.isfinite(stored)
        drift = float(np.max(np.abs(stored[agree] - scores["upper"][agree]))) if agree.any() else math.nan
        xyz = unit(np.array([c.lat for c in cells]), np.array([c.lon for c in cells]))
        txyz = unit(lat, lon)
        apart = 2.0 * spacing / radius
        ranks = [truth_rank(scores[v], xyz, txyz, apart, apart) for v in variants]
        ranked = [Place(est.best.file, est.best.node, est.best.lat, est.best.lon)]
        ranked += [Place(c.tile, c.node, c.lat, c.lon) for c in sorted(cells, key=lambda c: -c.log_upper_unnormalised)]
        places = distinct_places(ranked, SCREEN_PLACES, 2.0 * spacing, dem)
        settings = FitSettings(index.height_m, index.n_azimuths, index.max_range_m, index.raw.get("refraction"),
                               spacing, PARAMS.sigma_deg, PARAMS.heading_tolerance_deg)
        t1 = time.perf_counter()
        screened = screen_places(dem, sky, places, settings)
        t_screen = time.perf_counter() - t1
        near = [i + 1 for i, (_, p) in enumerate(screened) if unit(p.lat, p.lon) @ txyz >= math.cos(apart)]
        ranks.append(near[0] if near else None)
        print(k, f"{lat:.2f} {lon:.2f}", n, " ".join(str(r) if r is not None else ">3000" for r in ranks),
              f"(grid {t_grid:.1f} s, screen of {len(places)} {t_screen:.1f} s, upper recomputed within "
              f"{drift:.2g} nats)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
