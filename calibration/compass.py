"""Compass calibration: hard and soft iron, heading error before and after, mounting offset.

A magnetometer reading is ``raw = S (h + ...) + b``: a hard-iron offset ``b`` and a soft-iron/scale
distortion that turns the sphere of constant field magnitude into an ellipsoid.  The correction
``h = W (raw - b)`` (:class:`appliance.drivers.magnetometer.HardSoftIron`, the drivers' type) maps
the fitted ellipsoid back onto a sphere whose radius is the geometric mean of the ellipsoid's
semi-axes, so the corrected readings keep the sensor's units.

Units: the fit works in the log's units (gauss: the ``mag_*_gauss`` columns), so
``CompassCalibration.iron`` and the printed report are in gauss.  The file it writes is SI: the
``[compass]`` table of the calibration TOML holds ``hard_iron_offset`` in tesla and the
dimensionless ``soft_iron_matrix`` (row-major), the keys and units of the ``[devices.compass]``
configuration, which is what the magnetometer driver applies to its readings in tesla
(``CompassCalibration.iron_tesla``; see :mod:`appliance.drivers.magnetometer`).

* ``mode="sphere"``: the platform was turned through (nearly) all orientations; a general quadric
  is fitted by least squares and must be an ellipsoid.
* ``mode="level"``: a levelled stage turned the platform about the vertical; an ellipse is fitted
  to the horizontal components (x, y).  The vertical axis is not observable this way: its offset
  is 0 and its scale 1.

Body frame: right-handed, x forward, z up unless a measured down direction is given (the raw
HMC5883L set-2 data: x forward, y left, z up).  Heading: magnetic azimuth of the x axis, degrees
clockwise from magnetic north, in [0, 360).  True heading = magnetic heading + declination (east
positive) - mounting offset.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from viper_calibration.config_edit import significant, update_toml_table

from appliance.drivers.magnetometer import (
    CALIBRATION_TABLE,
    GAUSS_TO_TESLA,
    MOUNTING_KEY,
    HardSoftIron,
)
from appliance.errors import CalibrationError, InputError

MAG_COLUMNS = ("mag_x_gauss", "mag_y_gauss", "mag_z_gauss")
ACC_COLUMNS = ("acc_x_g", "acc_y_g", "acc_z_g")
TIME_COLUMN = "t_s"
REFERENCE_COLUMN = "reference_heading_deg"
MIN_SAMPLES = 20
MIN_AXIS_SPREAD_RATIO = 0.05  # sphere mode: smallest / largest principal spread of the readings
MAX_HEADING_GAP_DEG = 60.0  # level mode: the turn may leave no gap wider than this
LEVEL_DOWN = (0.0, 0.0, -1.0)  # down in a z-up body frame
LEGACY_KEYS = ("offset", "matrix")  # the table's keys before it held SI units (gauss offset)
MAX_ACCEL_EXTRAPOLATION_S = 0.5  # the accelerometer log may start/end this much inside the magnetometer's


@dataclass(frozen=True)
class MagnetometerLog:
    """A logged rotation: sample times (s), raw field (N, 3) gauss, optional reference headings.

    ``reference_heading_deg`` holds the true heading of the x axis where one is known (a stage
    encoder, a sighted landmark) and NaN where it is not; it is None when the log has no such column.
    """

    t_s: np.ndarray
    field_gauss: np.ndarray
    reference_heading_deg: np.ndarray | None = None


@dataclass(frozen=True)
class CompassCalibration:
    """The fitted correction and the figures that show what it did."""

    mode: str
    iron: HardSoftIron  # in the log's units (gauss)
    n: int
    field_gauss: float
    magnitude_spread_before: float  # std / mean of |B| (sphere) or of |B_xy| (level), raw
    magnitude_spread_after: float  # the same, corrected
    heading_correction_max_deg: float  # max |raw heading - corrected heading|
    heading_error_rms_before_deg: float | None  # against reference headings, when the log has them
    heading_error_rms_after_deg: float | None
    mounting_offset_deg: float | None  # corrected heading + declination - known bearing
    declination_deg: float

    @property
    def iron_tesla(self) -> HardSoftIron:
        """The correction for readings in tesla (what the driver reads and the file holds)."""
        return self.iron.scaled(GAUSS_TO_TESLA)

    def as_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "n": self.n,
            "offset": list(self.iron.offset),
            "matrix": list(self.iron.matrix),
            "field_gauss": self.field_gauss,
            "magnitude_spread_before": self.magnitude_spread_before,
            "magnitude_spread_after": self.magnitude_spread_after,
            "heading_correction_max_deg": self.heading_correction_max_deg,
            "heading_error_rms_before_deg": self.heading_error_rms_before_deg,
            "heading_error_rms_after_deg": self.heading_error_rms_after_deg,
            "mounting_offset_deg": self.mounting_offset_deg,
            "declination_deg": self.declination_deg,
        }


# --------------------------------------------------------------------------- reading logs


def _read_table(path: str | Path) -> tuple[list[str], list[list[str]], str]:
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{p}: file not found") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not UTF-8 text: {exc}") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc.strerror or exc}") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{p}: empty file")
    return [c.strip() for c in rows[0]], rows[1:], str(p)


def _column(header: list[str], rows: list[list[str]], name: str, source: str, *, empty_ok: bool = False):
    index = header.index(name)
    values = np.empty(len(rows))
    for line_no, row in enumerate(rows, start=2):
        if len(row) != len(header):
            raise InputError(f"{source}:{line_no}: expected {len(header)} fields, got {len(row)}")
        cell = row[index].strip()
        if cell == "" and empty_ok:
            values[line_no - 2] = math.nan
            continue
        try:
            value = float(cell)
        except ValueError:
            raise InputError(f"{source}:{line_no}: {name} {cell!r} is not a number") from None
        if not math.isfinite(value):
            raise InputError(f"{source}:{line_no}: {name} is {cell}")
        values[line_no - 2] = value
    return values


def read_magnetometer_csv(path: str | Path) -> MagnetometerLog:
    """Read ``t_s`` (optional), ``mag_x_gauss,mag_y_gauss,mag_z_gauss`` and ``reference_heading_deg``."""
    header, rows, source = _read_table(path)
    missing = [c for c in MAG_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{source}: no column {missing[0]} (header: {','.join(header)})")
    field = (
        np.column_stack([_column(header, rows, c, source) for c in MAG_COLUMNS]) if rows else np.empty((0, 3))
    )
    t = (
        _column(header, rows, TIME_COLUMN, source)
        if TIME_COLUMN in header
        else np.arange(len(rows), dtype=float)
    )
    ref = (
        _column(header, rows, REFERENCE_COLUMN, source, empty_ok=True) if REFERENCE_COLUMN in header else None
    )
    return MagnetometerLog(t, field, ref)


def read_down_csv(path: str | Path, t_s: np.ndarray, *, measures: str = "up") -> np.ndarray:
    """Unit down vectors (N, 3) at ``t_s`` from an accelerometer log (t_s, acc_x_g, acc_y_g, acc_z_g).

    ``measures="up"``: a usual accelerometer reading +1 g upwards at rest; ``"down"``: one whose
    reading points down (the set-2 MPU6050 reads z = -1 g when level, z up).
    """
    if measures not in ("up", "down"):
        raise InputError(f"accelerometer sense must be 'up' or 'down', got {measures!r}")
    header, rows, source = _read_table(path)
    for c in (TIME_COLUMN, *ACC_COLUMNS):
        if c not in header:
            raise InputError(f"{source}: no column {c} (header: {','.join(header)})")
    t_acc = _column(header, rows, TIME_COLUMN, source)
    if len(t_acc) < 2 or np.any(np.diff(t_acc) <= 0):
        raise InputError(f"{source}: {TIME_COLUMN} must increase strictly over at least two rows")
    if t_s[0] < t_acc[0] - MAX_ACCEL_EXTRAPOLATION_S or t_s[-1] > t_acc[-1] + MAX_ACCEL_EXTRAPOLATION_S:
        raise InputError(
            f"{source}: covers {t_acc[0]:.3f}..{t_acc[-1]:.3f} s,"
            f" the magnetometer {t_s[0]:.3f}..{t_s[-1]:.3f} s"
        )
    acc = np.column_stack([np.interp(t_s, t_acc, _column(header, rows, c, source)) for c in ACC_COLUMNS])
    norm = np.linalg.norm(acc, axis=1)
    if np.any(norm < 0.5):
        raise InputError(f"{source}: acceleration below 0.5 g at {int(np.sum(norm < 0.5))} sample(s)")
    down = acc / norm[:, None]
    return -down if measures == "up" else down


# --------------------------------------------------------------------------- fits


def _check_samples(xyz: np.ndarray, columns: tuple[str, ...]) -> None:
    if xyz.ndim != 2 or xyz.shape[1] < len(columns):
        raise InputError(f"expected an (N, {len(columns)}) array of readings, got shape {xyz.shape}")
    if len(xyz) < MIN_SAMPLES:
        raise CalibrationError(f"{len(xyz)} magnetometer sample(s); the fit needs at least {MIN_SAMPLES}")
    if not np.all(np.isfinite(xyz)):
        raise InputError("magnetometer readings contain NaN or infinite values")
    for name, column in zip(columns, xyz.T, strict=False):
        if np.ptp(column) == 0.0:
            raise CalibrationError(f"{name} is constant ({column[0]}) over all {len(xyz)} samples")


def _sqrtm_spd(M: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(M)
    return (V * np.sqrt(w)) @ V.T


def fit_ellipsoid(xyz: np.ndarray) -> tuple[HardSoftIron, float]:
    """Hard and soft iron from a full-sphere rotation: (correction, corrected field magnitude, gauss)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    _check_samples(xyz, MAG_COLUMNS)
    spread = np.sqrt(np.linalg.eigvalsh(np.cov(xyz.T)))
    if spread[0] < MIN_AXIS_SPREAD_RATIO * spread[-1]:
        raise CalibrationError(
            f"the readings span a plane (principal spreads {spread[0]:.4g}..{spread[-1]:.4g} gauss);"
            " turn through all orientations, or use the level mode for a stage rotation"
        )
    mu = xyz.mean(axis=0)
    scale = float(xyz.std())
    x, y, z = ((xyz - mu) / scale).T
    design = np.column_stack(
        [x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones_like(x)]
    )
    v = np.linalg.svd(design, full_matrices=False)[2][-1]
    A = np.array([[v[0], v[5], v[4]], [v[5], v[1], v[3]], [v[4], v[3], v[2]]])
    b = v[6:9]
    try:
        centre = -np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        raise CalibrationError("the readings do not lie on an ellipsoid (singular quadric)") from None
    M = A / (centre @ A @ centre - v[9])
    eig = np.linalg.eigvalsh(M)
    if not np.all(eig > 0):
        raise CalibrationError(f"the fitted quadric is not an ellipsoid (eigenvalues {np.round(eig, 4)})")
    radius = float(np.prod(eig) ** (-1.0 / 6.0))  # geometric mean of the semi-axes (normalised units)
    W = _sqrtm_spd(M) * radius
    offset = centre * scale + mu
    return _iron(offset, W), radius * scale


def fit_level_ellipse(xyz: np.ndarray) -> tuple[HardSoftIron, float]:
    """Hard and soft iron in the horizontal plane from a levelled turn: (correction, |B_h| gauss)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    _check_samples(xyz[:, :2], MAG_COLUMNS[:2])
    mu = xyz[:, :2].mean(axis=0)
    scale = float(xyz[:, :2].std())
    x, y = ((xyz[:, :2] - mu) / scale).T
    design = np.column_stack([x * x, 2 * x * y, y * y, 2 * x, 2 * y, np.ones_like(x)])
    v = np.linalg.svd(design, full_matrices=False)[2][-1]
    A = np.array([[v[0], v[1]], [v[1], v[2]]])
    if np.linalg.det(A) <= 0:
        raise CalibrationError(
            "the horizontal readings do not lie on an ellipse; turn the stage a full circle"
        )
    centre = -np.linalg.solve(A, v[3:5])
    M = A / (centre @ A @ centre - v[5])
    eig = np.linalg.eigvalsh(M)
    if not np.all(eig > 0):
        raise CalibrationError(f"the fitted conic is not an ellipse (eigenvalues {np.round(eig, 4)})")
    radius = float(np.prod(eig) ** (-1.0 / 4.0))
    W2 = _sqrtm_spd(M) * radius
    W = np.eye(3)
    W[:2, :2] = W2
    offset = np.array([*(centre * scale + mu), 0.0])
    iron = _iron(offset, W)
    headings = heading_deg(iron.apply_array(xyz))
    gap = _largest_gap_deg(headings)
    if gap > MAX_HEADING_GAP_DEG:
        raise CalibrationError(
            f"the turn leaves {gap:.0f} deg of headings unvisited (at most {MAX_HEADING_GAP_DEG:.0f});"
            " turn the stage a full circle"
        )
    return iron, radius * scale


def _iron(offset: np.ndarray, W: np.ndarray) -> HardSoftIron:
    o = tuple(float(v) for v in offset)
    m = tuple(float(v) for v in W.ravel())
    return HardSoftIron((o[0], o[1], o[2]), (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]))


def _largest_gap_deg(headings_deg: np.ndarray) -> float:
    h = np.sort(np.mod(headings_deg, 360.0))
    gaps = np.diff(np.concatenate([h, [h[0] + 360.0]]))
    return float(gaps.max())


# --------------------------------------------------------------------------- headings


def heading_deg(field: np.ndarray, down: np.ndarray | None = None) -> np.ndarray:
    """Magnetic heading of the body x axis, degrees clockwise from magnetic north in [0, 360).

    ``field``: (N, 3) or (3,) body-frame field; ``down``: the body-frame down direction, same shape
    or (3,), default (0, 0, -1) (a levelled, z-up body).  Tilt is compensated through ``down``.
    """
    f = np.atleast_2d(np.asarray(field, dtype=np.float64))
    d = np.atleast_2d(np.asarray(LEVEL_DOWN if down is None else down, dtype=np.float64))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    east = np.cross(d, f)
    north = np.cross(east, d)
    heading = np.degrees(np.arctan2(east[:, 0], north[:, 0])) % 360.0
    return heading


def wrap_deg(angle_deg: Any) -> np.ndarray:
    """Angles wrapped into [-180, 180)."""
    return (np.asarray(angle_deg, dtype=np.float64) + 180.0) % 360.0 - 180.0


def circular_mean_deg(angles_deg: np.ndarray) -> float:
    r = np.radians(angles_deg)
    return float(np.degrees(np.arctan2(np.mean(np.sin(r)), np.mean(np.cos(r)))))


def circular_std_deg(angles_deg: np.ndarray) -> float:
    r = np.radians(angles_deg)
    R = math.hypot(float(np.mean(np.sin(r))), float(np.mean(np.cos(r))))
    return math.degrees(math.sqrt(-2.0 * math.log(max(R, 1e-300))))


def magnitude_spread(field: np.ndarray) -> float:
    """Relative spread std(|B|) / mean(|B|) of the readings."""
    norm = np.linalg.norm(np.asarray(field, dtype=np.float64), axis=1)
    return float(np.std(norm) / np.mean(norm))


def mounting_offset_deg(
    magnetic_heading_deg: np.ndarray, known_bearing_deg: float, declination_deg: float
) -> float:
    """Mounting offset in [-180, 180): circular mean of magnetic heading + declination - known bearing."""
    return float(
        wrap_deg(circular_mean_deg(np.asarray(magnetic_heading_deg) + declination_deg - known_bearing_deg))
    )


# --------------------------------------------------------------------------- the calibration


def calibrate_compass(
    log: MagnetometerLog,
    mode: str = "sphere",
    *,
    down: np.ndarray | None = None,
    known_bearing_deg: float | None = None,
    bearing_window_s: float = 1.0,
    declination_deg: float = 0.0,
) -> CompassCalibration:
    """Fit hard and soft iron and report the figures; see the module docstring for the modes.

    ``known_bearing_deg``: true bearing the x axis faced during the first ``bearing_window_s``
    seconds of the log; gives the mounting offset.  ``down``: body-frame down per sample (from an
    accelerometer) for tilt-compensated headings; None assumes the body level.
    """
    raw = np.asarray(log.field_gauss, dtype=np.float64)
    if mode == "sphere":
        iron, field = fit_ellipsoid(raw)
    elif mode == "level":
        iron, field = fit_level_ellipse(raw)
    else:
        raise InputError(f"compass mode must be 'sphere' or 'level', got {mode!r}")
    corrected = iron.apply_array(raw)
    components = slice(0, 3) if mode == "sphere" else slice(0, 2)
    h_raw = heading_deg(raw, down)
    h_cal = heading_deg(corrected, down)

    err_before = err_after = None
    ref = log.reference_heading_deg
    if ref is not None and np.any(np.isfinite(ref)):
        known = np.isfinite(ref)
        rms = []
        for h in (h_raw, h_cal):
            e = wrap_deg(h[known] + declination_deg - ref[known])
            e = wrap_deg(e - circular_mean_deg(e))  # the constant part is the mounting offset
            rms.append(float(np.sqrt(np.mean(e * e))))
        err_before, err_after = rms

    offset = None
    if known_bearing_deg is not None:
        window = log.t_s <= log.t_s[0] + bearing_window_s
        offset = mounting_offset_deg(h_cal[window], known_bearing_deg, declination_deg)

    return CompassCalibration(
        mode=mode,
        iron=iron,
        n=len(raw),
        field_gauss=field,
        magnitude_spread_before=magnitude_spread(raw[:, components]),
        magnitude_spread_after=magnitude_spread(corrected[:, components]),
        heading_correction_max_deg=float(np.max(np.abs(wrap_deg(h_raw - h_cal)))),
        heading_error_rms_before_deg=err_before,
        heading_error_rms_after_deg=err_after,
        mounting_offset_deg=offset,
        declination_deg=declination_deg,
    )


def calibrate_compass_file(
    path: str | Path,
    mode: str = "sphere",
    *,
    accel_path: str | Path | None = None,
    accel_measures: str = "up",
    known_bearing_deg: float | None = None,
    bearing_window_s: float = 1.0,
    declination_deg: float = 0.0,
) -> CompassCalibration:
    log = read_magnetometer_csv(path)
    down = None if accel_path is None else read_down_csv(accel_path, log.t_s, measures=accel_measures)
    return calibrate_compass(
        log,
        mode,
        down=down,
        known_bearing_deg=known_bearing_deg,
        bearing_window_s=bearing_window_s,
        declination_deg=declination_deg,
    )


def compass_table(result: CompassCalibration) -> dict[str, Any]:
    """The ``[compass]`` table of the calibration file, SI units: what the magnetometer driver reads.

    ``hard_iron_offset`` in tesla, ``soft_iron_matrix`` (9 floats, row-major), and
    ``mounting_offset_deg`` when a known bearing was given.
    """
    table: dict[str, Any] = {
        key: [significant(v, 8) for v in values] for key, values in result.iron_tesla.to_table().items()
    }
    if result.mounting_offset_deg is not None:
        table[MOUNTING_KEY] = significant(result.mounting_offset_deg, 6)
    return table


def write_compass_calibration(path: str | Path, result: CompassCalibration) -> None:
    """Set ``[compass]`` in the calibration TOML ``path`` (created if absent; the rest kept).

    The keys a previous version of this table held (``offset``/``matrix`` in gauss) are removed,
    so the file has one calibration, in one unit.
    """
    update_toml_table(path, CALIBRATION_TABLE, compass_table(result), must_exist=False, remove=LEGACY_KEYS)


def format_report(result: CompassCalibration) -> str:
    o = result.iron.offset
    W = np.asarray(result.iron.matrix).reshape(3, 3)
    what = "|B|" if result.mode == "sphere" else "|B_xy|"
    lines = [
        f"mode {result.mode}, {result.n} samples, corrected field {result.field_gauss:.4f} gauss",
        f"hard iron offset = [{o[0]:.5f}, {o[1]:.5f}, {o[2]:.5f}] gauss"
        f" (written in tesla: [{o[0] * GAUSS_TO_TESLA:.4e}, {o[1] * GAUSS_TO_TESLA:.4e}, {o[2] * GAUSS_TO_TESLA:.4e}])",
        "soft iron matrix = " + "; ".join("[" + ", ".join(f"{v:.5f}" for v in row) + "]" for row in W),
        f"{what} spread (std/mean): before {result.magnitude_spread_before:.2%},"
        f" after {result.magnitude_spread_after:.2%}",
        f"largest heading correction = {result.heading_correction_max_deg:.2f} deg",
    ]
    if result.heading_error_rms_before_deg is not None:
        lines.append(
            f"heading error against the reference (rms):"
            f" before {result.heading_error_rms_before_deg:.2f} deg,"
            f" after {result.heading_error_rms_after_deg:.2f} deg"
        )
    if result.mounting_offset_deg is not None:
        lines.append(
            f"mounting offset = {result.mounting_offset_deg:.2f} deg"
            f" (declination {result.declination_deg:.2f} deg east)"
        )
    return "\n".join(lines)
