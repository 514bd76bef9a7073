"""Simulated I2C chips behind a fake bus with ``smbus2.SMBus``'s method names.

:class:`FakeI2cBus` routes ``read_byte_data``, ``write_byte_data`` and ``read_i2c_block_data`` to
the chip at the address; an address with no chip raises ``OSError`` (errno 121, ``EREMOTEIO``) as
the Linux I2C driver does on a missing ACK.  Each chip keeps its datasheet register map and
computes its data registers from the :class:`SimWorld` when they are read.
"""

from __future__ import annotations

import errno
import math
import threading

import numpy as np

from appliance.drivers.accelerometer import ADXL345_DEVID, ADXL345_FULL_RES_G_PER_LSB, Adxl345Register
from appliance.drivers.attitude import Vec3
from appliance.drivers.magnetometer import (
    GAUSS_TO_TESLA,
    HMC5883L_ID,
    HMC5883L_LSB_PER_GAUSS,
    Hmc5883lRegister,
)
from appliance.sim.world import SimWorld


class SimChip:
    def __init__(self) -> None:
        self.registers = bytearray(256)

    def read(self, register: int, length: int) -> list[int]:
        self.refresh(register)
        return list(self.registers[register : register + length])

    def write(self, register: int, value: int) -> None:
        self.registers[register] = value & 0xFF

    def refresh(self, register: int) -> None:
        """Recompute data registers before a read (override)."""


class FakeI2cBus:
    def __init__(self) -> None:
        self.chips: dict[int, SimChip] = {}
        self.lock = threading.Lock()
        self.transfers = 0

    def attach(self, address: int, chip: SimChip) -> None:
        self.chips[address] = chip

    def _chip(self, address: int) -> SimChip:
        chip = self.chips.get(address)
        if chip is None:
            raise OSError(errno.EREMOTEIO, f"no ACK from I2C address 0x{address:02X}")
        return chip

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        with self.lock:
            self.transfers += 1
            return self._chip(i2c_addr).read(register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        with self.lock:
            self.transfers += 1
            self._chip(i2c_addr).write(register, value)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        with self.lock:
            self.transfers += 1
            return self._chip(i2c_addr).read(register, length)

    def close(self) -> None:
        self.chips.clear()


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))


class SimHmc5883l(SimChip):
    """HMC5883L: data X, Z, Y big-endian from the world's raw field (with hard and soft iron)."""

    def __init__(self, world: SimWorld, noise_t: float = 2e-8, seed: int = 0, stuck: bool = False,
                 drift_deg_per_s: float = 0.0, metal_nearby: bool = False) -> None:
        super().__init__()
        self.world = world
        self.metal_nearby = metal_nearby
        self.noise_t = noise_t
        self.rng = np.random.default_rng(seed)
        self.stuck = stuck
        self.drift_deg_per_s = drift_deg_per_s
        self._first: bytes | None = None
        self._t0 = world.clock.now()
        self.registers[Hmc5883lRegister.ID_A : Hmc5883lRegister.ID_A + 3] = HMC5883L_ID
        self.registers[Hmc5883lRegister.CONFIG_B] = 1 << 5
        self.registers[Hmc5883lRegister.MODE] = 1

    def field(self) -> Vec3:
        x, y, z = self.world.field_body_raw_t()
        if self.drift_deg_per_s:
            a = math.radians(self.drift_deg_per_s * (self.world.clock.now() - self._t0).total_seconds())
            x, y = x * math.cos(a) - y * math.sin(a), x * math.sin(a) + y * math.cos(a)
        if self.metal_nearby:
            # induced magnetisation of nearby steel: a distortion no ellipse fit absorbs
            h = math.radians(self.world.head_heading_deg)
            b = math.hypot(self.world.field_world_t[0], self.world.field_world_t[1])
            x, y = x + 0.4 * b * math.cos(3 * h), y + 0.4 * b * math.sin(2 * h)
        n = self.rng.normal(0.0, self.noise_t, 3)
        return (x + n[0], y + n[1], z + n[2])

    def refresh(self, register: int) -> None:
        if register != Hmc5883lRegister.DATA_X_MSB:
            return
        gain = self.registers[Hmc5883lRegister.CONFIG_B] >> 5
        k = HMC5883L_LSB_PER_GAUSS[gain] / GAUSS_TO_TESLA
        x, y, z = self.field()
        data = b"".join(_i16(v * k).to_bytes(2, "big", signed=True) for v in (x, z, y))
        if self.stuck:
            self._first = self._first or data
            data = self._first
        self.registers[Hmc5883lRegister.DATA_X_MSB : Hmc5883lRegister.DATA_X_MSB + 6] = data
        self.registers[Hmc5883lRegister.STATUS] = 0x01


class SimAdxl345(SimChip):
    """ADXL345 in full resolution: data X, Y, Z little-endian from gravity in the head's frame."""

    def __init__(self, world: SimWorld, noise_g: float = 0.004, seed: int = 0, stuck: bool = False,
                 devid: int = ADXL345_DEVID) -> None:
        super().__init__()
        self.world = world
        self.noise_g = noise_g
        self.rng = np.random.default_rng(seed + 1)
        self.stuck = stuck
        self._first: bytes | None = None
        self.registers[Adxl345Register.DEVID] = devid

    def refresh(self, register: int) -> None:
        if register != Adxl345Register.DATAX0:
            return
        a = self.world.accel_body_g()
        n = self.rng.normal(0.0, self.noise_g, 3)
        data = b"".join(
            _i16((a[i] + n[i]) / ADXL345_FULL_RES_G_PER_LSB).to_bytes(2, "little", signed=True) for i in range(3)
        )
        if self.stuck:
            self._first = self._first or data
            data = self._first
        if not self.registers[Adxl345Register.POWER_CTL] & 0x08:
            data = bytes(6)  # standby: the data registers hold no measurement
        self.registers[Adxl345Register.DATAX0 : Adxl345Register.DATAX0 + 6] = data
