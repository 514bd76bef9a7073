"""Continuous refinement on exact renders: position and heading between nodes, where parallax rules.

The grid search ranks nodes; near terrain moves by parallax between them, so a blend of the nodes'
skylines cannot say what is seen in between.  Here the skyline at a continuous position is
rendered from the terrain itself (``estimator/raycast.py``: the heights the database was built on,
sampled finely near the eye), at the true azimuths the measured skyline maps to under the trial
heading, and position and heading are fitted by Levenberg-Marquardt on those renders.

The Jacobian is the parallax of every horizon point (``parallax.py``): for range d, elevation e,
ground gradient g and skyline slope s' along azimuth, a move delta of the camera changes the
skyline at a fixed azimuth by [sin e cos e (u . delta) - cos^2 e (g . delta) + s' (t . delta)] / d,
with u the ray's direction and t its right-hand normal; a heading change by s'.  Every trial step
is checked on a new render, so the answer is the exact render's, not the linear model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from appliance.estimator.likelihood import kernel_cap, occluded_mask, variance_weighted
from appliance.estimator.raycast import Terrain, bilinear, render

DEG = 180.0 / math.pi
#: np.radians's factor
RAD = math.pi / 180.0
MAX_ITERATIONS = 10
#: Trial steps per iteration before giving up, and the relative reduction of the residual sum
#: below which the fit has converged.
MAX_REJECTIONS = 3
STOP_REDUCTION = 0.005
#: The map's height error under the camera (m, one sigma): the eye's height floats this much.
EYE_SIGMA_M = 2.0
#: A fit whose RMS residual is within this many sigma is at the noise: annealing stops there.
CONVERGED_NOISE = 1.5
#: Residuals beyond this many standard deviations count ever less (Cauchy).
ROBUST_SCALE = 3.0
#: The parameters' spread (cells) when a fit starts, and its shrinking at every iteration.
START_SPREAD_CELLS = 0.4
ANNEAL = 0.1
#: How far either side of its start heading a look scans (deg, in steps of 0.1).
SCREEN_SCAN_DEG = 8.0
#: How far (cells) a fit may wander from the node it started at.
MAX_OFFSET_CELLS = 2.0
#: The sectors of azimuth (deg) whose pulls on a fit are compared (:attr:`Fit.sector_pulls`): several
#: times the correlation of a levelled head's and a stitched panorama's errors (a few degrees), so that
#: sectors' errors are nearly independent, and at least a dozen around a panorama.
SECTOR_DEG = 30.0


@dataclass(frozen=True)
class Model:
    """How measurements meet renders: per-azimuth weights (confidence, masks; None = 1), the
    occlusion cap (deg^2, ``likelihood.occlusion_cap_deg2``) and the map's vertical error (m)."""

    measurement_weights: np.ndarray | None = None
    cap_deg2: float = math.inf
    map_sigma_m: float = 0.0

    @property
    def eye_sigma_m(self) -> float:
        """How far the eye may float from the map's surface (1 sigma): the map's error, at least
        EYE_SIGMA_M."""
        return max(EYE_SIGMA_M, self.map_sigma_m)

    def weights_for(self, valid: np.ndarray) -> np.ndarray:
        w = self.measurement_weights
        return valid.astype(float) if w is None else np.where(valid, w, 0.0)

    def weights(self, valid: np.ndarray, distance_m: np.ndarray, sigma_deg: float) -> np.ndarray:
        """Each azimuth's weight sigma^2 / (sigma^2 + (sigma_v / d)^2), times its measurement weight."""
        u = self.weights_for(valid)
        if self.map_sigma_m > 0.0:
            m2 = (DEG * self.map_sigma_m / np.maximum(distance_m, 1.0)) ** 2
            u = variance_weighted(u, sigma_deg, m2)
        return u

    def hidden(self, r: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The measurements taken for occluders: above the render (residual ``r`` > 0) by more than
        the cap (weighted square u r^2)."""
        return occluded_mask(r, u * r * r, self.cap_deg2)

    def split(self, r: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Over the last axis: the sum of u r^2 over the measurements the terrain explains, and the
        weight of those above it by more than the cap (occluders)."""
        q = u * r * r
        hidden = occluded_mask(r, q, self.cap_deg2)
        return np.sum(np.where(hidden, 0.0, q), axis=-1), np.sum(np.where(hidden, u, 0.0), axis=-1)

    def cost(self, r: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Sum over the last axis of u r^2, each occluded term counting the cap: the residual sum at
        sigma's reference, which ranks trial positions and headings."""
        ssd, occ = self.split(r, u)
        return ssd + occ * kernel_cap(self.cap_deg2)


@dataclass(frozen=True)
class PositionPrior:
    """A Gaussian belief about the position in fractional grid cells (row, col): the last estimate
    of a traverse moved by the odometry (``fusion.transport_fix``).  ``information`` is the inverse
    of its 2 x 2 covariance (cells^-2)."""

    row: float
    col: float
    information: np.ndarray

    def cost(self, p: np.ndarray) -> float:
        """Its share of a fit's cost (chi-square units): the squared Mahalanobis distance."""
        d = np.array([p[0] - self.row, p[1] - self.col])
        return float(d @ self.information @ d)


@dataclass(frozen=True)
class Fit:
    """A refined candidate: fractional node (row, col), heading correction, residual sum over n;
    ``covariance_cells`` is the 2 x 2 covariance of (row, col) (cells^2) from the fit's curvature."""

    row: float
    col: float
    heading_deg: float
    ssd: float
    n: int
    iterations: int
    eye_offset_m: float = 0.0
    occluded: float = 0.0  # weight of the measurements taken for occluders (not in ssd)
    covariance_cells: np.ndarray | None = None
    #: (n_az,) measured minus rendered (deg) on the azimuth grid, NaN where missing or occluded
    residual_deg: np.ndarray | None = None
    #: (4, 4) Gauss-Newton curvature of the residual sum over (row, col, heading, eye) at unit sigma
    #: (J^T diag(u) J, u the measurement weights), and the priors' information (P) on the same parameters
    curvature: np.ndarray | None = None
    prior_information: np.ndarray | None = None
    #: the head's residual tilt fitted (deg): the elevation change t1 cos(a) + t2 sin(a) over azimuth a
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    #: per SECTOR_DEG sector of azimuth holding explained azimuths, its pull on the parameters
    #: J^T diag(u) r (k, p) and its share of the curvature J^T diag(u) J (k, p, p), at unit sigma as
    #: ``curvature``: what the fit would do without each sector (a jackknife over sectors)
    sector_pulls: np.ndarray | None = None
    sector_curvatures: np.ndarray | None = None

    @property
    def rms_deg(self) -> float:
        return math.sqrt(self.ssd / max(self.n, 1))


def _gradient(terrain: Terrain, row: float, col: float, dx_m: float, dy_m: float) -> tuple[float, float]:
    """Ground gradient (dz/d east, dz/d north) at fractional node (row, col), central differences."""
    Z = terrain.heights64
    tr, tc = row + terrain.row0, col + terrain.col0
    h = 0.5
    ge = (bilinear(Z, tr, tc + h) - bilinear(Z, tr, tc - h)) / (2 * h * dx_m)
    gn = (bilinear(Z, tr - h, tc) - bilinear(Z, tr + h, tc)) / (2 * h * dy_m)
    return (ge if math.isfinite(ge) else 0.0), (gn if math.isfinite(gn) else 0.0)


def screen(
    terrain: Terrain,
    dx_m: float,
    dy_m: float,
    measured: np.ndarray,
    row: float,
    col: float,
    gamma_deg: float,
    heading_deg: float,
    heading_bounds_deg: tuple[float, float],
    height_m: float | None = None,
    sigma_deg: float = 0.3,
    model: Model | None = None,
    spread_cells: float = 0.0,
) -> tuple[float, float]:
    """(cost, heading) of the best heading (within the bounds) at one position, from one exact
    render interpolated along azimuth, the eye's height fitted to first order under its prior: a
    cheap look before a full fit.

    With ``spread_cells`` > 0 the look stands for a neighbourhood of that spread (1 sigma, cells):
    each azimuth's variance grows by its parallax over the spread (J var J^T), and the cost is
    -2 sigma^2 log of the Gaussian with that variance, so a point near a sharp optimum is not
    judged by the near ridges that swing across it."""
    mdl = Model() if model is None else model
    n_az = measured.size
    step = 360.0 / n_az
    az = np.arange(n_az) * step
    valid = np.isfinite(measured)
    h_m = terrain.height_m if height_m is None else float(height_m)
    s, d, _ = render(terrain, dx_m, dy_m, row, col, az + heading_deg - gamma_deg,
                     terrain.look_distances(min(dx_m, dy_m)), h_m)
    ok_s = np.isfinite(s) & np.isfinite(d)
    if ok_s.sum() < 0.9 * n_az:
        return math.inf, heading_deg
    filled = np.interp(az, az[ok_s], s[ok_s], period=360.0)
    dz = np.interp(az, az[ok_s], -DEG * np.cos(np.radians(s[ok_s])) ** 2 / d[ok_s], period=360.0)
    lo, hi = heading_bounds_deg
    trial = heading_deg + np.arange(-SCREEN_SCAN_DEG, SCREEN_SCAN_DEG + 1e-9, 0.1)
    trial = trial[(trial >= lo) & (trial <= hi)]
    if trial.size == 0:
        trial = np.array([min(max(heading_deg, lo), hi)])
    sky = turned_interp((trial - heading_deg) / step, n_az, az, filled, 360.0)
    r = np.where(valid[None, :], measured[None, :] - sky, 0.0)
    d_all = d if ok_s.all() else np.interp(az, az[ok_s], d[ok_s], period=360.0)
    u = mdl.weights(valid, d_all, sigma_deg)
    log_var = 0.0
    if spread_cells > 0.0:
        J = jacobian(terrain, dx_m, dy_m, row, col, az + heading_deg - gamma_deg, filled, d_all)
        ratio = 1.0 + (J[:, 0] ** 2 + J[:, 1] ** 2) * spread_cells**2 / sigma_deg**2
        u = u / ratio
        log_var = sigma_deg**2 * float(np.sum(np.where(valid, np.log(ratio), 0.0)))
    # the eye's height, to first order, with its prior
    jz = np.where(valid, dz, 0.0)
    prior = (sigma_deg / mdl.eye_sigma_m) ** 2
    h = ((r * u) @ jz) / ((u * jz) @ jz + prior)
    r = r - h[:, None] * jz[None, :]
    cost = mdl.cost(r, u) + prior * h * h + log_var
    k = int(np.argmin(cost))
    return float(cost[k]), float(trial[k])


def _periodic_knots(xp: np.ndarray, fp: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The knots as ``np.interp(..., period=period)`` makes them: wrapped into the period, sorted,
    and extended by one period each way."""
    xp = np.asarray(xp, dtype=np.float64) % period
    order = np.argsort(xp)
    xp, fp = xp[order], np.asarray(fp, dtype=np.float64)[order]
    return np.concatenate((xp[-1:] - period, xp, xp[0:1] + period)), np.concatenate((fp[-1:], fp, fp[0:1]))


def turned_interp(turn: np.ndarray, n: int, xp: np.ndarray, fp: np.ndarray, period: float) -> np.ndarray:
    """``np.interp(((np.arange(n)[None, :] + turn[:, None]) % n) * (period / n), xp, fp,
    period=period)``: the same numbers (one row per turn, in steps of the ``n`` azimuths), compiled."""
    xk, fk = _periodic_knots(xp, fp, period)
    x = np.empty((turn.size, n))
    _turned_points(np.ascontiguousarray(turn, dtype=np.float64), n, period / n, x)
    out = np.empty_like(x)
    _interp_points(x.ravel(), xk, fk, float(period), out.ravel())
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _wrapped(x: float, period: float) -> float:
    """``x % period`` (Python's float remainder, as numpy's) for a positive period, without fmod one
    period either side: fmod is exact, so there the remainder is x itself, x + period rounded (x in
    (-period, 0)), or x - period (exact for x in [period, 2 period))."""
    if 0.0 < x < period:
        return x
    if -period < x < 0.0:
        return x + period
    if period <= x < 2.0 * period:
        return x - period
    return x % period


@numba.njit(cache=True, nogil=True)
def _turned_points(turn: np.ndarray, n: int, step: float, out: np.ndarray) -> None:
    """((a + turn[k]) % n) * step for every azimuth index a and turn k, as numpy rounds it."""
    nf = float(n)
    for k in range(turn.size):
        for a in range(n):
            out[k, a] = _wrapped(float(a) + turn[k], nf) * step


@numba.njit(cache=True, nogil=True)
def _interp_points(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, period: float, out: np.ndarray) -> None:
    """numpy's periodic interpolation of each ``x`` on ascending knots ``xp`` holding ``fp`` (a
    positive period), in its operations: ``x % period``, its slopes, its ends, the knot itself, and
    its NaN rules."""
    n = xp.size
    slopes = np.empty(n - 1)
    for i in range(n - 1):
        slopes[i] = (fp[i + 1] - fp[i]) / (xp[i + 1] - xp[i])
    j = 0
    for i in range(x.size):
        v = _wrapped(x[i], period)
        if math.isnan(v):
            out[i] = v
            continue
        if v < xp[0]:
            out[i] = fp[0]
            continue
        if v > xp[n - 1]:
            out[i] = fp[n - 1]
            continue
        # the last knot at or below v: the last point's or its next (the points mostly ascend), else searched
        if xp[j] <= v and (j == n - 1 or v < xp[j + 1]):
            pass
        elif j + 1 < n and xp[j + 1] <= v and (j + 1 == n - 1 or v < xp[j + 2]):
            j += 1
        else:
            lo, hi = 0, n - 1
            while hi - lo > 1:
                mid = (lo + hi) >> 1
                if xp[mid] <= v:
                    lo = mid
                else:
                    hi = mid
            j = hi if xp[hi] <= v else lo
        if j == n - 1 or xp[j] == v:
            out[i] = fp[j]
            continue
        slope = slopes[j]
        y = slope * (v - xp[j]) + fp[j]
        if math.isnan(y):
            y = slope * (v - xp[j + 1]) + fp[j + 1]
            if math.isnan(y) and fp[j] == fp[j + 1]:
                y = fp[j]
        out[i] = y


def jacobian(terrain: Terrain, dx_m: float, dy_m: float, row: float, col: float, grid_azimuth_deg: np.ndarray,
             elevation_deg: np.ndarray, distance_m: np.ndarray) -> np.ndarray:
    """d(elevation)/d(row, col, heading, eye height) per azimuth (deg per cell, deg per deg, deg per
    metre), from the parallax of each horizon point of the skyline rendered at (row, col)."""
    ge, gn = _gradient(terrain, row, col, dx_m, dy_m)
    az = np.asarray(grid_azimuth_deg, dtype=np.float64)
    out = np.empty((az.size, 4))
    _parallax_rows(az, np.asarray(elevation_deg, dtype=np.float64), np.asarray(distance_m, dtype=np.float64),
                   float(ge), float(gn), float(dx_m), float(dy_m), out)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _parallax_rows(az: np.ndarray, s: np.ndarray, dist: np.ndarray, ge: float, gn: float, dx_m: float, dy_m: float,
                   out: np.ndarray) -> None:
    """:func:`jacobian`'s rows, azimuth by azimuth: for range d, elevation e (0 where missing),
    ground gradient g and skyline slope s' (the central difference around the circle, 0 where it
    is not finite), the move's [sin e cos e (u . delta) - cos^2 e (g . delta) + s' (t . delta)] / d."""
    n = az.size
    step = 360.0 / n
    for i in range(n):
        ahead = s[i + 1] if i + 1 < n else s[0]
        behind = s[i - 1] if i > 0 else s[n - 1]
        slope = (ahead - behind) / (2.0 * step)
        if not math.isfinite(slope):
            slope = 0.0
        beta = az[i] * RAD
        e = (s[i] if math.isfinite(s[i]) else 0.0) * RAD
        cos_e = math.cos(e)
        se = math.sin(e) * cos_e
        ce2 = cos_e * cos_e
        ue = math.sin(beta)
        un = math.cos(beta)
        d = dist[i]
        out[i, 0] = -dy_m * (DEG * (se * un - ce2 * gn + slope * -ue) / d)
        out[i, 1] = dx_m * (DEG * (se * ue - ce2 * ge + slope * un) / d)
        out[i, 2] = slope
        out[i, 3] = -DEG * ce2 / d


def refine(
    terrain: Terrain,
    dx_m: float,
    dy_m: float,
    measured: np.ndarray,
    node_row: int,
    node_col: int,
    n_cols: int,
    heading_deg: float,
    height_m: float | None = None,
    start: tuple[float, float] | None = None,
    sigma_deg: float = 0.3,
    heading_bounds_deg: tuple[float, float] = (-180.0, 180.0),
    model: Model | None = None,
    position_prior: PositionPrior | None = None,
    max_offset_cells: float = MAX_OFFSET_CELLS,
    start_spread_cells: float = START_SPREAD_CELLS,
    tilt_sigma_deg: float = 0.0,
) -> Fit | None:
    """Fit (row, col, heading, eye height) to ``measured`` (deg on the azimuth grid j * 360 / n,
    NaN where missing; azimuths in the heading sensor's frame: true = j * step + heading) from a
    node.  The eye's height above the map's surface is ``height_m`` plus an offset with a
    Gaussian prior (``Model.eye_sigma_m``): the map's own height error under the camera.  ``model`` holds
    the measurement weights, the occlusion cap and the map's vertical error; the fit's ``ssd`` is
    its cost (:meth:`Model.cost`).  A ``position_prior`` (a traverse's transported belief) adds its
    Mahalanobis term to what the fit minimises, so the answer between nodes weighs the odometry as
    the grid's posterior does; ``ssd`` stays the measurements' own cost.  The fit stays within
    ``max_offset_cells`` of the node along each axis; ``start_spread_cells`` is the position's
    spread when the annealing starts (below).  With ``tilt_sigma_deg`` > 0 the head's residual tilt is
    fitted too: two more parameters, the elevation change t1 cos(a) + t2 sin(a) over the sensor's
    azimuth a (a pitch and a roll of the levelled head), each under a Gaussian prior of that sigma (deg)."""
    fitter = _Fitter(terrain, dx_m, dy_m, measured, node_row, node_col, n_cols, height_m, sigma_deg,
                     heading_bounds_deg, Model() if model is None else model, max_offset_cells, tilt_sigma_deg,
                     position_prior)
    r0, c0 = (float(node_row), float(node_col)) if start is None else start
    here = fitter.trial(fitter.clamp(np.array([r0, c0, float(heading_deg), 0.0] + [0.0] * fitter.n_tilt)))
    if not math.isfinite(here.cost):
        return None
    # Annealed weights: each azimuth counts by 1 / (sigma^2 + J var J^T), with var the spread of
    # the parameters still in doubt.  Far from the optimum the near ridges, whose skyline swings by
    # degrees within a cell, count for little and the far ones steer; as the fit closes in, the
    # spread shrinks and every azimuth counts fully.  Cauchy weights keep a ridge that jumped to
    # another one near the eye from pulling the fit.
    spread = np.array([start_spread_cells**2, start_spread_cells**2, (0.5 * fitter.step) ** 2, fitter.eye2]
                      + [tilt_sigma_deg**2] * fitter.n_tilt)
    lam = 1e-3
    iterations = 0
    while iterations < MAX_ITERATIONS:
        iterations += 1
        here, lam, improved = fitter.iterate(here, spread, lam)
        annealing = bool(spread[0] > 1e-4)
        spread *= ANNEAL
        # done when no step helps and either the spread is spent or the fit is down to the noise
        if not improved and (not annealing or here.cost <= (CONVERGED_NOISE * sigma_deg) ** 2 * fitter.n_valid):
            break
    return fitter.fit(here, iterations)


@dataclass(frozen=True)
class _Trial:
    """One trial of a fit: the parameters (row, col, heading, eye offset, tilts), their cost
    (:meth:`Model.cost`, rescaled to the measured count; inf when too little is rendered), the
    residuals (deg, 0 where not ``ok``), the rendered elevations (deg) and ranges (m)."""

    p: np.ndarray
    cost: float
    r: np.ndarray
    s: np.ndarray
    d: np.ndarray
    ok: np.ndarray


class _Fitter:
    """What one :func:`refine` holds fixed (its arguments, the azimuths, the schedule of the ray
    march, the priors' information ``P`` about ``mu``), and its steps: a trial rendered, one
    Levenberg-Marquardt iteration, and the fit made from the last trial."""

    def __init__(self, terrain: Terrain, dx_m: float, dy_m: float, measured: np.ndarray, node_row: int,
                 node_col: int, n_cols: int, height_m: float | None, sigma_deg: float,
                 heading_bounds_deg: tuple[float, float], model: Model, max_offset_cells: float,
                 tilt_sigma_deg: float, position_prior: PositionPrior | None) -> None:
        self.terrain, self.dx_m, self.dy_m, self.measured, self.mdl = terrain, dx_m, dy_m, measured, model
        self.node_row, self.node_col, self.max_offset_cells = node_row, node_col, max_offset_cells
        self.sigma_deg, self.sig2, self.heading_bounds_deg = sigma_deg, sigma_deg * sigma_deg, heading_bounds_deg
        n_az = measured.size
        self.step = 360.0 / n_az
        self.az = np.arange(n_az) * self.step
        self.valid = np.isfinite(measured)
        self.n_valid = int(self.valid.sum())
        # the azimuths a trial renders: the measured ones and their neighbours (the Jacobian's slope at
        # a measured azimuth reads the render either side of it); nothing reads the others, and each
        # azimuth's ray is marched on its own, so leaving them out changes no number
        needed = self.valid | np.roll(self.valid, 1) | np.roll(self.valid, -1)
        self.rendered = None if needed.all() else np.flatnonzero(needed)
        self.h_m = terrain.height_m if height_m is None else float(height_m)
        self.dist = terrain.distances(min(dx_m, dy_m))
        self.gamma = float(terrain.convergence_deg[node_row * n_cols + node_col])
        self.tilt_sigma_deg, self.tilted = tilt_sigma_deg, tilt_sigma_deg > 0.0
        self.tilt_basis = (np.stack([np.cos(np.radians(self.az)), np.sin(np.radians(self.az))], axis=1) if self.tilted
                           else np.zeros((n_az, 0)))
        self.n_tilt = self.tilt_basis.shape[1]
        self.eye2 = self.mdl.eye_sigma_m**2
        size = 4 + self.n_tilt
        self.P = np.zeros((size, size))
        self.P[3, 3] = 1.0 / self.eye2
        if self.tilted:
            self.P[4, 4] = self.P[5, 5] = 1.0 / tilt_sigma_deg**2
        self.mu = np.zeros(size)
        if position_prior is not None:
            self.P[:2, :2] = position_prior.information
            self.mu[:2] = position_prior.row, position_prior.col

    def trial(self, p: np.ndarray) -> _Trial:
        """The render at parameters ``p`` and its cost."""
        az = self.az + p[2] - self.gamma
        if self.rendered is None:
            s, d, _ = render(self.terrain, self.dx_m, self.dy_m, p[0], p[1], az, self.dist, self.h_m + p[3])
        else:  # NaN (no terrain) where nothing reads the render
            s = np.full(az.size, np.nan)
            d = np.full(az.size, np.nan)
            s[self.rendered], d[self.rendered], _ = render(self.terrain, self.dx_m, self.dy_m, p[0], p[1],
                                                           az[self.rendered], self.dist, self.h_m + p[3])
        ok = self.valid & np.isfinite(s) & np.isfinite(d)
        r = np.where(ok, self.measured - np.where(ok, s + self.tilt_basis @ p[4:], 0.0), 0.0)
        if ok.sum() < 0.9 * self.n_valid or not ok.any():
            return _Trial(p, math.inf, r, s, d, ok)
        u = self.mdl.weights(ok, np.where(ok, d, 1.0), self.sigma_deg)
        return _Trial(p, float(self.mdl.cost(r, u)) * self.n_valid / ok.sum(), r, s, d, ok)

    def clamp(self, q: np.ndarray) -> np.ndarray:
        """``q`` held within the offset allowed from the node and the heading's bounds (in place)."""
        q[0] = min(max(q[0], self.node_row - self.max_offset_cells), self.node_row + self.max_offset_cells)
        q[1] = min(max(q[1], self.node_col - self.max_offset_cells), self.node_col + self.max_offset_cells)
        q[2] = min(max(q[2], self.heading_bounds_deg[0]), self.heading_bounds_deg[1])
        return q

    def belief(self, q: np.ndarray) -> float:
        """The priors' term at ``q`` (the heading has none)."""
        dq = q - self.mu
        dq[2] = 0.0
        return float(dq @ self.P @ dq)

    def jacobian(self, t: _Trial, grid_azimuth_deg: np.ndarray, okd: np.ndarray) -> np.ndarray:
        """:func:`jacobian` at trial ``t`` with the tilts' columns, 0 where ``okd`` is not."""
        J = jacobian(self.terrain, self.dx_m, self.dy_m, t.p[0], t.p[1], grid_azimuth_deg, t.s,
                     np.where(okd, t.d, 1.0))
        return np.where(okd[:, None], np.hstack([J, self.tilt_basis]), 0.0)

    def iterate(self, t: _Trial, spread: np.ndarray, lam: float) -> tuple[_Trial, float, bool]:
        """One iteration from trial ``t`` with the parameters' ``spread`` and damping ``lam``: the
        trial it moves to (``t`` when no step helps), the damping after it, and whether it helped
        enough to go on."""
        okd = t.ok & np.isfinite(t.d)
        J_all = self.jacobian(t, self.az + t.p[2] - self.gamma, okd)
        u = self.mdl.weights(t.ok, np.where(okd, t.d, 1.0), self.sigma_deg)
        var = self.sig2 + (J_all * J_all) @ spread
        # Cauchy weights keep a ridge that jumped to another one near the eye from pulling the fit;
        # an occluded azimuth does not pull at all
        w_all = np.where(t.ok, u / (var * (1.0 + t.r * t.r / (ROBUST_SCALE**2 * var))), 0.0)
        w_all = np.where(self.mdl.hidden(t.r, u), 0.0, w_all)
        A = J_all.T @ (J_all * w_all[:, None]) + self.P
        dp = t.p - self.mu
        dp[2] = 0.0
        g = J_all.T @ (w_all * t.r) - self.P @ dp
        here = float(np.sum(w_all * t.r * t.r)) + self.belief(t.p)
        for _ in range(MAX_REJECTIONS):
            try:
                delta = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                break
            # the linear model's promised reduction: too small to be worth a render
            promised = float(2.0 * g @ delta - delta @ A @ delta)
            if promised < STOP_REDUCTION * here + 1e-12:
                break
            moved = self.trial(self.clamp(t.p + delta))
            there = float(np.sum(w_all * moved.r * moved.r)) + self.belief(moved.p)
            if math.isfinite(moved.cost) and there < here:
                return moved, max(lam / 4.0, 1e-6), here - there >= STOP_REDUCTION * there
            lam *= 8.0
        return t, lam, False

    def fit(self, t: _Trial, iterations: int) -> Fit:
        """The fit at trial ``t``: the eye's departure from the map's surface and the tilts paid for
        under their priors, the covariance from the curvature over the azimuths the terrain explains."""
        p, r, ok, sig2, n_valid = t.p, t.r, t.ok, self.sig2, self.n_valid
        u = self.mdl.weights(ok, np.where(ok, t.d, 1.0), self.sigma_deg)
        ssd_u, occ_u = self.mdl.split(r, u)
        k = n_valid / max(int(ok.sum()), 1)
        ssd, occ = float(ssd_u) * k, float(occ_u) * k
        okd = ok & np.isfinite(t.d)
        explained = okd & ~self.mdl.hidden(r, u)
        J = self.jacobian(t, self.az - self.gamma + p[2], okd)
        ue = np.where(explained, u, 0.0)
        H = J.T @ (J * ue[:, None])
        cov = _position_covariance(H, self.P, sig2, ssd, n_valid)
        tilt_cost = sig2 * float(np.sum(p[4:] ** 2)) / self.tilt_sigma_deg**2 if self.tilted else 0.0
        pulls, curvatures = _sectors(J, ue, np.where(explained, r, 0.0), explained, self.step)
        return Fit(float(p[0]), float(p[1]), float(p[2]), ssd + sig2 * p[3] ** 2 / self.eye2 + tilt_cost, n_valid,
                   iterations, float(p[3]), occ, cov, np.where(explained, r, np.nan), H, self.P.copy(),
                   (float(p[4]), float(p[5])) if self.tilted else (0.0, 0.0), pulls, curvatures)


def _sectors(J: np.ndarray, u: np.ndarray, r: np.ndarray, explained: np.ndarray,
             step_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """:attr:`Fit.sector_pulls` and :attr:`Fit.sector_curvatures`: the azimuth grid cut into SECTOR_DEG
    sectors, those without an explained azimuth left out."""
    starts = np.arange(0, J.shape[0], max(1, int(round(SECTOR_DEG / step_deg))))
    g = np.add.reduceat(J * (u * r)[:, None], starts, axis=0)
    h = np.add.reduceat(J[:, :, None] * (J * u[:, None])[:, None, :], starts, axis=0)
    held = np.add.reduceat(explained.astype(np.int64), starts) > 0
    return g[held], h[held]


def _position_covariance(H: np.ndarray, P: np.ndarray, sig2: float, ssd: float, n_valid: int) -> np.ndarray | None:
    """The (row, col) covariance (cells^2) of a fit: the inverse of the Gauss-Newton curvature ``H``
    (at unit sigma, over the measurements the terrain explains) at sigma^2 ``sig2`` plus the priors'
    information ``P``, heading and eye height marginalised.  Residuals above the noise widen it by
    the reduced chi-square, so a fit that explains the skyline poorly does not claim the precision
    of one that does."""
    inflation = max(1.0, ssd / max(n_valid * sig2, 1e-300))
    return marginal_position_covariance(H / (sig2 * inflation) + P)


def marginal_position_covariance(information: np.ndarray) -> np.ndarray | None:
    """The (row, col) block (cells^2) of the inverse of a fit's information matrix (row, col first);
    None when it is singular or not positive."""
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return None
    c = cov[:2, :2]
    if not (np.all(np.isfinite(c)) and c[0, 0] > 0 and c[1, 1] > 0 and np.linalg.det(c) > 0):
        return None
    return 0.5 * (c + c.T)
