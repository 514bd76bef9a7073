"""How far the skyline may move between nodes: a model variance per node and azimuth.

A database node stands for every position within its cell, but the skyline seen from a point
between nodes differs from the node's: near terrain moves by parallax.  For a horizon point at
range d and elevation e, a displacement delta of the camera with radial component delta_r (towards
the point), lateral component delta_t (to the right of the ray) and ground gradient g changes the
skyline at a fixed azimuth by, to first order (radians),

    de = [sin e cos e * delta_r  -  cos^2 e * (g . delta)  +  s'(alpha) * delta_t] / d,

where s'(alpha) is the skyline's slope along azimuth (rad per rad): moving right turns the ridge
left.  The first term is the point coming closer, the second the eye rising with the ground, the
third the ridge sliding sideways.  With the true position uniform in the node's cell, each
component of delta has variance rho^2 = (dx^2 + dy^2) / 24, and treating the three terms as
independent,

    tau^2 = (rho / d)^2 * [(sin e cos e)^2 + cos^4 e |g|^2 + s'^2]          (rad^2).

The likelihood of a node then uses sigma^2 + tau^2 per azimuth (in quadrature with the sensor's
sigma): a near ridge counts for little in the grid search, a far one fully, and the true node is
never ruled out by the parallax of the walls around it.  The exact answer between nodes comes
from the exact fit (``exact.py``), which renders the terrain itself.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from appliance.estimator.likelihood import is_occluded, variance_log_normaliser, variance_tables, variance_weight
from appliance.numerics import FAST_FINITE

MISSING_CODE = 255
#: Model variances are kept as uint8 codes of log(tau^2): 1e-6 deg^2 * exp(TAU2_LOG_STEP * code).
TAU2_MIN_DEG2 = 1e-6
TAU2_LOG_STEP = 0.1
#: Scale on the uniform-cell standard deviation of the offset between the truth and its node.
OFFSET_SCALE = 1.0
DEG = 180.0 / math.pi


def offset_variance_m2(dx_m: float, dy_m: float) -> float:
    """rho^2: variance of one component of the offset between a point of the cell and its node."""
    return OFFSET_SCALE**2 * (dx_m * dx_m + dy_m * dy_m) / 24.0


def inverse_range2_table(distance_min_m: float, log_step: float) -> np.ndarray:
    """(180/pi)^2 / d^2 for every range code (0 for the missing code): deg^2 per unit of rho^2
    times the bracket of the model."""
    codes = np.arange(256, dtype=np.float64)
    d = distance_min_m * np.exp(log_step * codes)
    out = DEG * DEG / (d * d)
    out[MISSING_CODE] = 0.0
    return out.astype(np.float32)


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def tau2_at(codes: np.ndarray, dist: np.ndarray, i: int, j: int, n_az: int, off: float, st: float,
            az_step_deg: float, g2: float, rho2: float, inv_d2: np.ndarray) -> float:
    """tau^2 (deg^2) of node i at azimuth j, from its codes and ranges (0 where unknown)."""
    c = codes[i, j]
    dc = dist[i, j]
    if c == MISSING_CODE or dc == MISSING_CODE:
        return 0.0
    e = (off + st * c) / DEG
    se = e * (1.0 - 0.6666667 * e * e)  # sin e cos e
    ce = 1.0 - e * e  # cos^2 e
    jp = j + 1 if j + 1 < n_az else 0
    jm = j - 1 if j > 0 else n_az - 1
    cp = codes[i, jp]
    cm = codes[i, jm]
    slope = 0.0
    if cp != MISSING_CODE and cm != MISSING_CODE:
        slope = (np.float64(cp) - np.float64(cm)) * st / (2.0 * az_step_deg)
    return rho2 * inv_d2[dc] * (se * se + ce * ce * g2 + slope * slope)


@numba.njit(cache=True, inline="always")
def map_var_at(dist: np.ndarray, i: int, j: int, map2: float, inv_d2: np.ndarray) -> float:
    """The map's own height error seen at the horizon point (deg^2): sigma_v^2 / d^2."""
    dc = dist[i, j]
    if dc == MISSING_CODE:
        return 0.0
    return map2 * inv_d2[dc]


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def _coarse_tau2(codes: np.ndarray, dist: np.ndarray, offset: np.ndarray, step: np.ndarray, g2: np.ndarray,
                 rho2: float, inv_d2: np.ndarray, factor: int, map2: float, out: np.ndarray) -> None:
    n, n_az = codes.shape
    n_dec = n_az // factor
    az_step = 360.0 / n_az
    inv_log = 1.0 / TAU2_LOG_STEP
    for i in numba.prange(n):
        o = offset[i]
        if math.isnan(o):
            for t in range(n_dec):
                out[i, t] = 0
            continue
        st = step[i]
        for t in range(n_dec):
            acc = 0.0
            for j in range(t * factor, (t + 1) * factor):
                acc += tau2_at(codes, dist, i, j, n_az, o, st, az_step, g2[i], rho2, inv_d2)
                acc += map_var_at(dist, i, j, map2, inv_d2)
            v = acc / factor
            if v <= TAU2_MIN_DEG2:
                out[i, t] = 0
            else:
                out[i, t] = min(int(round(math.log(v / TAU2_MIN_DEG2) * inv_log)), MISSING_CODE - 1)


def coarse_tau2_codes(codes: np.ndarray, dist: np.ndarray, offset_deg: np.ndarray, step_deg: np.ndarray,
                      g2: np.ndarray, rho2: float, inv_d2: np.ndarray, factor: int,
                      map_sigma_m: float = 0.0) -> np.ndarray:
    """Mean tau^2 (parallax and the map's height error) over runs of ``factor`` azimuths, as uint8
    log codes, shape (n_nodes, n_az / factor)."""
    n, n_az = codes.shape
    out = np.empty((n, n_az // factor), dtype=np.uint8)
    _coarse_tau2(codes, dist, offset_deg, step_deg, g2, rho2, inv_d2, factor, map_sigma_m * map_sigma_m, out)
    return out


def tau2_tables(sigma_ref_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """For every tau^2 code: the weight sigma^2 / (sigma^2 + tau^2) of a squared residual, and the
    log-normaliser log(1 + tau^2 / sigma^2) that the wider Gaussian pays."""
    tau2 = TAU2_MIN_DEG2 * np.exp(TAU2_LOG_STEP * np.arange(256, dtype=np.float64))
    tau2[0] = 0.0
    return variance_tables(tau2, sigma_ref_deg)


#: The share of the parallax model's spread left once a node's skyline is moved by its own
#: first-order parallax (the linearised fit): what the linear model cannot say.
LINEARISED_SCALE = 0.3


def ground_gradient(ground_m: np.ndarray, n_rows: int, n_cols: int, dx_m: float,
                    dy_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(dz/d east, dz/d north) of the ground at every node (0 where unknown), float64."""
    z = np.asarray(ground_m, dtype=np.float64).reshape(n_rows, n_cols)
    if n_rows < 2 or n_cols < 2:
        zero = np.zeros(n_rows * n_cols)
        return zero, zero.copy()
    gy, gx = np.gradient(z, dy_m, dx_m)
    # rows grow southwards: north is -row
    return np.nan_to_num(gx).ravel(), np.nan_to_num(-gy).ravel()


def ground_gradient_at(ground_m: np.ndarray, n_rows: int, n_cols: int, dx_m: float, dy_m: float,
                       nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ground_gradient` at ``nodes`` (flat indices) only, 0 at every other node: the same
    numbers bit for bit (np.gradient's central differences inside the grid, one-sided on its edges,
    in float64), from the heights beside those nodes instead of the whole map's."""
    n = n_rows * n_cols
    ge = np.zeros(n)
    gn = np.zeros(n)
    if n_rows < 2 or n_cols < 2:
        return ge, gn
    idx = np.asarray(nodes, dtype=np.int64).ravel()
    z = np.asarray(ground_m).reshape(n)
    r, c = np.divmod(idx, n_cols)

    def diff(plus: np.ndarray, minus: np.ndarray, inside: np.ndarray, spacing: float) -> np.ndarray:
        d = z[plus].astype(np.float64) - z[minus].astype(np.float64)
        return np.where(inside, d / (2. * spacing), d / spacing)

    gx = diff(r * n_cols + np.minimum(c + 1, n_cols - 1), r * n_cols + np.maximum(c - 1, 0),
              (c > 0) & (c < n_cols - 1), dx_m)
    gy = diff(np.minimum(r + 1, n_rows - 1) * n_cols + c, np.maximum(r - 1, 0) * n_cols + c,
              (r > 0) & (r < n_rows - 1), dy_m)
    ge[idx] = np.nan_to_num(gx)
    gn[idx] = np.nan_to_num(-gy)
    return ge, gn


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def parallax_row(codes: np.ndarray, dist: np.ndarray, inv_d2: np.ndarray, i: int, idx: int, st: float,
                  e_deg: float, sin_az: np.ndarray, cos_az: np.ndarray, sg: float, cg: float, ge: float, gn: float,
                  row: np.ndarray) -> None:
    """d(elevation) of node i at grid azimuth ``idx`` per move (east m, north m, heading deg, eye
    height m) into ``row``: its horizon point's parallax at elevation ``e_deg`` under ground gradient
    (``ge``, ``gn``), the azimuth tables turned by the node's convergence (sine ``sg``, cosine
    ``cg``); the heading's alone where its range is unknown."""
    n_az = codes.shape[1]
    az_step = 360.0 / n_az
    dc = dist[i, idx]
    jp = idx + 1 if idx + 1 < n_az else 0
    jm = idx - 1 if idx > 0 else n_az - 1
    slope = 0.0
    if codes[i, jp] != MISSING_CODE and codes[i, jm] != MISSING_CODE:
        slope = (np.float64(codes[i, jp]) - np.float64(codes[i, jm])) * st / (2.0 * az_step)
    row[0] = 0.0
    row[1] = 0.0
    row[2] = slope
    row[3] = 0.0
    if dc != MISSING_CODE:
        inv_d = math.sqrt(inv_d2[dc])  # deg per metre of range
        e = e_deg / DEG
        se = e * (1.0 - 0.6666667 * e * e)
        ce = 1.0 - e * e
        sb = sin_az[idx] * cg - cos_az[idx] * sg
        cb = cos_az[idx] * cg + sin_az[idx] * sg
        row[0] = inv_d * (se * sb - ce * ge + slope * cb)
        row[1] = inv_d * (se * cb - ce * gn - slope * sb)
        row[3] = -inv_d * ce


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def _normal_equations(codes: np.ndarray, dist: np.ndarray, i: int, o: float, st: float, sh: int, jj: np.ndarray,
                      mj: np.ndarray, wj: np.ndarray, rho2: float, inv_d2: np.ndarray, sig2: float, lin2: float,
                      cap: float, map2: float, ge: float, gn: float, g2: float, sin_az: np.ndarray, cos_az: np.ndarray,
                      sg: float, cg: float, A: np.ndarray, b: np.ndarray) -> tuple[float, float, float, int]:
    """Node i's weighted normal equations at whole shift ``sh`` added into ``A`` and ``b``
    (:func:`linearised_fit`'s arguments; ``sg``, ``cg`` the sine and cosine of its convergence):
    its weighted residual sum, log-normaliser, occluded weight and count of azimuths with terrain
    (``g2`` is the gradient's square)."""
    n_az = codes.shape[1]
    az_step = 360.0 / n_az
    row = np.zeros(4)
    rr = 0.0
    p = 0.0
    occ = 0.0
    cnt = 0
    for t in range(jj.size):
        idx = jj[t] + sh
        if idx >= n_az:
            idx -= n_az
        c = codes[i, idx]
        if c == MISSING_CODE:
            continue
        cnt += 1
        e_deg = o + st * c
        res = mj[t] - e_deg
        t2 = lin2 * tau2_at(codes, dist, i, idx, n_az, o, st, az_step, g2, rho2, inv_d2)
        t2 += map_var_at(dist, i, idx, map2, inv_d2)
        w = variance_weight(sig2, t2)
        p += wj[t] * variance_log_normaliser(sig2, t2)
        if is_occluded(res, w * res * res, cap):
            occ += wj[t]
            continue
        w *= wj[t]
        parallax_row(codes, dist, inv_d2, i, idx, st, e_deg, sin_az, cos_az, sg, cg, ge, gn, row)
        for u in range(4):
            b[u] += w * row[u] * res
            for v in range(4):
                A[u, v] += w * row[u] * row[v]
        rr += w * res * res
    return rr, p, occ, cnt


@numba.njit(cache=True, inline="always", fastmath=FAST_FINITE)
def add_move_prior(A: np.ndarray, sig2: float, g2: float, offset_prior_m2: float, heading_prior_deg2: float) -> None:
    """The move's Gaussian prior added to normal equations ``A`` over (east m, north m, heading deg,
    eye height m), in the residuals' units (deg^2 per sigma^2 of weight): ``offset_prior_m2`` per
    axis, ``heading_prior_deg2``, and for the eye the ground's rise over the offset (``g2`` the
    gradient's square) plus a quarter of a square metre."""
    height_prior_m2 = 0.25 * g2 * offset_prior_m2 + 0.25
    A[0, 0] += sig2 / offset_prior_m2
    A[1, 1] += sig2 / offset_prior_m2
    A[2, 2] += sig2 / heading_prior_deg2
    A[3, 3] += sig2 / height_prior_m2


@numba.njit(cache=True, parallel=True, nogil=True, fastmath=FAST_FINITE)
def linearised_fit(codes: np.ndarray, dist: np.ndarray, offset: np.ndarray, step: np.ndarray, ge: np.ndarray,
                   gn: np.ndarray, gamma_deg: np.ndarray, jj: np.ndarray, mj: np.ndarray, rows: np.ndarray,
                   shifts: np.ndarray, rho2: float, inv_d2: np.ndarray, sig2: float, lin2: float,
                   offset_prior_m2: float, heading_prior_deg2: float, wj: np.ndarray, cap: float, map2: float,
                   out: np.ndarray, pen: np.ndarray, delta: np.ndarray, occ_out: np.ndarray) -> None:
    """For node rows[r] at whole shift shifts[r]: the best move (east m, north m, heading deg, eye
    height m) of its skyline under the first-order parallax model, and the weighted residual sum.

    The eye's height is free beside the ground plane's g . delta: the node's gradient comes from
    its neighbours two cells apart and the ground under the camera may bend away from it.  Each
    azimuth's residual is weighted by sigma^2 / (sigma^2 + lin2 * tau^2); the move has a Gaussian
    prior (``offset_prior_m2`` per axis, ``heading_prior_deg2``, and for the height the ground's
    rise over the offset).  out[r] is the minimum of the weighted sum plus the prior's term, in
    deg^2; pen[r] the log-normaliser.  ``wj`` weighs each measured azimuth (the detector's
    confidence); a residual above the model whose weighted square exceeds ``cap`` is an occluder
    (``likelihood.occlusion_cap_deg2``): it leaves the fit and the sum alone and is counted, by its
    weight, in occ_out[r].  ``map2`` is the map's height variance (m^2)."""
    n_az = codes.shape[1]
    n_t = jj.size
    az_step = 360.0 / n_az
    sin_az = np.empty(n_az)
    cos_az = np.empty(n_az)
    for j in range(n_az):
        sin_az[j] = math.sin(j * az_step / DEG)
        cos_az[j] = math.cos(j * az_step / DEG)
    for r in numba.prange(rows.size):
        i = rows[r]
        o = offset[i]
        pen[r] = 0.0
        # grid azimuth = true azimuth - convergence: turn the tables by the node's convergence
        sg = math.sin(gamma_deg[i] / DEG)
        cg = math.cos(gamma_deg[i] / DEG)
        for q in range(4):
            delta[r, q] = 0.0
        occ_out[r] = 0.0
        if math.isnan(o):
            out[r] = np.inf
            continue
        A = np.zeros((4, 4))
        b = np.zeros(4)
        g2 = ge[i] * ge[i] + gn[i] * gn[i]
        rr, p, occ, cnt = _normal_equations(codes, dist, i, o, step[i], shifts[r] % n_az, jj, mj, wj, rho2, inv_d2,
                                            sig2, lin2, cap, map2, ge[i], gn[i], g2, sin_az, cos_az, sg, cg, A, b)
        if cnt < (1.0 - 0.1) * n_t or cnt == 0:
            out[r] = np.inf
            continue
        scale = n_t / cnt
        add_move_prior(A, sig2, g2, offset_prior_m2, heading_prior_deg2)
        x = np.linalg.solve(A, b)
        for q in range(4):
            delta[r, q] = x[q]
        out[r] = max(rr - (b[0] * x[0] + b[1] * x[1] + b[2] * x[2] + b[3] * x[3]), 0.0) * scale
        pen[r] = p * scale
        occ_out[r] = occ * scale
