"""The calibration file of ``[devices] calibration_file``, read at the edge into the objects the
drivers receive (:class:`appliance.drivers.factory.DeviceCalibration`).

``viper calibrate compass|inclinometer`` writes its ``[compass]`` table (``hard_iron_offset`` in
tesla, ``soft_iron_matrix``) and its ``[inclinometer]`` table (``pitch_offset_deg``,
``roll_offset_deg``); they replace the same keys of ``[devices.compass]`` and
``[devices.inclinometer]``, which must then be left at their defaults.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import tomlkit
import tomlkit.exceptions

from appliance.config import DevicesConfig
from appliance.drivers.accelerometer import CALIBRATION_TABLE as INCLINOMETER_TABLE
from appliance.drivers.accelerometer import TiltOffset
from appliance.drivers.factory import DeviceCalibration
from appliance.drivers.magnetometer import CALIBRATION_TABLE as MAGNETOMETER_TABLE
from appliance.drivers.magnetometer import HardSoftIron
from appliance.errors import ConfigError


def _calibration_table(devices: DevicesConfig, name: str) -> tuple[dict[str, Any] | None, str]:
    """The ``[name]`` table of ``[devices] calibration_file`` (None if no file or no such table)."""
    path = devices.calibration_file
    if path is None:
        return None, ""
    try:
        doc = tomlkit.parse(Path(path).read_text(encoding="utf-8")).unwrap()
    except FileNotFoundError:
        raise ConfigError(f"devices.calibration_file: {path}: file not found") from None
    except tomlkit.exceptions.ParseError as exc:
        raise ConfigError(f"devices.calibration_file: {path}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"devices.calibration_file: {path}: cannot read: {exc}") from None
    table = doc.get(name)
    if table is not None and not isinstance(table, dict):
        raise ConfigError(f"{path}: {name} is not a table")
    return table, f"{path} [{name}]"


def calibration_of(devices: DevicesConfig) -> HardSoftIron:
    """The magnetometer's hard/soft iron (tesla): the calibration file's [compass], else [devices.compass]."""
    c = devices.compass
    inline = HardSoftIron(c.hard_iron_offset, c.soft_iron_matrix)
    table, source = _calibration_table(devices, MAGNETOMETER_TABLE)
    if table is None:
        return inline
    if inline != HardSoftIron():
        raise ConfigError(f"compass calibration given twice: in [devices.compass] and in {source}; keep one")
    return HardSoftIron.from_table(table, source)


def tilt_offset_of(devices: DevicesConfig) -> TiltOffset:
    """The inclinometer's offsets (deg): the calibration file's [inclinometer], else [devices.inclinometer]."""
    c = devices.inclinometer
    inline = TiltOffset(c.pitch_offset_deg, c.roll_offset_deg)
    table, source = _calibration_table(devices, INCLINOMETER_TABLE)
    if table is None:
        return inline
    if inline != TiltOffset():
        raise ConfigError(f"inclinometer offsets given twice: in [devices.inclinometer] and in {source}; keep one")
    return TiltOffset.from_table(table, source)


def load_device_calibration(devices: DevicesConfig) -> DeviceCalibration:
    """Both calibrations, each from the calibration file where it has the table, else inline."""
    return DeviceCalibration(calibration_of(devices), tilt_offset_of(devices))
