"""Stitching the images taken while the stage rotates into one cylindrical panorama.

1. Every image is warped onto a vertical cylinder of focal length ``fy`` through the full camera
   model (distortion, the camera's pitch and roll), so a rotation about the vertical becomes a pure
   horizontal shift and residual tilt is corrected, not assumed away.
   The remap maps depend only on the camera model and the (pitch, roll) of a shot: they are
   computed once per distinct (pitch, roll) and reused for every such image, both to register and
   to blend (a sub-column shift of a strip interpolates the maps, not the pixels).
2. Neighbours (sorted by stage angle) are registered: a coarse shift by phase correlation
   (Kuglin-Hines, ``cv2.phaseCorrelate``) on their nominal overlap, then Levenberg-Marquardt
   (``scipy.optimize.least_squares(method="lm")``) on the photometric residual over the overlap
   refines the rotation between them (and a vertical shift, a gain and an offset).  The residual
   is sampled every ``LM_STRIDE_PX`` rows and columns, with an analytic Jacobian (the warped image
   derivatives), from the same single remap as the residual.
3. Around a full circle the measured rotations must add up to 360 degrees; the misclosure is
   spread evenly over all seams instead of piling up on the last one.
4. The images are blended with feathered weights (falling to zero at each image's side edges).

Absolute azimuth: the panorama keeps the mean of (refined yaw - stage angle) at zero, plus
``heading_offset_deg`` (the azimuth of stage angle zero, from the compass).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from appliance.errors import InputError
from appliance.vision.camera import CameraPose, directions_to_pixels
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection, full_circle_width

MIN_PEAK_RESPONSE = 0.03  # phase-correlation peak below which two images are taken not to overlap
MIN_OVERLAP_PX = 16
MIN_CORRELATION = 0.5  # normalised correlation of a registered overlap below which images do not match
LM_STRIDE_PX = 2  # the refinement samples the overlap every LM_STRIDE_PX rows and columns


@dataclass(frozen=True)
class Shot:
    """One image and the pose it was taken at (degrees; yaw is the stage angle)."""

    image: np.ndarray
    stage_angle_deg: float
    pitch_deg: float = 0.0
    roll_deg: float = 0.0


@dataclass(frozen=True)
class StitchResult:
    panorama: Panorama
    #: refined azimuth of every shot's optical axis, in input order (degrees)
    yaw_deg: np.ndarray
    #: rotation between each shot and the next (sorted by stage angle), after loop closure (degrees)
    seam_rotation_deg: np.ndarray
    #: misclosure of the 360-degree loop before it was spread (degrees; NaN for a partial panorama)
    misclosure_deg: float


@dataclass
class _Strip:
    image: np.ndarray  # HxWsx3 float32
    weight: np.ndarray  # HxWs float32, 0 outside the photo
    gray: np.ndarray  # HxWs float32


def _strip_geometry(k: CameraIntrinsics, f: float) -> tuple[int, int, float]:
    """(strip width, panorama height, horizon row) for a camera of intrinsics ``k``."""
    half_w = math.atan2(max(k.cx, k.width - 1 - k.cx) + 1.0, k.fx)
    ws = 2 * int(math.ceil(f * half_w)) + 3
    top = math.atan2(k.cy, k.fy)
    bot = math.atan2(k.height - 1 - k.cy, k.fy)
    horizon = math.floor(f * math.tan(top))
    height = int(horizon + math.floor(f * math.tan(bot))) + 1
    return ws, height, float(horizon)


class _WarpMaps:
    """Remap maps from strip pixels to photo pixels, computed once per (pitch, roll).

    The camera model is evaluated on a grid one column wider than the strip, starting one column
    to the left; a strip shifted by a fraction ``frac`` in [0, 1) of a column takes its maps by
    linear interpolation between neighbouring grid columns.  The maps are smooth (a fraction of a
    pixel per column of curvature), so the interpolation error is far below 1e-3 px, and every
    strip, whether for registration or for blending, samples the photo exactly once.
    """

    def __init__(self, k: CameraIntrinsics, f: float, ws: int, h: int, horizon: float) -> None:
        self._k, self._f, self._ws, self._h, self._horizon = k, f, ws, h, horizon
        self._grids: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    def _grid(self, pitch_deg: float, roll_deg: float) -> tuple[np.ndarray, np.ndarray]:
        key = (float(pitch_deg), float(roll_deg))
        if key not in self._grids:
            x = np.arange(self._ws + 1, dtype=np.float64) - (self._ws - 1) / 2.0 - 1.0
            y = np.arange(self._h, dtype=np.float64)
            az = np.degrees(x / self._f)
            el = np.degrees(np.arctan((self._horizon - y) / self._f))
            azg, elg = np.meshgrid(az, el)
            u, v = directions_to_pixels(self._k, CameraPose(0.0, pitch_deg, roll_deg), azg, elg)
            self._grids[key] = (u, v)
        return self._grids[key]

    def maps(self, pitch_deg: float, roll_deg: float, frac: float) -> tuple[np.ndarray, np.ndarray]:
        """Photo pixel (u, v) of every strip pixel (NaN behind the camera), strip shifted by ``frac``."""
        u, v = self._grid(pitch_deg, roll_deg)
        if frac == 0.0:
            return u[:, 1:], v[:, 1:]
        # strip column j sits at grid abscissa x_(j+1) - frac, between grid columns j and j + 1
        a, b = np.float64(frac), np.float64(1.0 - frac)
        return a * u[:, :-1] + b * u[:, 1:], a * v[:, :-1] + b * v[:, 1:]


def _warp(shot: Shot, k: CameraIntrinsics, maps: _WarpMaps, frac: float) -> _Strip:
    """Warp ``shot`` onto strip columns centred on its optical axis, shifted by ``frac`` columns."""
    u, v = maps.maps(shot.pitch_deg, shot.roll_deg, frac)
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(u) & (u >= 0) & (u <= k.width - 1) & (v >= 0) & (v <= k.height - 1)
    mx = np.where(inside, u, -10).astype(np.float32)
    my = np.where(inside, v, -10).astype(np.float32)
    img = cv2.remap(shot.image.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    # feather: weight falls linearly to zero towards the photo's side edges
    edge = np.minimum(u, k.width - 1 - u) / (k.width / 2.0)
    weight = np.where(inside, np.clip(edge, 0.0, 1.0), 0.0).astype(np.float32)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return _Strip(img, weight, gray)


def _overlap(a: _Strip, b: _Strip, shift_px: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The part of strip ``a`` and of strip ``b`` that overlap when ``b`` sits ``shift_px`` to the right."""
    s = int(round(shift_px))
    ws = a.gray.shape[1]
    width = ws - s
    if width < MIN_OVERLAP_PX:
        return np.empty((0, 0), np.float32), np.empty((0, 0), np.float32), s
    ga = a.gray[:, s:]
    gb = b.gray[:, :width]
    valid = (a.weight[:, s:] > 0) & (b.weight[:, :width] > 0)
    cols = np.flatnonzero(valid.mean(axis=0) > 0.75)
    rows = np.flatnonzero(valid[:, cols].all(axis=1)) if cols.size else np.empty(0, int)
    if rows.size < MIN_OVERLAP_PX or cols.size < MIN_OVERLAP_PX:
        return np.empty((0, 0), np.float32), np.empty((0, 0), np.float32), s
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    if not valid[r0:r1, c0:c1].all():
        return np.empty((0, 0), np.float32), np.empty((0, 0), np.float32), s
    return ga[r0:r1, c0:c1], gb[r0:r1, c0:c1], s


def _register(a: _Strip, b: _Strip, nominal_px: float, names: tuple[str, str]) -> float:
    """Horizontal shift (px) of ``b`` relative to ``a``: phase correlation, then Levenberg-Marquardt."""
    pa, pb, s = _overlap(a, b, nominal_px)
    if pa.size == 0:
        raise InputError(f"{names[0]} and {names[1]}: the images do not overlap at their stage angles")
    win = cv2.createHanningWindow((pa.shape[1], pa.shape[0]), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(np.ascontiguousarray(pb), np.ascontiguousarray(pa), win)
    if response < MIN_PEAK_RESPONSE or abs(dx) > pa.shape[1] / 3:
        raise InputError(
            f"{names[0]} and {names[1]}: no common features in their overlap"
            f" (phase-correlation peak {response:.3f}, shift {dx:.1f} px)"
        )
    # refine: pa(x) ~ gain * pb(x + d) + offset over the overlap's interior
    margin = int(math.ceil(abs(dx))) + 3
    h, w = pa.shape
    if w - 2 * margin < MIN_OVERLAP_PX:
        return s + dx
    ys, xs = np.mgrid[0:h:LM_STRIDE_PX, margin : w - margin : LM_STRIDE_PX].astype(np.float32)
    target = pa[::LM_STRIDE_PX, margin : w - margin : LM_STRIDE_PX].ravel()
    # pb with its horizontal and vertical derivatives (central differences), warped in one remap:
    # the residual and its analytic Jacobian come from the same samples
    stack = cv2.merge(
        [
            pb,
            cv2.Sobel(pb, cv2.CV_32F, 1, 0, ksize=1, scale=0.5),
            cv2.Sobel(pb, cv2.CV_32F, 0, 1, ksize=1, scale=0.5),
        ]
    )
    cache: dict[tuple[float, float], np.ndarray] = {}

    def sampled(p: np.ndarray) -> np.ndarray:
        key = (float(p[0]), float(p[1]))
        if key not in cache:
            cache.clear()
            cache[key] = cv2.remap(stack, xs + np.float32(p[0]), ys + np.float32(p[1]), cv2.INTER_LINEAR).reshape(-1, 3)
        return cache[key]

    def residual(p: np.ndarray) -> np.ndarray:
        return np.asarray(p[2] * sampled(p)[:, 0] + p[3] - target, dtype=np.float64)

    def jacobian(p: np.ndarray) -> np.ndarray:
        smp = sampled(p)
        jac = np.empty((smp.shape[0], 4), dtype=np.float64)
        jac[:, 0] = p[2] * smp[:, 1]
        jac[:, 1] = p[2] * smp[:, 2]
        jac[:, 2] = smp[:, 0]
        jac[:, 3] = 1.0
        return jac

    fit = least_squares(residual, x0=np.array([-dx, -dy, 1.0, 0.0]), jac=jacobian, method="lm")
    p = fit.x if fit.success and abs(fit.x[0] + dx) <= 2.0 else np.array([-dx, -dy, 1.0, 0.0])
    warped = cv2.remap(pb, xs + np.float32(p[0]), ys + np.float32(p[1]), cv2.INTER_LINEAR).ravel()
    ncc = float(np.corrcoef(warped, target)[0, 1])
    if not ncc >= MIN_CORRELATION:
        raise InputError(
            f"{names[0]} and {names[1]}: their overlap does not match (correlation {ncc:.2f} after registration)"
        )
    return float(s - p[0])


def stitch(
    shots: list[Shot],
    intrinsics: CameraIntrinsics,
    heading_offset_deg: float = 0.0,
    names: list[str] | None = None,
) -> StitchResult:
    """Stitch ``shots`` into a cylindrical panorama (full circle if they cover it)."""
    if not shots:
        raise InputError("stitch: no images")
    names = names or [f"image {i}" for i in range(len(shots))]
    for shot, name in zip(shots, names):
        if shot.image.shape[:2] != (intrinsics.height, intrinsics.width):
            raise InputError(
                f"{name}: image is {shot.image.shape[1]}x{shot.image.shape[0]},"
                f" the calibration is for {intrinsics.width}x{intrinsics.height}"
            )
    f_nominal = intrinsics.fy
    width_full = full_circle_width(f_nominal)
    f = width_full / (2 * math.pi)  # the columns span exactly 360 degrees
    ws, height, horizon = _strip_geometry(intrinsics, f)
    order = np.argsort([np.mod(s.stage_angle_deg, 360.0) for s in shots], kind="stable")
    stage = np.array([np.mod(shots[i].stage_angle_deg, 360.0) for i in order])
    n = len(shots)
    maps = _WarpMaps(intrinsics, f, ws, height, horizon)
    strips = [_warp(shots[i], intrinsics, maps, 0.0) for i in order]

    # nominal gaps (deg) between neighbours; a full circle closes from the last back to the first
    gaps = np.diff(stage)
    hfov = 2 * math.degrees((ws - 3) / 2 / f)
    closing = 360.0 - (stage[-1] - stage[0]) if n > 1 else 360.0
    full = n > 1 and bool(np.all(gaps < hfov * 0.95)) and closing < hfov * 0.95
    if n > 1 and not np.all(gaps < hfov * 0.95):
        k = int(np.argmax(gaps))
        raise InputError(
            f"{names[order[k]]} and {names[order[k + 1]]}: stage angles {stage[k]:.1f} and {stage[k + 1]:.1f} deg"
            f" are too far apart for a {hfov:.1f} deg field of view (the images do not overlap)"
        )
    pairs = [(i, i + 1, gaps[i]) for i in range(n - 1)]
    if full:
        pairs.append((n - 1, 0, closing))
    measured = np.empty(len(pairs))
    for k, (i, j, gap) in enumerate(pairs):
        shift = _register(strips[i], strips[j], math.radians(gap) * f, (names[order[i]], names[order[j]]))
        measured[k] = math.degrees(shift / f)
    misclosure = float("nan")
    if full:
        misclosure = float(measured.sum() - 360.0)
        measured = measured - misclosure / len(measured)
    yaw_sorted = stage[0] + np.concatenate([[0.0], np.cumsum(measured[: n - 1])])
    yaw_sorted += float(np.mean(stage - yaw_sorted))  # keep the stage angles' mean
    yaw_sorted += heading_offset_deg

    pano = _blend(shots, order, yaw_sorted, intrinsics, maps, f, ws, height, horizon, full)
    yaw = np.empty(n)
    yaw[order] = np.mod(yaw_sorted, 360.0)
    return StitchResult(pano, yaw, measured, misclosure)


def _blend(
    shots: list[Shot],
    order: np.ndarray,
    yaw_sorted: np.ndarray,
    k: CameraIntrinsics,
    maps: _WarpMaps,
    f: float,
    ws: int,
    height: int,
    horizon: float,
    full: bool,
) -> Panorama:
    width_full = full_circle_width(f)
    centres = np.radians(yaw_sorted) * f  # panorama column of each optical axis (azimuth 0 = column 0)
    if full:
        width, origin = width_full, 0.0
    else:
        origin = math.floor(centres[0] - (ws - 1) / 2.0)
        width = min(width_full, int(math.ceil(centres[-1] + (ws - 1) / 2.0 - origin)) + 1)
    acc = np.zeros((height, width, 3), np.float32)
    wsum = np.zeros((height, width), np.float32)
    for idx, c in zip(order, centres):
        start = c - (ws - 1) / 2.0 - origin
        first = int(math.floor(start))
        strip = _warp(shots[idx], k, maps, start - first)
        weighted = strip.image * strip.weight[..., None]
        # the strip's columns as at most two contiguous runs of panorama columns (two where a full
        # circle wraps); a strip is narrower than the panorama, so the runs do not overlap
        for lo, hi, j in _column_runs(first, ws, width, full):
            acc[:, lo:hi] += weighted[:, j : j + hi - lo]
            wsum[:, lo:hi] += strip.weight[:, j : j + hi - lo]
    covered = wsum > 1e-6
    out = acc / np.maximum(wsum, np.float32(1e-6))[..., None]
    out[~covered] = 0.0
    image = np.clip(out + np.float32(0.5), 0, 255).astype(np.uint8)
    azimuth0 = float(np.mod(math.degrees(origin / f), 360.0))
    return Panorama(image, Projection.CYLINDRICAL, f, azimuth0, horizon, full)


def _column_runs(first: int, ws: int, width: int, full: bool) -> list[tuple[int, int, int]]:
    """Runs ``(lo, hi, j)``: panorama columns [lo, hi) take strip columns from ``j`` on.

    The strip's columns are panorama columns ``first .. first + ws - 1``; on a full circle they
    wrap modulo ``width`` (two runs at the seam), otherwise columns outside the panorama are dropped.
    """
    if full:
        a = first % width
        if a + ws <= width:
            return [(a, a + ws, 0)]
        return [(a, width, 0), (0, a + ws - width, width - a)]
    lo, hi = max(first, 0), min(first + ws, width)
    return [(lo, hi, lo - first)] if hi > lo else []
