"""Calibration files -> drivers: what `viper calibrate` writes is what the drivers read and apply.

Compass: fit on the real raw HMC5883L log (gauss), write the calibration TOML (SI: tesla), point
``[devices] calibration_file`` at it, load the configuration, take the hard/soft iron the platform
factory gives the magnetometer driver and apply it to raw readings in tesla (as the driver decodes
them from the chip's registers): the field magnitude must be as constant as the fit made it.
Inclinometer: reversal readings of a sensor with known offsets -> `viper calibrate inclinometer`
-> the driver's tilt at stage 0 and 180 deg is the stage's true tilt, reversed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from viper_calibration.compass import calibrate_compass_file, magnitude_spread, write_compass_calibration
from viper_calibration.device_file import calibration_of, tilt_offset_of

from appliance.cli.main import main
from appliance.config import load_config
from appliance.drivers.accelerometer import TiltOffset, average_tilt
from appliance.drivers.magnetometer import GAUSS_TO_TESLA, HMC5883L_LSB_PER_GAUSS, HardSoftIron, decode_hmc5883l_data
from appliance.errors import CalibrationError, ConfigError
from tests.conftest import data_file

MAG_LOG = "imu_magnetometer/sunsided_mpu6050_hmc5883l/full-sphere/hmc5883l_compass.csv"


def _config(tmp_path: Path, calibration: Path, extra: str = "") -> Path:
    cfg = tmp_path / "viper.toml"
    cfg.write_text(f'[devices]\ncalibration_file = "{calibration}"\n{extra}')
    return cfg


def _hmc5883l_block(xyz_gauss: np.ndarray, lsb_per_gauss: float) -> list[int]:
    """The chip's six data bytes (X, Z, Y big-endian int16) for a field in gauss."""
    x, y, z = (int(round(v * lsb_per_gauss)) for v in xyz_gauss)
    return [b for v in (x, z, y) for b in v.to_bytes(2, "big", signed=True)]


def test_compass_calibration_file_round_trip_through_the_drivers(tmp_path: Path) -> None:
    path = data_file(MAG_LOG)
    result = calibrate_compass_file(path, "sphere")
    cal = tmp_path / "calibration.toml"
    write_compass_calibration(cal, result)
    iron = calibration_of(load_config(_config(tmp_path, cal)).devices)

    raw_gauss = np.loadtxt(path, delimiter=",", skiprows=1, usecols=(1, 2, 3))
    assert raw_gauss.shape == (result.n, 3)
    raw_t = raw_gauss * GAUSS_TO_TESLA
    corrected = iron.apply_array(raw_t)
    # the same spread the fit reported (13.6 % -> 0.46 %), now on readings in tesla
    assert magnitude_spread(raw_t) == pytest.approx(0.136, abs=0.002)
    assert magnitude_spread(corrected) < 0.006
    assert magnitude_spread(corrected) == pytest.approx(result.magnitude_spread_after, rel=1e-3)
    # and the field strength in tesla is the fitted one in gauss, converted
    mean_t = float(np.mean(np.linalg.norm(corrected, axis=1)))
    assert mean_t == pytest.approx(result.field_gauss * GAUSS_TO_TESLA, rel=2e-3)

    # through the chip's registers: counts -> tesla (driver decode) -> calibration (driver apply)
    lsb = HMC5883L_LSB_PER_GAUSS[1]
    per_reading = np.array([iron.apply(decode_hmc5883l_data(_hmc5883l_block(g, lsb), lsb)) for g in raw_gauss[::10]])
    assert per_reading == pytest.approx(corrected[::10], abs=2e-9)  # 1 LSB = 0.09 uT before correction


def test_compass_file_errors_are_clear(tmp_path: Path) -> None:
    cal = tmp_path / "calibration.toml"
    cal.write_text("[compass]\noffset = [0.1, 0.2, 0.3]\nmatrix = [1, 0, 0, 0, 1, 0, 0, 0, 1]\n")
    with pytest.raises(CalibrationError, match="unknown key matrix"):
        calibration_of(load_config(_config(tmp_path, cal)).devices)
    cal.write_text("[compass]\nhard_iron_offset = [1e-5, 2e-5]\n")
    with pytest.raises(CalibrationError, match="hard_iron_offset: expected an array of 3 numbers"):
        calibration_of(load_config(_config(tmp_path, cal)).devices)
    cal.write_text("[compass]\nhard_iron_offset = [1e-5, 2e-5, 0.0]\n")
    twice = _config(tmp_path, cal, "[devices.compass]\nhard_iron_offset = [1e-6, 0.0, 0.0]\n")
    with pytest.raises(ConfigError, match="given twice"):
        calibration_of(load_config(twice).devices)
    # a file without a [compass] table leaves the configuration's own values
    cal.write_text("[inclinometer]\npitch_offset_deg = 0.5\n")
    inline = _config(tmp_path, cal, "[devices.compass]\nhard_iron_offset = [1e-6, 0.0, 0.0]\n")
    assert calibration_of(load_config(inline).devices) == HardSoftIron((1e-6, 0.0, 0.0))
    with pytest.raises(ConfigError, match="file not found"):
        calibration_of(load_config(_config(tmp_path, tmp_path / "absent.toml")).devices)


def _accel_g(pitch_deg: float, roll_deg: float) -> tuple[float, float, float]:
    """An at-rest accelerometer reading (g, FLU) whose pitch and roll are the given angles."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    return (math.sin(p), math.cos(p) * math.sin(r), math.cos(p) * math.cos(r))


def test_inclinometer_offsets_written_are_what_the_driver_subtracts(tmp_path: Path, capsys) -> None:
    stage_tilt = (0.30, -0.20)  # (pitch, roll) of the head at stage 0; reversed at 180
    sensor_offset = (0.06, 0.11)  # what the sensor adds to both
    rows = ["stage_deg,tilt_x_deg,tilt_y_deg"]
    samples = {}
    for stage, sign in ((0.0, 1.0), (180.0, -1.0)):
        raw = [_accel_g(sign * stage_tilt[0] + sensor_offset[0], sign * stage_tilt[1] + sensor_offset[1])] * 4
        samples[stage] = raw
        t = average_tilt(raw)  # the driver's reading before its offset: x = pitch, y = roll
        rows.append(f"{stage},{t.pitch_deg!r},{t.roll_deg!r}")
    csv = tmp_path / "reversal.csv"
    csv.write_text("\n".join(rows) + "\n")
    cal = tmp_path / "calibration.toml"
    assert main(["calibrate", "inclinometer", str(csv), "--output", str(cal)]) == 0
    capsys.readouterr()

    offset = tilt_offset_of(load_config(_config(tmp_path, cal)).devices)
    assert (offset.pitch_deg, offset.roll_deg) == pytest.approx(sensor_offset, abs=1e-6)
    at_0 = average_tilt(samples[0.0], offset)
    at_180 = average_tilt(samples[180.0], offset)
    assert (at_0.pitch_deg, at_0.roll_deg) == pytest.approx(stage_tilt, abs=1e-6)
    assert (at_180.pitch_deg, at_180.roll_deg) == pytest.approx((-stage_tilt[0], -stage_tilt[1]), abs=1e-6)

    twice = _config(tmp_path, cal, "[devices.inclinometer]\npitch_offset_deg = 0.5\n")
    with pytest.raises(ConfigError, match="given twice"):
        tilt_offset_of(load_config(twice).devices)
    assert tilt_offset_of(load_config(None).devices) == TiltOffset()
