"""How much exact pruning could take off the every-heading first pass (N44W072, 1.44M nodes).

The idea measured: bound every node's first-pass score cheaply from below (stage 1), score in
full only the nodes whose resulting upper log-likelihood comes within a margin of the best lower
one, and keep the stage-1 bound for the others.  For each sigma interval and occlusion weight this
prints, over every node of the tile and the skyline of ``estimator_speed.py``:

- needed: the share of nodes an exact search must score in full whatever the bound (those whose
  first-pass upper log-posterior reaches the rescoring threshold, best lower - RESCORE_MARGIN_NATS,
  or the region's, read from the estimate's own posteriors);
- for each stage-1 bound, the share of nodes left to score in full at a margin of 250 nats (the
  least that keeps the rescored set exact by construction, with a check of the region after) and of
  1000, and the bound's CPU time over that of the full kernel on every node.

Bounds: "az 1/k", the kernel on one pair of azimuths in k (the other weights zeroed; every term is
non-negative, so the partial sums bound the full ones); "shift g", the least over the node's codes
and weights across groups of g consecutive turns (:func:`_floor_kernel`); "means of r", runs of r
measured azimuths against the running means of the codes (:func:`_block_floor_kernel`).  With occlusion a
bound R on the ranked quantity ssd + cap * occluded bounds the likelihood through rho R, where
rho <= 1 is the least ratio over sigma's interval of the cap at sigma to the cap at its midpoint
(the likelihood is that of ssd + occluded * cap(sigma) at each sigma).

The table is added to bench/results/first_pass_pruning.md.

    python bench/first_pass_pruning.py
"""

from __future__ import annotations

import functools
import math
import os
import resource
import sys
from collections.abc import Callable
from datetime import date
from pathlib import Path
from typing import Any

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from appliance.estimator import COARSE_STRIDE, estimate, parallax  # noqa: E402
from appliance.estimator.coarse_kernels import (  # noqa: E402
    BLOCK,
    SHIFT_RUN,
    _code_units,
    _node_weights,
    box_decimate,
    ssd_coarse_best,
)
from appliance.estimator.likelihood import OCCLUDER_SPAN_DEG, best_column_bounds  # noqa: E402
from appliance.estimator.measurement import measure  # noqa: E402
from appliance.estimator.rescore import RESCORE_MARGIN_NATS  # noqa: E402
from appliance.locating.position import skyline_grid  # noqa: E402
from appliance.numerics import FAST_FINITE  # noqa: E402
from bench.estimator_speed import bench_skyline, tile_database  # noqa: E402
from bench.results_file import append_result  # noqa: E402

MARGINS_NATS = (250.0, 1000.0)
#: float32 sums of the bounds may exceed the full sums by a few units in the last place
ROUNDING = 1.0 - 1e-4


@numba.njit(parallel=True, nogil=True, fastmath=FAST_FINITE)
def _floor_kernel(C: np.ndarray, offset: np.ndarray, step: np.ndarray, partial: np.ndarray, m: np.ndarray,
                      w: np.ndarray, T: np.ndarray, lut_w: np.ndarray, lut_p: np.ndarray, use_tau: bool, cap: float,
                      group: int, out: np.ndarray, pen: np.ndarray) -> None:
    """out[i] <= the least over every circular shift k of what :func:`_ssd_coarse_best` ranks,
    out + cap * occ (deg^2), and pen[i] the node's log-normaliser as that kernel makes it.

    The shifts are taken in groups of ``group`` consecutive turns.  Within a group each azimuth t
    meets codes between the least and the greatest of the ``group`` codes it can face, with a
    weight no less than the least of theirs; a term is then at least its weight times the square
    of the measurement's distance to that span, no more than the cap above it (an occluder costs
    the cap), and nothing inside it.  The group's sum of these bounds every shift of the group
    from below, and the least over the groups every shift of the node: d / ``group`` sums per node
    in place of d.  Nodes lacking terrain somewhere (or nodata) get 0, which bounds anything."""
    n, d = C.shape
    n_groups = (d + group - 1) // group
    n_blocks = (n + BLOCK - 1) // BLOCK
    capped = cap < 1e30
    for b in numba.prange(n_blocks):
        ww = np.empty(d, dtype=np.float32)
        mt = np.empty(d, dtype=np.float32)
        c_lo = np.empty(2 * d, dtype=np.float32)
        c_hi = np.empty(2 * d, dtype=np.float32)
        v_lo = np.empty(2 * d, dtype=np.float32)
        cf = np.empty(2 * d, dtype=np.float32)
        vf = np.empty(2 * d, dtype=np.float32)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            o = offset[i]
            pen[i] = 0.0
            if math.isnan(o):
                out[i] = 0.0
                continue
            pen[i] = _node_weights(T[i if use_tau else 0], w, lut_w, lut_p, use_tau, ww)
            if partial[i]:
                out[i] = 0.0
                continue
            scale, cap_c = _code_units(m, o, step[i], cap, mt)
            row = C[i]
            # each azimuth's span of codes and least weight over the group's turns from it on,
            # laid out twice around the circle: a doubled copy of the row first, so that no index wraps
            for x in range(d):
                cf[x] = np.float32(row[x])
                cf[x + d] = cf[x]
                vf[x] = ww[x]
                vf[x + d] = ww[x]
            for x in range(d):
                c_lo[x] = cf[x]
                c_hi[x] = cf[x]
                v_lo[x] = vf[x]
            for j in range(1, group):
                cj = cf[j : j + d]
                vj = vf[j : j + d]
                for x in range(d):
                    c = cj[x]
                    v = vj[x]
                    c_lo[x] = c if c < c_lo[x] else c_lo[x]
                    c_hi[x] = c if c > c_hi[x] else c_hi[x]
                    v_lo[x] = v if v < v_lo[x] else v_lo[x]
            for x in range(d):
                c_lo[x + d] = c_lo[x]
                c_hi[x + d] = c_hi[x]
                v_lo[x + d] = v_lo[x]
            best = np.float32(np.inf)
            zero = np.float32(0.0)
            for g in range(n_groups):
                k0 = g * group
                lo_g = c_lo[k0 : k0 + d]
                hi_g = c_hi[k0 : k0 + d]
                v_g = v_lo[k0 : k0 + d]
                acc = np.float32(0.0)
                if capped:
                    for t in range(d):
                        above = mt[t] - hi_g[t]
                        below = lo_g[t] - mt[t]
                        qa = v_g[t] * above * above
                        qa = qa if qa < cap_c else cap_c
                        qa = qa if above > zero else zero
                        qb = v_g[t] * below * below
                        qb = qb if below > zero else zero
                        acc += w[t] * (qa + qb)
                else:
                    # no occluder: the distance to the span on whichever side the measurement lies
                    for t in range(d):
                        above = mt[t] - hi_g[t]
                        below = lo_g[t] - mt[t]
                        e = above if above > below else below
                        e = e if e > zero else zero
                        acc += w[t] * (v_g[t] * e * e)
                best = acc if acc < best else best
            out[i] = best * scale


@numba.njit(parallel=True, nogil=True, fastmath=FAST_FINITE)
def _block_floor_kernel(C: np.ndarray, offset: np.ndarray, step: np.ndarray, partial: np.ndarray, m: np.ndarray,
                        w: np.ndarray, T: np.ndarray, lut_w: np.ndarray, lut_p: np.ndarray, use_tau: bool,
                        cap: float, size: int, out: np.ndarray, pen: np.ndarray) -> None:
    """As :func:`_floor_kernel`, through the means of runs of ``size`` measured azimuths: over a run,
    sum_t w_t v_t e_t^2 >= size min(w) min(v) e^2, e the difference between the run's mean measurement
    and the mean of the codes it faces (Cauchy-Schwarz), and with a cap no more than min(w) times
    the cap.  The codes' running means are made once per node, then every shift is scored at once
    as in :func:`appliance.estimator.search._ssd_coarse_best`: d / ``size`` terms per shift."""
    n, d = C.shape
    k_pad = ((d + SHIFT_RUN - 1) // SHIFT_RUN) * SHIFT_RUN
    n_ext = d + k_pad + size
    n_runs = d // size
    n_blocks = (n + BLOCK - 1) // BLOCK
    capped = cap < 1e30
    for b in numba.prange(n_blocks):
        ww = np.empty(d, dtype=np.float32)
        mt = np.empty(d, dtype=np.float32)
        cf = np.empty(n_ext, dtype=np.float32)
        vf = np.empty(n_ext, dtype=np.float32)
        cm = np.empty(n_ext, dtype=np.float32)
        vm = np.empty(n_ext, dtype=np.float32)
        acc = np.empty(k_pad, dtype=np.float32)
        inv = np.float32(1.0 / size)
        fs = np.float32(size)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            o = offset[i]
            pen[i] = 0.0
            if math.isnan(o):
                out[i] = 0.0
                continue
            pen[i] = _node_weights(T[i if use_tau else 0], w, lut_w, lut_p, use_tau, ww)
            if partial[i]:
                out[i] = 0.0
                continue
            scale, cap_c = _code_units(m, o, step[i], cap, mt)
            row = C[i]
            for x in range(d):
                cf[x] = np.float32(row[x])
                vf[x] = ww[x]
            for x in range(d, n_ext):
                cf[x] = cf[x - d]
                vf[x] = vf[x - d]
            # running means of the codes and least weights over ``size`` azimuths from each one on
            for x in range(n_ext):
                cm[x] = cf[x]
                vm[x] = vf[x]
            for j in range(1, size):
                cj = cf[j:]
                vj = vf[j:]
                for x in range(n_ext - size + 1):
                    cm[x] += cj[x]
                    vm[x] = vj[x] if vj[x] < vm[x] else vm[x]
            for x in range(n_ext - size + 1):
                cm[x] *= inv
            for k in range(k_pad):
                acc[k] = 0.0
            for r in range(n_runs):
                t0 = r * size
                mm = mt[t0]
                wr = w[t0]
                for j in range(1, size):
                    mm += mt[t0 + j]
                    wr = w[t0 + j] if w[t0 + j] < wr else wr
                if wr == 0:
                    continue
                mm = mm * inv
                c_r = cm[t0 : t0 + k_pad]
                v_r = vm[t0 : t0 + k_pad]
                if capped:
                    for k in range(k_pad):
                        e = mm - c_r[k]
                        q = fs * (v_r[k] * e * e)
                        acc[k] += wr * (q if q < cap_c else cap_c)
                else:
                    for k in range(k_pad):
                        e = mm - c_r[k]
                        acc[k] += wr * (fs * (v_r[k] * e * e))
            best = np.float32(np.inf)
            for k in range(d):
                best = acc[k] if acc[k] < best else best
            out[i] = best * scale


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(f: Callable[..., Any], *args: Any, repeats: int = 3) -> tuple[Any, float]:
    """f(*args) and its least CPU time over every thread (s), after one warm call."""
    out = f(*args)
    cs = []
    for _ in range(repeats):
        c = cpu_s()
        out = f(*args)
        cs.append(cpu_s() - c)
    return out, float(np.min(cs))


def relative_cost(f: Callable[..., Any], full: Callable[[], Any], *args: Any, rounds: int = 3) -> float:
    """f(*args)'s CPU time over full()'s, the two run in alternation (the least of each): the
    machine's load moves both alike."""
    f(*args)
    own, ref = [], []
    for _ in range(rounds):
        c = cpu_s()
        full()
        ref.append(cpu_s() - c)
        c = cpu_s()
        f(*args)
        own.append(cpu_s() - c)
    return min(own) / min(ref)


def rho(meas: Any, weight: float) -> float:
    """The least ratio over sigma's interval of the occlusion cap at sigma to the cap the ranking uses
    (1 without occlusion; <= 0: no bound through the ranked quantity)."""
    if not weight > 0.0:
        return 1.0
    c_ref = meas.cap_deg2
    if not c_ref > 0.0:
        return 0.0

    def cap_at(s: float) -> float:
        kappa = weight * math.sqrt(2.0 * math.pi) * s / ((1.0 - weight) * OCCLUDER_SPAN_DEG)
        return 2.0 * s * s * math.log(1.0 / kappa)

    # the cap is unimodal in sigma: its least over the interval lies at an end
    lo, hi = meas.sigma_lo_deg, meas.sigma_hi_deg
    return min(1.0, cap_at(lo) / c_ref, cap_at(hi) / c_ref)


def upper_from_floor(floor: np.ndarray, pen: np.ndarray, meas: Any, weight: float) -> np.ndarray:
    """Each node's upper log-likelihood bound from a lower bound ``floor`` (deg^2, scaled as the first
    pass scales its sums) on its ranked quantity ssd + cap * occluded."""
    r = rho(meas, weight)
    lo, hi = meas.sigma_lo_deg, meas.sigma_hi_deg
    # a node (nearly) all occluded counts one Gaussian sample, not n - occluded: at most this much more
    slack = max(0.0, -0.5 * math.log(2 * math.pi * lo * lo) + math.log1p(-weight)) if weight > 0 else 0.0
    # the upper bound falls by at least 1 / (2 sigma_hi^2) per deg^2 of the sum: the slack taken off it
    s = np.maximum(floor.astype(np.float64) * ROUNDING * max(r, 0.0) - 2.0 * hi * hi * slack, 0.0)
    _, up, _ = best_column_bounds(s.astype(np.float32)[:, None], np.zeros((s.size, 1), np.float32), pen,
                                  np.zeros(s.size), math.inf, meas.n_eff, lo, hi, weight)
    return up


def main() -> int:
    loaded = tile_database()
    if loaded is None:
        return 0
    _, db = loaded
    g = skyline_grid(db)
    az, el = bench_skyline(db)
    coarse = g.coarse
    partial = coarse[1]
    rows = []
    for sigma in ((0.3, 0.8), (0.5, 2.0), (1.0, 3.0)):
        for weight in (0.0, 0.1):
            meas = measure(g, az, el, sigma, None, weight, 0.0, 20.0)
            m_dec = box_decimate(meas.elevation_deg, COARSE_STRIDE)
            w_nan = box_decimate(np.where(meas.valid, meas.weight, np.nan), COARSE_STRIDE)
            w_dec = np.nan_to_num(w_nan).astype(np.float32)
            scale = meas.n_eff / max(float(np.nansum(w_nan)), 1e-9)
            tau = (g.coarse_tau2(0.0), *parallax.tau2_tables(meas.sigma_ref_deg))
            cap = meas.cap_deg2
            full = functools.partial(ssd_coarse_best, coarse, g.offset_deg, g.step_deg, m_dec, tau, w_dec, cap)
            (s, o, _, pen), full_cpu = timed(full)
            pen64 = pen.astype(np.float64) * scale
            lo, up, _ = best_column_bounds((s * np.float32(scale))[:, None], (o * np.float32(scale))[:, None], pen64,
                                           np.zeros(s.size), cap, meas.n_eff, sigma[0], sigma[1], weight)
            best_lo = float(np.max(lo))
            res = estimate(g, az, el, sigma, None, occlusion_weight=weight, refine=False)
            region_at = res.log_lower + res.log_evidence_lower
            needed = float(np.mean(up >= min(region_at, best_lo - RESCORE_MARGIN_NATS)))
            cells = [f"{sigma[0]}-{sigma[1]}", f"{weight}", f"{needed:.1%}", f"{best_lo - region_at:.0f}"]
            cap32 = np.float32(min(cap, 1e30))
            d = m_dec.size
            for every in (2, 3):
                keep = (np.arange(d) // 2) % every == 0
                ws = np.where(keep, w_dec, 0.0).astype(np.float32)
                s1, o1, _, p1 = ssd_coarse_best(coarse, g.offset_deg, g.step_deg, m_dec, tau, ws, cap)
                cost1 = relative_cost(ssd_coarse_best, full, coarse, g.offset_deg, g.step_deg, m_dec, tau, ws, cap)
                ranked = (s1 + o1 * cap32 if math.isfinite(cap) else s1) * np.float32(scale)
                # the normaliser over the azimuths scored: a part of the node's (its terms are >= 0)
                u1 = upper_from_floor(ranked, p1.astype(np.float64) * scale, meas, weight)
                cells.append(_shares(u1, partial, best_lo, cost1, up))
            T, lut_w, lut_p = tau[0], np.asarray(tau[1], np.float32), np.asarray(tau[2], np.float32)
            m32 = np.nan_to_num(m_dec).astype(np.float32)
            for kernel, size in ((_floor_kernel, 4), (_floor_kernel, 6), (_floor_kernel, 8), (_block_floor_kernel, 2),
                                 (_block_floor_kernel, 3), (_block_floor_kernel, 5)):
                out = np.empty(s.size, np.float32)
                pf = np.empty(s.size, np.float32)
                cost2 = relative_cost(kernel, full, coarse[0], g.offset_deg, g.step_deg, partial, m32, w_dec, T, lut_w,
                                      lut_p, True, float(min(cap, 1e30)), size, out, pf)
                u2 = upper_from_floor(out * np.float32(scale), pf.astype(np.float64) * scale, meas, weight)
                cells.append(_shares(u2, partial, best_lo, cost2, up))
            line = "| " + " | ".join(cells) + f" | {full_cpu * 1e3:.0f} ms |"
            print(line, flush=True)
            rows.append(line + "\n")
    header = ("# Exact pruning of the every-heading first pass (bench/first_pass_pruning.py)\n\n"
              "Each bound's cell: nodes left to score in full at a margin of 250 / 1000 nats; the bound's CPU time "
              "over the full kernel's (the two run in alternation, the least of three each).\n\n")
    table = (f"{date.today()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}, numba threads "
             f"{numba.get_num_threads()}:\n\n"
             "| sigma (deg) | occlusion | needed | best lower - region (nats) | az 1/2 | az 1/3 | shift 4 | shift 6 "
             "| shift 8 | means of 2 | means of 3 | means of 5 | full kernel CPU |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "".join(rows))
    append_result(HERE / "results" / "first_pass_pruning.md", header, table)
    return 0


def _shares(upper: np.ndarray, partial: np.ndarray, best_lo: float, cost: float, exact: np.ndarray) -> str:
    """The shares of nodes left at each margin (nodes lacking terrain somewhere are always scored),
    once the bound is checked against the ``exact`` first-pass upper bounds."""
    whole = ~partial & np.isfinite(exact)
    wrong = int(np.count_nonzero(upper[whole] < exact[whole] - 1e-9 * np.abs(exact[whole])))
    if wrong:
        raise AssertionError(f"the stage-1 bound lies below the first pass at {wrong} nodes")
    left = [float(np.mean((upper >= best_lo - mg) | partial)) for mg in MARGINS_NATS]
    return " / ".join(f"{v:.1%}" for v in left) + f"; {cost:.2f}"


if __name__ == "__main__":
    sys.exit(main())
