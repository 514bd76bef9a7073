"""The small I2C bus interface the chip drivers use (a subset of ``smbus2.SMBus``).

``smbus2.SMBus(bus_number)`` satisfies it on hardware; the simulated chips in
:mod:`appliance.sim.i2c_chips` implement the same three methods over a register map.
"""

from __future__ import annotations

from typing import Protocol

from appliance.errors import DeviceError


class I2cBus(Protocol):
    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...


def open_smbus(bus_number: int) -> I2cBus:
    """``smbus2.SMBus`` on ``/dev/i2c-<bus_number>``; a missing bus raises :class:`DeviceError`."""
    import smbus2

    try:
        return smbus2.SMBus(bus_number)
    except OSError as exc:
        raise DeviceError(f"/dev/i2c-{bus_number}: cannot open I2C bus: {exc.strerror}") from None


def checked(what: str, call, *args):  # type: ignore[no-untyped-def]
    """Run one bus transfer; an ``OSError`` (no ACK, bus gone) becomes a :class:`DeviceError`."""
    try:
        return call(*args)
    except OSError as exc:
        raise DeviceError(f"{what}: I2C transfer failed: {exc}") from None
