"""The calibration file of ``[devices] calibration_file``, read at the edge into the objects the
drivers receive (:class:`appliance.drivers.factory.DeviceCalibration`).

``viper calibrate compass|inclinometer`` writes its ``[compass]`` table (``hard_iron_offset`` in
tesla, ``soft_iron_matrix``) and its ``[inclinometer]`` table (``pitch_offset_deg``,
``roll_offset_deg``); they replace the same keys of ``[devices.compass]`` and
``[devices.inclinometer]``, which must then be left at their defaults.
"""

from __future__ import annotations

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
from appliance.inputs import MAX_CONFIG_BYTES, NestingError, check_nesting, read_text_bounded


def _calibration_table(devices: DevicesConfig, name: str) -> tuple[dict[str, Any] | None, str]:
    """The ``[name]`` table of ``[devices] calibration_file`` (None if no file or no such table)."""
    path = devices.calibration_file
    if path is None:
        return None, ""
    try:
        text = read_text_bounded(path, MAX_CONFIG_BYTES, "calibration file", ConfigError)
        check_nesting(text)
        doc = tomlkit.parse(text).unwrap()
    except FileNotFoundError:
        raise ConfigError(f"devices.calibration_file: {path}: file not found") from None
    except NestingError as exc:
        raise ConfigError(f"devices.calibration_file: {path}: {exc}") from None
    except tomlkit.exceptions.ParseError as exc:
        raise ConfigError(f"devices.calibration_file: {path}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"devices.calibration_file: {path}: cannot read: {exc}") from None
    table = doc.get(name)
    if table is not None and not isinstance(table, dict):
        raise ConfigError(f"{path}: {name} is not a table")
    return table, f"{path} [{name}]"


def _file_or_inline(devices: DevicesConfig, table_name: str, inline: Any, what: str, where: str) -> Any:
    """A calibration from the calibration file's ``table_name`` where it has one, else ``inline``; given in
    both (the inline one not at its default) is refused."""
    table, source = _calibration_table(devices, table_name)
    if table is None:
        return inline
    if inline != type(inline)():
        raise ConfigError(f"{what} given twice: in {where} and in {source}; keep one")
    return type(inline).from_table(table, source)


def calibration_of(devices: DevicesConfig) -> HardSoftIron:
    """The magnetometer's hard/soft iron (tesla): the calibration file's [compass], else [devices.compass]."""
    c = devices.compass
    return _file_or_inline(devices, MAGNETOMETER_TABLE, HardSoftIron(c.hard_iron_offset, c.soft_iron_matrix),
                           "compass calibration", "[devices.compass]")


def tilt_offset_of(devices: DevicesConfig) -> TiltOffset:
    """The inclinometer's offsets (deg): the calibration file's [inclinometer], else [devices.inclinometer]."""
    c = devices.inclinometer
    return _file_or_inline(devices, INCLINOMETER_TABLE, TiltOffset(c.pitch_offset_deg, c.roll_offset_deg),
                           "inclinometer offsets", "[devices.inclinometer]")


def load_device_calibration(devices: DevicesConfig) -> DeviceCalibration:
    """Both calibrations, each from the calibration file where it has the table, else inline."""
    return DeviceCalibration(calibration_of(devices), tilt_offset_of(devices))
