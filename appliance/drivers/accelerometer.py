"""I2C accelerometer (Analog Devices ADXL345) as an inclinometer: roll and pitch from gravity.

Register map (ADXL345 datasheet, rev. G): 0x00 DEVID = 0xE5, 0x2C BW_RATE (rate code bits 3:0),
0x2D POWER_CTL (bit 3 Measure), 0x31 DATA_FORMAT (bit 3 FULL_RES, bits 1:0 range), 0x32..0x37
DATAX0..DATAZ1 little-endian int16.  In full resolution the scale is 3.9 mg/LSB at every range.
The chip's axes are taken as the body FLU axes (x forward, y left, z up); at rest level it reads
+1 g on z.  Tilt is averaged over ``samples`` readings and corrected by a :class:`TiltOffset`
(the readings of the mounted sensor on a level reference).

Pitch is the inclination of the x axis (nose up positive), roll that of the y axis (left side up,
i.e. right side down, positive), both in degrees.  ``viper calibrate inclinometer``
(:mod:`viper_calibration.inclinometer`, reversal method) writes the offsets as the ``[inclinometer]``
table of a calibration TOML, with the keys of the ``[devices.inclinometer]`` configuration section::

    [inclinometer]
    pitch_offset_deg = 0.06    # the reversal's x axis (tilt_x_deg)
    roll_offset_deg = 0.11     # the reversal's y axis (tilt_y_deg)

``[devices] calibration_file`` points the platform at that file (:meth:`TiltOffset.from_table`).
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from appliance.drivers.attitude import Vec3, tilt_from_accel
from appliance.drivers.i2c import I2cBus, checked
from appliance.errors import CalibrationError, DeviceError

log = logging.getLogger(__name__)
ADXL345_ADDRESS = 0x53
#: A real sensor's noise makes this many bit-identical 3-axis readings in a row implausible.
STUCK_MIN_SAMPLES = 4
ADXL345_DEVID = 0xE5
ADXL345_FULL_RES_G_PER_LSB = 0.0039
STANDARD_GRAVITY_M_S2 = 9.80665


class Adxl345Register(enum.IntEnum):
    DEVID = 0x00
    BW_RATE = 0x2C
    POWER_CTL = 0x2D
    DATA_FORMAT = 0x31
    DATAX0 = 0x32


POWER_CTL_MEASURE = 0x08
DATA_FORMAT_FULL_RES = 0x08
DATA_FORMAT_RANGE_16G = 0x03
BW_RATE_100HZ = 0x0A


#: The table of a calibration TOML that holds the inclinometer's offsets, and its keys.
CALIBRATION_TABLE = "inclinometer"
PITCH_KEY = "pitch_offset_deg"
ROLL_KEY = "roll_offset_deg"


@dataclass(frozen=True)
class TiltOffset:
    """Pitch and roll (deg) the sensor reads when the platform is level; subtracted from readings."""

    pitch_deg: float = 0.0
    roll_deg: float = 0.0

    def to_table(self) -> dict[str, float]:
        """The keys of an ``[inclinometer]`` calibration table (degrees)."""
        return {PITCH_KEY: float(self.pitch_deg), ROLL_KEY: float(self.roll_deg)}

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "[inclinometer]") -> TiltOffset:
        """Read an ``[inclinometer]`` calibration table; missing keys are 0, unknown keys raise."""
        known = (PITCH_KEY, ROLL_KEY)
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise CalibrationError(f"{source}: unknown key {unknown[0]} (known: {', '.join(known)})")
        values = []
        for key in known:
            v = table.get(key, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise CalibrationError(f"{source} {key}: expected a finite number of degrees, got {v!r}")
            values.append(float(v))
        return cls(values[0], values[1])


@dataclass(frozen=True)
class Tilt:
    """Platform pitch and roll in degrees (pitch nose up, roll right side down), with the spread
    (standard deviation, deg) of the averaged samples."""

    pitch_deg: float
    roll_deg: float
    pitch_sigma_deg: float
    roll_sigma_deg: float
    samples: int


def decode_adxl345_data(block: list[int]) -> Vec3:
    """Six data bytes (X, Y, Z little-endian int16, full resolution) to acceleration in g."""
    if len(block) != 6:
        raise DeviceError(f"ADXL345: expected 6 data bytes, got {len(block)}")
    x, y, z = (int.from_bytes(bytes(block[i : i + 2]), "little", signed=True) for i in (0, 2, 4))
    return (x * ADXL345_FULL_RES_G_PER_LSB, y * ADXL345_FULL_RES_G_PER_LSB, z * ADXL345_FULL_RES_G_PER_LSB)


def average_tilt(samples_g: list[Vec3], offset: TiltOffset = TiltOffset()) -> Tilt:
    """Mean tilt of several accelerometer readings (pure); a reading far from 1 g is refused."""
    if not samples_g:
        raise CalibrationError("no accelerometer samples to average")
    n = len(samples_g)
    for s in samples_g:
        norm = (s[0] ** 2 + s[1] ** 2 + s[2] ** 2) ** 0.5
        if not 0.5 < norm < 1.5:
            raise DeviceError(f"accelerometer reads {norm:.3f} g, not at rest (or stuck)")
    mean = (sum(s[0] for s in samples_g) / n, sum(s[1] for s in samples_g) / n, sum(s[2] for s in samples_g) / n)
    pitch, roll = tilt_from_accel(mean)
    each = [tilt_from_accel(s) for s in samples_g]
    sp = (sum((p - pitch) ** 2 for p, _ in each) / n) ** 0.5
    sr = (sum((r - roll) ** 2 for _, r in each) / n) ** 0.5
    return Tilt(pitch - offset.pitch_deg, roll - offset.roll_deg, sp, sr, n)


class Adxl345:
    """ADXL345 on an I2C bus (``smbus2.SMBus`` or a simulated chip's bus)."""

    def __init__(self, bus: I2cBus, address: int = ADXL345_ADDRESS) -> None:
        self.bus = bus
        self.address = address
        devid = checked("ADXL345 DEVID", bus.read_byte_data, address, Adxl345Register.DEVID)
        if devid != ADXL345_DEVID:
            raise DeviceError(f"I2C 0x{address:02X}: DEVID 0x{devid:02X}, expected 0x{ADXL345_DEVID:02X} (ADXL345)")
        checked("ADXL345 BW_RATE", bus.write_byte_data, address, Adxl345Register.BW_RATE, BW_RATE_100HZ)
        checked("ADXL345 DATA_FORMAT", bus.write_byte_data, address, Adxl345Register.DATA_FORMAT,
                DATA_FORMAT_FULL_RES | DATA_FORMAT_RANGE_16G)
        checked("ADXL345 POWER_CTL", bus.write_byte_data, address, Adxl345Register.POWER_CTL, POWER_CTL_MEASURE)

    def read_g(self) -> Vec3:
        block = checked("ADXL345 data", self.bus.read_i2c_block_data, self.address, Adxl345Register.DATAX0, 6)
        return decode_adxl345_data(list(block))

    def read_tilt(self, samples: int = 16, offset: TiltOffset = TiltOffset()) -> Tilt:
        """Averaged tilt; ``samples`` (>= 4) bit-identical readings mean a stuck sensor: DeviceError."""
        readings = [self.read_g() for _ in range(samples)]
        if samples >= STUCK_MIN_SAMPLES and len(set(readings)) == 1:
            log.warning("ADXL345 at 0x%02X: %d identical readings %s (stuck)", self.address, samples, readings[0])
            raise DeviceError(f"ADXL345 at 0x{self.address:02X}: {samples} identical readings, sensor stuck")
        return average_tilt(readings, offset)


def calibrate_level_offset(samples_g: list[Vec3]) -> TiltOffset:
    """The offset that makes the current (known level) attitude read zero pitch and roll."""
    t = average_tilt(samples_g)
    return TiltOffset(t.pitch_deg, t.roll_deg)
