"""Inclinometer offsets by the two-position (reversal) method.

The platform stands on a stage; the two-axis inclinometer is read with the stage at 0 deg and again
after turning it 180 deg about the vertical.  The turn reverses the sign of the true tilt seen by
each sensor axis but not the sensor's zero offset, so with readings r0 and r180 (degrees)

    offset = (r0 + r180) / 2        true tilt at 0 deg = (r0 - r180) / 2

Corrected reading = raw reading - offset.  Several readings per position are averaged.

Axes: ``tilt_x_deg`` is the inclination of the body x axis (forward; nose up positive), i.e. the
pitch the inclinometer driver (:mod:`appliance.drivers.accelerometer`) reads before its offset;
``tilt_y_deg`` that of the y axis (left; left side up positive), i.e. its roll.  The file written
is the ``[inclinometer]`` table of a calibration TOML with the keys of ``[devices.inclinometer]``:
``pitch_offset_deg`` (x) and ``roll_offset_deg`` (y), degrees, which the driver subtracts
(:class:`appliance.drivers.accelerometer.TiltOffset`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from viper_calibration.config_edit import significant, update_toml_table
from viper_calibration.csvtable import read_input, read_rows

from appliance.drivers.accelerometer import CALIBRATION_TABLE, TiltOffset
from appliance.errors import CalibrationError, InputError

HEADER = ("stage_deg", "tilt_x_deg", "tilt_y_deg")
AXES = ("x", "y")


@dataclass(frozen=True)
class ReversalReadings:
    """Stage angles (deg) and tilt readings (N, 2) in degrees, axes x and y."""

    stage_deg: np.ndarray
    tilt_deg: np.ndarray


@dataclass(frozen=True)
class InclinometerCalibration:
    """Per-axis zero offsets, the stage tilt seen at 0 deg, and the reading spread per position (deg)."""

    offset_deg: tuple[float, float]
    tilt_at_zero_deg: tuple[float, float]
    readings_at_0: int
    readings_at_180: int
    spread_deg: tuple[float, float]  # largest std of one axis at one position (0 with one reading)

    @property
    def tilt_offset(self) -> TiltOffset:
        """The offsets as the inclinometer driver takes them (x axis = pitch, y axis = roll)."""
        return TiltOffset(self.offset_deg[0], self.offset_deg[1])

    def as_dict(self) -> dict[str, Any]:
        return {
            "offset_x_deg": self.offset_deg[0],
            "offset_y_deg": self.offset_deg[1],
            "tilt_x_at_zero_deg": self.tilt_at_zero_deg[0],
            "tilt_y_at_zero_deg": self.tilt_at_zero_deg[1],
            "readings_at_0": self.readings_at_0,
            "readings_at_180": self.readings_at_180,
        }


def parse_reversal_csv(data: bytes, source: str = "<readings>") -> ReversalReadings:
    """Parse ``stage_deg,tilt_x_deg,tilt_y_deg`` rows."""
    rows = read_rows(data, source, HEADER)
    values = np.empty((len(rows), 3))
    for i, row in enumerate(rows):
        line_no = i + 2
        if len(row) != len(HEADER):
            raise InputError(f"{source}:{line_no}: expected {len(HEADER)} fields, got {len(row)}")
        for j, (name, cell) in enumerate(zip(HEADER, row, strict=True)):
            try:
                value = float(cell)
            except ValueError:
                raise InputError(f"{source}:{line_no}: {name} {cell.strip()!r} is not a number") from None
            if not math.isfinite(value):
                raise InputError(f"{source}:{line_no}: {name} is {cell.strip()}")
            values[i, j] = value
    return ReversalReadings(values[:, 0], values[:, 1:])


def read_reversal_csv(path: str | Path) -> ReversalReadings:
    return parse_reversal_csv(read_input(path), source=str(path))


def calibrate_reversal(
    readings: ReversalReadings, angle_tolerance_deg: float = 2.0
) -> InclinometerCalibration:
    """Offsets from readings at stage 0 and 180 deg (each within ``angle_tolerance_deg``)."""
    stage = np.mod(readings.stage_deg, 360.0)
    tilt = readings.tilt_deg
    at_0 = (stage <= angle_tolerance_deg) | (stage >= 360.0 - angle_tolerance_deg)
    at_180 = np.abs(stage - 180.0) <= angle_tolerance_deg
    elsewhere = ~(at_0 | at_180)
    if np.any(elsewhere):
        first = float(readings.stage_deg[np.argmax(elsewhere)])
        raise InputError(
            f"stage angle {first} deg is neither 0 nor 180 (tolerance {angle_tolerance_deg} deg);"
            " the reversal method uses those two positions only"
        )
    if not at_0.any() or not at_180.any():
        have = "0" if at_0.any() else "180"
        raise CalibrationError(f"readings only at stage {have} deg; the reversal needs both 0 and 180 deg")
    for k, axis in enumerate(AXES):
        if np.ptp(tilt[:, k]) == 0.0:
            raise CalibrationError(
                f"tilt_{axis}_deg is constant ({tilt[0, k]} deg) at both positions; is the sensor answering?"
            )
    mean_0 = tilt[at_0].mean(axis=0)
    mean_180 = tilt[at_180].mean(axis=0)
    offset = (mean_0 + mean_180) / 2.0
    true_tilt = (mean_0 - mean_180) / 2.0
    spread = np.maximum(tilt[at_0].std(axis=0), tilt[at_180].std(axis=0))
    return InclinometerCalibration(
        offset_deg=(float(offset[0]), float(offset[1])),
        tilt_at_zero_deg=(float(true_tilt[0]), float(true_tilt[1])),
        readings_at_0=int(at_0.sum()),
        readings_at_180=int(at_180.sum()),
        spread_deg=(float(spread[0]), float(spread[1])),
    )


LEGACY_KEYS = ("offset_x_deg", "offset_y_deg")  # the table's keys before it used the driver's names


def inclinometer_table(result: InclinometerCalibration) -> dict[str, float]:
    """The ``[inclinometer]`` table of the calibration file (degrees, subtracted from raw readings)."""
    return {key: significant(v, 8) for key, v in result.tilt_offset.to_table().items()}


def write_inclinometer_calibration(path: str | Path, result: InclinometerCalibration) -> None:
    """Set ``[inclinometer]`` in the calibration TOML ``path`` (created if absent; the rest kept)."""
    update_toml_table(path, CALIBRATION_TABLE, inclinometer_table(result), must_exist=False, remove=LEGACY_KEYS)


def format_report(result: InclinometerCalibration) -> str:
    lines = [
        f"readings: {result.readings_at_0} at stage 0 deg, {result.readings_at_180} at stage 180 deg",
        f"{'axis':<5}  {'offset_deg':>11}  {'stage_tilt_deg':>14}  {'spread_deg':>10}",
    ]
    for k, axis in enumerate(AXES):
        lines.append(
            f"{axis:<5}  {result.offset_deg[k]:>11.4f}  {result.tilt_at_zero_deg[k]:>14.4f}"
            f"  {result.spread_deg[k]:>10.4f}"
        )
    return "\n".join(lines)
