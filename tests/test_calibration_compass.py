"""Compass hard/soft iron on the real raw HMC5883L logs (sunsided/sensor-fusion data set 2).

Axes (set-2 README): x forward, y left, z up; the MPU6050 reads z = -1 g when level, i.e. its
reading points down.  The magnetometer shares the accelerometer's axes: after calibration the
angle between the field and the measured down direction is near-constant (the dip), which no other
axis permutation/sign achieves.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import tomlkit
from viper_calibration.compass import (
    ACC_COLUMNS,
    MagnetometerLog,
    _column,
    _read_table,
    calibrate_compass,
    circular_mean_deg,
    circular_std_deg,
    fit_ellipsoid,
    fit_level_ellipse,
    heading_deg,
    magnitude_spread,
    read_down_csv,
    read_magnetometer_csv,
    wrap_deg,
)

from appliance.cli.main import main
from appliance.drivers.magnetometer import HardSoftIron
from appliance.errors import CalibrationError
from tests.conftest import data_file

SET2 = "imu_magnetometer/sunsided_mpu6050_hmc5883l"


def _log(part: str) -> tuple[MagnetometerLog, np.ndarray]:
    mag = data_file(f"{SET2}/{part}/hmc5883l_compass.csv")
    acc = data_file(f"{SET2}/{part}/mpu6050_accelerometer.csv")
    log = read_magnetometer_csv(mag)
    return log, read_down_csv(acc, log.t_s, measures="down")


@pytest.fixture(scope="module")
def sphere():
    log, down = _log("full-sphere")
    return log, down, calibrate_compass(log, "sphere", down=down)


def _tilt_noise_rad(part: str, t0_s: float = -np.inf, t1_s: float = np.inf) -> float:
    """The accelerometer's tilt error while the board is handled (rad, 1 sigma): the linear
    acceleration beside gravity, whose size shows as the spread of |a| around its mean.  A linear
    acceleration of relative size e tilts the measured down vector by up to e radians."""
    header, rows, source = _read_table(data_file(f"{SET2}/{part}/mpu6050_accelerometer.csv"))
    t = _column(header, rows, "t_s", source)
    a = np.column_stack([_column(header, rows, c, source) for c in ACC_COLUMNS])
    norm = np.linalg.norm(a, axis=1)[(t > t0_s) & (t < t1_s)]
    return float(np.std(norm / np.mean(norm)))


def _dip_deg(field: np.ndarray, down: np.ndarray) -> np.ndarray:
    cos = np.sum(field * down, axis=1) / np.linalg.norm(field, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_full_sphere_field_magnitude_becomes_constant(sphere) -> None:
    log, down, result = sphere
    assert result.n == 8190
    # |B| spread 13.6 % raw -> 0.46 % corrected
    assert result.magnitude_spread_before > 0.12
    assert result.magnitude_spread_after < 0.006
    assert result.magnitude_spread_after == pytest.approx(
        magnitude_spread(result.iron.apply_array(log.field_gauss))
    )
    # A min/max estimate of the hard iron (an independent, cruder method) agrees within 10 mG.
    minmax = (log.field_gauss.max(axis=0) + log.field_gauss.min(axis=0)) / 2.0
    assert np.allclose(result.iron.offset, minmax, atol=0.01)
    assert result.field_gauss == pytest.approx(
        np.mean(np.linalg.norm(result.iron.apply_array(log.field_gauss), axis=1)), rel=1e-3
    )


def test_full_sphere_dip_angle_consistent_with_accelerometer(sphere) -> None:
    log, down, result = sphere
    before = _dip_deg(log.field_gauss, down)
    after = _dip_deg(result.iron.apply_array(log.field_gauss), down)
    # angle down-to-field: 24.6 deg (inclination about 65 deg, central Europe).  After calibration its
    # spread is what the sensors' noise allows: the down vector's tilt error (linear acceleration
    # while handled) and the field's direction error (its relative magnitude residual), in quadrature;
    # 20 % beyond that for what the model leaves out (interpolating the accelerometer to the
    # magnetometer's times, the accelerometer's own noise)
    noise_deg = math.degrees(math.hypot(_tilt_noise_rad("full-sphere"), result.magnitude_spread_after))
    assert np.std(after) < 1.2 * noise_deg
    assert np.std(before) > 2.0 * noise_deg
    assert np.mean(after) == pytest.approx(24.6, abs=1.5)


def test_roll_and_tilt_headings_hold_while_rolling(sphere) -> None:
    """The sphere calibration, applied to the second log: the heading holds through +-90 deg rolls."""
    _, _, result = sphere
    log, down = _log("roll-and-tilt-at-45-90")
    pitch = np.degrees(np.arcsin(np.clip(down[:, 0], -1.0, 1.0)))
    corrected = result.iron.apply_array(log.field_gauss)
    assert magnitude_spread(log.field_gauss) > 0.12 and magnitude_spread(corrected) < 0.02
    means = []
    # rolls about x at the ~45 deg and ~90 deg headings (times read off the log; pitch kept < 30 deg)
    for start_s, end_s in ((6.5, 12.5), (22.0, 28.0)):
        hold = (log.t_s > start_s) & (log.t_s < end_s) & (np.abs(pitch) < 30.0)
        roll = np.degrees(np.arctan2(-down[hold, 1], -down[hold, 2]))
        assert roll.min() < -80.0 and roll.max() > 80.0
        raw = heading_deg(log.field_gauss[hold], down[hold])
        cal = heading_deg(corrected[hold], down[hold])
        # the heading's noise: a tilt error e turns the heading by up to e tan(I) (I the inclination),
        # a field error of relative size s by s / cos(I)
        incl = math.radians(90.0 - float(np.mean(_dip_deg(corrected[hold], down[hold]))))
        tilt = _tilt_noise_rad("roll-and-tilt-at-45-90", start_s, end_s)
        noise_deg = math.degrees(math.hypot(tilt * math.tan(incl), result.magnitude_spread_after / math.cos(incl)))
        assert circular_std_deg(cal) < noise_deg
        assert circular_std_deg(raw) > 2.0 * noise_deg
        means.append(circular_mean_deg(cal))
    # the platform turned by about 45 deg between the two holds
    assert float(wrap_deg(means[1] - means[0])) == pytest.approx(45.0, abs=8.0)


def _level_turn(iron_true: HardSoftIron, n: int = 360, noise: float = 0.0, seed: int = 0):
    """Raw readings of a level turn, through the inverse of a known correction."""
    rng = np.random.default_rng(seed)
    heading = np.linspace(0.0, 360.0, n, endpoint=False)
    h = np.radians(heading)
    horizontal, vertical = 0.21, -0.48
    # body frame x forward, y left, z up: north lies at (cos h, sin h) in (x, y)
    field = np.column_stack([horizontal * np.cos(h), horizontal * np.sin(h), np.full(n, vertical)])
    W = np.asarray(iron_true.matrix).reshape(3, 3)
    raw = field @ np.linalg.inv(W).T + np.asarray(iron_true.offset) + rng.normal(0.0, noise, (n, 3))
    return heading, raw


def test_level_mode_recovers_a_known_horizontal_correction() -> None:
    true = HardSoftIron((-0.01, -0.105, 0.02), (0.98, 0.03, 0.0, 0.03, 0.92, 0.0, 0.0, 0.0, 1.0))
    heading, raw = _level_turn(true, noise=0.001)
    iron, field = fit_level_ellipse(raw)
    assert iron.offset[:2] == pytest.approx(true.offset[:2], abs=5e-4)
    # the corrected radius is the geometric mean of the raw ellipse's semi-axes, 0.21 / sqrt(det W_xy)
    W_xy = np.asarray(true.matrix).reshape(3, 3)[:2, :2]
    assert field == pytest.approx(0.21 / math.sqrt(np.linalg.det(W_xy)), rel=0.01)
    result = calibrate_compass(
        MagnetometerLog(np.arange(len(raw)) * 0.1, raw, reference_heading_deg=heading), "level"
    )
    assert result.heading_error_rms_before_deg > 10.0
    assert result.heading_error_rms_after_deg < 0.5
    assert result.magnitude_spread_after < 0.01


def test_sphere_fit_recovers_synthetic_ellipsoid() -> None:
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    true_offset = np.array([0.05, -0.1, 0.2])
    distortion = np.array([[1.1, 0.05, 0.0], [0.05, 0.9, -0.04], [0.0, -0.04, 1.05]])
    raw = 0.5 * directions @ distortion.T + true_offset
    iron, field = fit_ellipsoid(raw)
    assert iron.offset == pytest.approx(tuple(true_offset), abs=1e-9)
    corrected = iron.apply_array(raw)
    assert np.allclose(np.linalg.norm(corrected, axis=1), field, rtol=1e-9)
    # the correction undoes the distortion up to a rotation and a uniform scale
    P = np.asarray(iron.matrix).reshape(3, 3) @ distortion
    assert np.allclose(P @ P.T / (P @ P.T)[0, 0], np.eye(3), atol=1e-9)


def test_known_bearing_gives_the_mounting_offset() -> None:
    true = HardSoftIron()
    heading, raw = _level_turn(true, n=720)
    t = np.arange(len(raw)) * 0.01
    # the platform faces true bearing 100 deg at the start; magnetic heading there is 0; declination +3
    result = calibrate_compass(
        MagnetometerLog(t, raw), "level", known_bearing_deg=100.0, bearing_window_s=0.0, declination_deg=3.0
    )
    assert result.mounting_offset_deg == pytest.approx(-97.0, abs=0.05)


def test_heading_convention() -> None:
    # level, z up, field north and down: facing north -> 0, facing east (north on the left) -> 90
    assert heading_deg(np.array([[0.2, 0.0, -0.4]]))[0] == pytest.approx(0.0)
    assert heading_deg(np.array([[0.0, 0.2, -0.4]]))[0] == pytest.approx(90.0)
    assert heading_deg(np.array([[0.0, -0.2, -0.4]]))[0] == pytest.approx(270.0)
    # facing east, rolled 90 deg about x, left side down: body y points down, body z points north
    assert heading_deg(np.array([[0.0, 0.4, 0.2]]), np.array([0.0, 1.0, 0.0]))[0] == pytest.approx(90.0)


def test_refusals(tmp_path: Path) -> None:
    heading, raw = _level_turn(HardSoftIron(), noise=0.001)
    with pytest.raises(CalibrationError, match="span a plane"):
        fit_ellipsoid(raw)
    with pytest.raises(CalibrationError, match="at least 20"):
        fit_ellipsoid(raw[:10])
    flat = raw.copy()
    flat[:, 0] = 0.3
    with pytest.raises(CalibrationError, match="mag_x_gauss is constant"):
        fit_level_ellipse(flat)
    with pytest.raises(CalibrationError, match="unvisited"):
        fit_level_ellipse(raw[:180])


def test_cli_writes_compass_table_and_keeps_the_file(tmp_path: Path, capsys) -> None:
    mag = data_file(f"{SET2}/full-sphere/hmc5883l_compass.csv")
    acc = data_file(f"{SET2}/full-sphere/mpu6050_accelerometer.csv")
    cal = tmp_path / "calibration.toml"
    head = "# sensor calibration\n[inclinometer]\npitch_offset_deg = 0.1\nroll_offset_deg = -0.2\n"
    cal.write_text(head)
    argv = ["calibrate", "compass", str(mag), "--accel", str(acc), "--accel-measures", "down"]
    assert main([*argv, "--known-bearing-deg", "0", "--output", str(cal), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["magnitude_spread_after"] < 0.006
    text = cal.read_text()
    assert text.startswith(head)
    table = tomlkit.parse(text).unwrap()["compass"]
    # the file is SI: the offset the fit reports in gauss is written in tesla, the matrix as is
    assert table["hard_iron_offset"] == pytest.approx([v * 1e-4 for v in out["offset"]], rel=1e-6)
    assert table["soft_iron_matrix"] == pytest.approx(out["matrix"], rel=1e-6)
    assert "offset" not in table and "matrix" not in table
    assert len(table["soft_iron_matrix"]) == 9 and table["mounting_offset_deg"] == pytest.approx(
        out["mounting_offset_deg"], abs=1e-4
    )

    before = cal.read_bytes()
    bad = tmp_path / "flat.csv"
    bad.write_text(
        "t_s,mag_x_gauss,mag_y_gauss,mag_z_gauss\n" + "".join(f"{i},0.1,0.2,0.3\n" for i in range(30))
    )
    assert main(["calibrate", "compass", str(bad), "--output", str(cal)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "constant" in err
    assert main(["calibrate", "compass", str(tmp_path / "absent.csv"), "--output", str(cal)]) == 2
    assert "file not found" in capsys.readouterr().err
    assert cal.read_bytes() == before
