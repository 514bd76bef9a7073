"""3-axis I2C magnetometer (Honeywell HMC5883L) with hard/soft-iron calibration.

Register map (HMC5883L datasheet, rev. E): 0x00 configuration A (samples averaged bits 6:5, output
rate bits 4:2, measurement mode bits 1:0), 0x01 configuration B (gain bits 7:5), 0x02 mode
(0 continuous, 1 single), 0x03..0x08 data X, Z, Y as big-endian int16 (note the X, Z, Y order),
0x09 status (bit 0 RDY), 0x0A..0x0C identification ``"H43"``.  A reading of -4096 on an axis
means ADC overflow.  The chip's axes are taken to be the body FLU axes (x forward, y left, z up);
mount it so, or fold the rotation into the calibration matrix.

Calibration: a measurement ``raw = S @ true + b`` (soft iron ``S``, hard iron ``b``) is corrected by
:class:`HardSoftIron` as ``matrix @ (raw - offset)`` (ideally ``offset = b``, ``matrix = S^-1``).
``offset`` is in the units of the readings it corrects (this driver reads tesla); ``matrix`` is
dimensionless.  ``viper calibrate compass`` (:mod:`viper_calibration.compass`) fits it and stores it, in
SI units, as the ``[compass]`` table of a calibration TOML, with the same keys as the
``[devices.compass]`` section of the configuration::

    [compass]
    hard_iron_offset = [x, y, z]        # tesla
    soft_iron_matrix = [9 floats]       # row-major, dimensionless
    mounting_offset_deg = 1.23          # optional; information for the operator

``[devices] calibration_file`` points the platform at that file (:func:`HardSoftIron.from_table`
reads the table; the configuration's own ``hard_iron_offset``/``soft_iron_matrix`` are used when
no file is given).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.drivers.attitude import Vec3
from appliance.drivers.i2c import I2cBus, checked
from appliance.errors import CalibrationError, DeviceError

HMC5883L_ADDRESS = 0x1E


class Hmc5883lRegister(enum.IntEnum):
    CONFIG_A = 0x00
    CONFIG_B = 0x01
    MODE = 0x02
    DATA_X_MSB = 0x03
    STATUS = 0x09
    ID_A = 0x0A


HMC5883L_ID = b"H43"
HMC5883L_OVERFLOW = -4096
#: Gain setting (config B bits 7:5) -> LSB per gauss (datasheet table 9).
HMC5883L_LSB_PER_GAUSS = (1370.0, 1090.0, 820.0, 660.0, 440.0, 390.0, 330.0, 230.0)
GAUSS_TO_TESLA = 1e-4


class Hmc5883lMode(enum.IntEnum):
    CONTINUOUS = 0
    SINGLE = 1
    IDLE = 2


#: The table of a calibration TOML that holds the magnetometer's calibration, and its keys.
CALIBRATION_TABLE = "compass"
OFFSET_KEY = "hard_iron_offset"  # tesla
MATRIX_KEY = "soft_iron_matrix"
MOUNTING_KEY = "mounting_offset_deg"  # written for the operator; not applied here


@dataclass(frozen=True)
class HardSoftIron:
    """Magnetometer calibration: ``corrected = matrix @ (raw - offset)``.

    ``offset`` is in the units of the raw readings (tesla for this driver and in calibration files);
    ``matrix`` holds 9 dimensionless floats, row-major.
    """

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    matrix: tuple[float, float, float, float, float, float, float, float, float] = (
        1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0,
    )

    def __post_init__(self) -> None:
        if len(self.offset) != 3 or len(self.matrix) != 9:
            raise CalibrationError(
                f"hard/soft iron: expected 3 offsets and 9 matrix values, got {len(self.offset)} and "
                f"{len(self.matrix)}"
            )
        bad = [v for v in (*self.offset, *self.matrix) if not math.isfinite(v)]
        if bad:
            raise CalibrationError(f"hard/soft iron: non-finite value {bad[0]}")

    def apply(self, xyz: Vec3) -> Vec3:
        """One corrected reading (units of ``offset``)."""
        d = (xyz[0] - self.offset[0], xyz[1] - self.offset[1], xyz[2] - self.offset[2])
        m = self.matrix
        return (
            m[0] * d[0] + m[1] * d[1] + m[2] * d[2],
            m[3] * d[0] + m[4] * d[1] + m[5] * d[2],
            m[6] * d[0] + m[7] * d[1] + m[8] * d[2],
        )

    def apply_array(self, xyz: Any) -> np.ndarray:
        """Corrected readings for an array of shape (3,) or (N, 3) (units of ``offset``)."""
        raw = np.asarray(xyz, dtype=np.float64)
        w = np.asarray(self.matrix, dtype=np.float64).reshape(3, 3)
        return np.asarray((raw - np.asarray(self.offset, dtype=np.float64)) @ w.T)

    def scaled(self, unit_factor: float) -> HardSoftIron:
        """The same correction for readings expressed in a unit ``unit_factor`` times smaller.

        E.g. ``iron_gauss.scaled(GAUSS_TO_TESLA)`` is the correction for readings in tesla: the
        offset is converted, the (dimensionless) matrix is kept.
        """
        o = self.offset
        k = float(unit_factor)
        return HardSoftIron((o[0] * k, o[1] * k, o[2] * k), self.matrix)

    def to_table(self) -> dict[str, list[float]]:
        """The keys of a ``[compass]`` calibration table (offset in this object's units: tesla)."""
        return {OFFSET_KEY: [float(v) for v in self.offset], MATRIX_KEY: [float(v) for v in self.matrix]}

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "[compass]") -> HardSoftIron:
        """Read a ``[compass]`` calibration table (``hard_iron_offset`` in tesla, ``soft_iron_matrix``).

        Missing keys keep the identity; unknown keys and values of the wrong shape or type raise
        :class:`CalibrationError`.
        """
        known = (OFFSET_KEY, MATRIX_KEY, MOUNTING_KEY)
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise CalibrationError(f"{source}: unknown key {unknown[0]} (known: {', '.join(known)})")
        default = cls()
        offset = _floats(table.get(OFFSET_KEY, default.offset), 3, f"{source} {OFFSET_KEY}")
        matrix = _floats(table.get(MATRIX_KEY, default.matrix), 9, f"{source} {MATRIX_KEY}")
        return cls((offset[0], offset[1], offset[2]), (
            matrix[0], matrix[1], matrix[2], matrix[3], matrix[4], matrix[5], matrix[6], matrix[7], matrix[8],
        ))


def _floats(value: Any, n: int, what: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise CalibrationError(f"{what}: expected an array of {n} numbers, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise CalibrationError(f"{what}: expected numbers, got {v!r}")
        out.append(float(v))
    return out


def decode_hmc5883l_data(block: list[int], lsb_per_gauss: float) -> Vec3:
    """Six data bytes (X, Z, Y big-endian int16) to (x, y, z) in tesla; overflow raises."""
    if len(block) != 6:
        raise DeviceError(f"HMC5883L: expected 6 data bytes, got {len(block)}")
    x, z, y = (int.from_bytes(bytes(block[i : i + 2]), "big", signed=True) for i in (0, 2, 4))
    if HMC5883L_OVERFLOW in (x, y, z):
        raise DeviceError(f"HMC5883L: ADC overflow (x={x}, y={y}, z={z}); lower the gain")
    k = GAUSS_TO_TESLA / lsb_per_gauss
    return (x * k, y * k, z * k)


class Hmc5883l:
    """HMC5883L on an I2C bus (``smbus2.SMBus`` or a simulated chip's bus)."""

    def __init__(self, bus: I2cBus, address: int = HMC5883L_ADDRESS, gain: int = 1, averaging: int = 3) -> None:
        if not 0 <= gain <= 7 or not 0 <= averaging <= 3:
            raise DeviceError(f"HMC5883L: gain {gain} (0..7) or averaging {averaging} (0..3) out of range")
        self.bus = bus
        self.address = address
        ident = bytes(checked("HMC5883L id", bus.read_i2c_block_data, address, Hmc5883lRegister.ID_A, 3))
        if ident != HMC5883L_ID:
            raise DeviceError(f"I2C 0x{address:02X}: identification {ident!r}, expected {HMC5883L_ID!r} (HMC5883L)")
        self.lsb_per_gauss = HMC5883L_LSB_PER_GAUSS[gain]
        rate_15hz = 0b100
        checked("HMC5883L config A", bus.write_byte_data, address, Hmc5883lRegister.CONFIG_A,
                (averaging << 5) | (rate_15hz << 2))
        checked("HMC5883L config B", bus.write_byte_data, address, Hmc5883lRegister.CONFIG_B, gain << 5)
        checked("HMC5883L mode", bus.write_byte_data, address, Hmc5883lRegister.MODE, Hmc5883lMode.CONTINUOUS)

    def read_tesla(self) -> Vec3:
        """One raw (uncalibrated) field reading in tesla, body axes."""
        block = checked("HMC5883L data", self.bus.read_i2c_block_data, self.address,
                        Hmc5883lRegister.DATA_X_MSB, 6)
        return decode_hmc5883l_data(list(block), self.lsb_per_gauss)
