"""The field procedures of a session (paper section 5.2): level, compass, ground truth, capture.

Each takes the platform's devices and the session's tolerances and returns a frozen result; the
numerical parts (:func:`level_guidance`, :func:`fit_hard_soft_iron`, :func:`average_fixes`,
:func:`capture_angles`) are pure functions tested on their own.
"""

from __future__ import annotations

import enum
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from appliance.acquisition.platform import (
    Camera,
    Clock,
    Compass,
    GpsSource,
    Leveller,
    Stage,
    Still,
    TiltSensor,
)
from appliance.config import SessionConfig
from appliance.drivers.gps import FixQuality, GpsFix
from appliance.errors import CalibrationError, DeviceError

GOOD_QUALITIES = frozenset({FixQuality.GPS, FixQuality.DGPS, FixQuality.PPS, FixQuality.RTK, FixQuality.FLOAT_RTK})
EARTH_RADIUS_M = 6_371_008.8


class Status(str, enum.Enum):
    OK = "ok"
    #: the estimate may be wrong: its region is large (the skyline does not single out a place)
    AMBIGUOUS = "ambiguous"
    DEGRADED = "degraded"
    FAILED = "failed"


# ------------------------------------------------------------------------------------------- level
@dataclass(frozen=True)
class LevelResult:
    status: Status
    roll_deg: float | None  # residual tilt, corrected later by the vision chain
    pitch_deg: float | None
    instructions: tuple[str, ...]
    reason: str = ""


def level_guidance(roll_deg: float, pitch_deg: float, tolerance_deg: float) -> str | None:
    """What the person at the tripod should do next, or None when level.

    The larger error first: roll positive (right side down) -> raise the right leg; pitch positive
    (nose up) -> lower the front leg.
    """
    if abs(roll_deg) <= tolerance_deg and abs(pitch_deg) <= tolerance_deg:
        return None
    if abs(roll_deg) >= abs(pitch_deg):
        side = "right" if roll_deg > 0 else "left"
        return f"raise the {side} leg (roll {roll_deg:+.2f} deg)"
    verb = "lower" if pitch_deg > 0 else "raise"
    return f"{verb} the front leg (pitch {pitch_deg:+.2f} deg)"


def level(
    tilt: TiltSensor,
    leveller: Leveller | None,
    clock: Clock,
    cfg: SessionConfig,
    on_reading: Callable[[object], None] = lambda r: None,
) -> LevelResult:
    """Read the inclinometers until level within tolerance, guiding the leveller; give up on timeout."""
    start = clock.monotonic_s()
    instructions: list[str] = []
    roll = pitch = None
    while True:
        reading = tilt.read_tilt()
        on_reading(reading)
        roll, pitch = reading.roll_deg, reading.pitch_deg
        advice = level_guidance(roll, pitch, cfg.level_tolerance_deg)
        if advice is None:
            return LevelResult(Status.OK, roll, pitch, tuple(instructions))
        if clock.monotonic_s() - start >= cfg.level_timeout_s:
            why = (
                f"not level after {cfg.level_timeout_s:.0f} s: roll {roll:+.2f} pitch {pitch:+.2f} deg "
                f"(tolerance {cfg.level_tolerance_deg} deg)"
            )
            return LevelResult(Status.DEGRADED, roll, pitch, tuple(instructions), why)
        instructions.append(advice)
        if leveller is not None:
            leveller.instruct(advice)
        clock.sleep(cfg.level_poll_s)


# ------------------------------------------------------------------------------------------ compass
@dataclass(frozen=True)
class IronFit:
    """Hard iron ``offset`` and soft iron ``matrix``: corrected = matrix @ (xy - offset), a circle."""

    offset: tuple[float, float]
    matrix: tuple[tuple[float, float], tuple[float, float]]
    radius: float
    residual: float  # RMS of (|corrected| - radius) / radius

    def heading_deg(self, x: float, y: float) -> float:
        """Magnetic heading (deg clockwise from magnetic north) of the head's forward axis."""
        cx, cy = np.asarray(self.matrix) @ (np.array([x, y]) - np.asarray(self.offset))
        return math.degrees(math.atan2(-cy, cx)) % 360.0


def fit_hard_soft_iron(x: np.ndarray, y: np.ndarray) -> IronFit:
    """Least-squares ellipse A x^2 + B xy + C y^2 + D x + E y = 1 turned into a centring and whitening."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 6:
        raise CalibrationError(f"compass fit: need at least 6 readings around the circle, got {x.size}")
    scale = float(np.max(np.hypot(x, y)))
    if not scale > 0:
        raise CalibrationError("compass fit: all readings are zero")
    xs, ys = x / scale, y / scale
    design = np.column_stack([xs * xs, xs * ys, ys * ys, xs, ys])
    coef, *_ = np.linalg.lstsq(design, np.ones_like(xs), rcond=None)
    a, b, c, d, e = coef
    m = np.array([[a, b / 2], [b / 2, c]])
    if np.linalg.det(m) <= 0 or a <= 0:
        raise CalibrationError("compass fit: readings do not lie on an ellipse (rotation incomplete?)")
    centre = -0.5 * np.linalg.solve(m, [d, e])
    k = 1.0 + centre @ m @ centre
    q = m / k
    w, v = np.linalg.eigh(q)
    sqrt_q = v @ np.diag(np.sqrt(w)) @ v.T
    radius = 1.0 / math.sqrt(math.sqrt(float(np.linalg.det(q))))
    soft = sqrt_q * radius
    pts = soft @ (np.vstack([xs, ys]) - centre[:, None])
    residual = float(np.sqrt(np.mean((np.hypot(pts[0], pts[1]) - radius) ** 2)) / radius)
    off = centre * scale
    return IronFit(
        (float(off[0]), float(off[1])),
        ((soft[0, 0], soft[0, 1]), (soft[1, 0], soft[1, 1])),
        radius * scale,
        residual,
    )


@dataclass(frozen=True)
class CompassResult:
    status: Status
    fit: IronFit | None
    platform_heading_deg: float | None  # magnetic heading of the head at stage angle 0
    readings: int
    reason: str = ""


def calibrate_compass(
    compass: Compass,
    stage: Stage,
    cfg: SessionConfig,
    on_reading: Callable[[object, float], None] = lambda r, s: None,
) -> CompassResult:
    """Rotate a full circle, fit hard and soft iron, reject a fit whose residual is too large."""
    xs, ys, stages = [], [], []
    for i in range(cfg.compass_steps):
        target = 360.0 * i / cfg.compass_steps
        reached = stage.move_to(target)
        reading = compass.read_field()
        on_reading(reading, reached)
        xs.append(reading.x)
        ys.append(reading.y)
        stages.append(reached)
    stage.move_to(0.0)
    try:
        fit = fit_hard_soft_iron(np.array(xs), np.array(ys))
    except CalibrationError as exc:
        return CompassResult(Status.FAILED, None, None, len(xs), str(exc))
    if fit.residual > cfg.compass_max_residual:
        why = (
            f"compass fit residual {fit.residual:.3f} exceeds {cfg.compass_max_residual} "
            "(metal nearby? keep ten metres from any sizable metal)"
        )
        return CompassResult(Status.FAILED, fit, None, len(xs), why)
    base = [(fit.heading_deg(x, y) - s) for x, y, s in zip(xs, ys, stages, strict=True)]
    heading = circular_mean_deg(np.array(base))
    return CompassResult(Status.OK, fit, heading, len(xs))


def circular_mean_deg(angles_deg: np.ndarray) -> float:
    r = np.radians(angles_deg)
    return float(math.degrees(math.atan2(np.mean(np.sin(r)), np.mean(np.cos(r)))) % 360.0)


# ------------------------------------------------------------------------------------- ground truth
@dataclass(frozen=True)
class TruthResult:
    status: Status
    lat_deg: float | None
    lon_deg: float | None
    alt_m: float | None
    sigma_m: float | None  # standard error of the mean position (horizontal, radial)
    spread_m: float | None  # standard deviation of the individual fixes (horizontal, radial)
    fix_type: str | None
    used: int
    rejected: int
    reason: str = ""


def average_fixes(fixes: Sequence[GpsFix], max_hdop: float, min_fixes: int) -> TruthResult:
    """Mean of the fixes that pass the quality gate (fix quality, HDOP); degraded below ``min_fixes``."""
    good = [f for f in fixes if f.quality in GOOD_QUALITIES and (f.hdop is None or f.hdop <= max_hdop)]
    rejected = len(fixes) - len(good)
    if len(good) < min_fixes:
        why = f"only {len(good)} of {len(fixes)} GPS fixes passed the quality gate (need {min_fixes})"
        return TruthResult(Status.DEGRADED, None, None, None, None, None, None, len(good), rejected, why)
    lat = np.array([f.lat_deg for f in good])
    lon = np.array([f.lon_deg for f in good])
    lat0, lon0 = float(lat.mean()), float(lon.mean())
    north = np.radians(lat - lat0) * EARTH_RADIUS_M
    east = np.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    spread = float(math.sqrt(np.var(north, ddof=1) + np.var(east, ddof=1))) if len(good) > 1 else 0.0
    alts = [f.alt_msl_m for f in good if f.alt_msl_m is not None]
    fix_type = Counter(f.quality.name for f in good).most_common(1)[0][0]
    return TruthResult(
        Status.OK,
        lat0,
        lon0,
        float(np.mean(alts)) if alts else None,
        spread / math.sqrt(len(good)),
        spread,
        fix_type,
        len(good),
        rejected,
    )


def ground_truth(
    gps: GpsSource, clock: Clock, cfg: SessionConfig, on_fix: Callable[[GpsFix], None] = lambda f: None
) -> TruthResult:
    """Collect fixes for ``truth_duration_s`` from now (what the receiver sent before is discarded) and
    average them with quality gating."""
    fixes: list[GpsFix] = []
    gps.discard_pending()
    start = clock.monotonic_s()
    while clock.monotonic_s() - start < cfg.truth_duration_s:
        for fix in gps.poll():
            on_fix(fix)
            fixes.append(fix)
        clock.sleep(0.2)
    return average_fixes(fixes, cfg.truth_max_hdop, cfg.truth_min_fixes)


# ------------------------------------------------------------------------------------------ capture
def capture_angles(hfov_deg: float, overlap: float) -> np.ndarray:
    """Stage angles (deg) covering the full circle with neighbours sharing ``overlap`` of the view."""
    if not 0 <= overlap < 1:
        raise CalibrationError(f"capture overlap must be in [0, 1), got {overlap}")
    n = max(1, math.ceil(360.0 / (hfov_deg * (1.0 - overlap)) - 1e-9))
    return np.arange(n) * (360.0 / n)


@dataclass(frozen=True)
class TaggedFrame:
    index: int
    frame: Still
    stage_deg: float
    heading_deg: float | None  # true heading of the optical axis (platform heading + stage)
    roll_deg: float | None
    pitch_deg: float | None


@dataclass(frozen=True)
class CaptureProblem:
    index: int
    stage_deg: float
    reason: str


def is_black(image: np.ndarray, max_mean: float) -> bool:
    return float(np.mean(image)) < max_mean


#: A frame with more than this share of its pixels at full scale in every channel is over-exposed.
MAX_SATURATED_SHARE = 0.9
#: A frame whose grey levels vary less than this (standard deviation) shows nothing: no sky, no ground.
MIN_FRAME_STD = 1.0


def frame_problem(image: np.ndarray, black_max_mean: float) -> str | None:
    """Why a frame holds no skyline to find (black, over-exposed, featureless), or None."""
    if is_black(image, black_max_mean):
        return f"black frame (mean {np.mean(image):.1f})"
    saturated = float(np.mean(np.all(image >= 250, axis=-1))) if image.ndim == 3 else float(np.mean(image >= 250))
    if saturated > MAX_SATURATED_SHARE:
        return f"over-exposed frame ({saturated:.0%} of pixels saturated)"
    std = float(np.std(image))
    if std < MIN_FRAME_STD:
        return f"featureless frame (grey level std {std:.2f})"
    return None


def capture_ring(
    stage: Stage,
    camera: Camera,
    tilt: TiltSensor | None,
    clock: Clock,
    cfg: SessionConfig,
    platform_heading_deg: float | None,
    on_frame: Callable[[TaggedFrame], None],
    on_problem: Callable[[CaptureProblem], None],
) -> tuple[list[TaggedFrame], list[CaptureProblem]]:
    """Rotate in steps, settle, capture and tag; a stalled step or a frame that is black, over-exposed or
    featureless twice is skipped (and reported), not fatal.

    A device that disappears (unplugged camera) raises :class:`DeviceError` to the session, which
    keeps the frames already written.
    """
    frames: list[TaggedFrame] = []
    problems: list[CaptureProblem] = []
    for i, target in enumerate(capture_angles(camera.intrinsics.hfov_deg, cfg.capture_overlap)):
        reached = stage.move_to(float(target))
        error = abs((reached - target + 180.0) % 360.0 - 180.0)
        if error > cfg.stage_tolerance_deg:
            p = CaptureProblem(i, float(target), f"stage stalled at {reached:.1f} deg (commanded {target:.1f})")
            problems.append(p)
            on_problem(p)
            continue
        clock.sleep(cfg.settle_s)
        frame = camera.capture()
        if frame_problem(frame.image, cfg.black_frame_max_mean) is not None:
            frame = camera.capture()
            why = frame_problem(frame.image, cfg.black_frame_max_mean)
            if why is not None:
                p = CaptureProblem(i, float(target), f"{why} twice")
                problems.append(p)
                on_problem(p)
                continue
        roll = pitch = None
        if tilt is not None:
            try:
                t = tilt.read_tilt()
                roll, pitch = t.roll_deg, t.pitch_deg
            except DeviceError as exc:
                on_problem(CaptureProblem(i, float(target), f"tilt unavailable: {exc}"))
        heading = None if platform_heading_deg is None else (platform_heading_deg + reached) % 360.0
        tagged = TaggedFrame(i, frame, reached, heading, roll, pitch)
        frames.append(tagged)
        on_frame(tagged)
    return frames, problems
