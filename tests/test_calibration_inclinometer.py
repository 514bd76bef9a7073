"""Inclinometer offsets by the reversal method: a simulated stage with known tilt and sensor offsets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tomlkit
from hypothesis import given
from hypothesis import strategies as st
from viper_calibration.inclinometer import ReversalReadings, calibrate_reversal, parse_reversal_csv

from appliance.cli.main import main
from appliance.errors import CalibrationError, InputError

finite = st.floats(-5.0, 5.0, allow_nan=False)


def _stage(tilt, offset, n=5, noise=0.0, seed=0) -> ReversalReadings:
    rng = np.random.default_rng(seed)
    stage = np.array([0.0] * n + [180.0] * n)
    sign = np.where(stage == 0.0, 1.0, -1.0)[:, None]
    readings = sign * np.asarray(tilt) + np.asarray(offset) + rng.normal(0.0, noise, (2 * n, 2))
    return ReversalReadings(stage, readings)


@given(tx=finite, ty=finite, ox=finite, oy=finite)
def test_recovers_offsets_and_tilt(tx: float, ty: float, ox: float, oy: float) -> None:
    readings = _stage((tx, ty), (ox, oy), n=3)
    if np.ptp(readings.tilt_deg[:, 0]) == 0.0 or np.ptp(readings.tilt_deg[:, 1]) == 0.0:
        return  # zero tilt: the columns are constant and are refused (tested below)
    result = calibrate_reversal(readings)
    assert result.offset_deg == pytest.approx((ox, oy), abs=1e-9)
    assert result.tilt_at_zero_deg == pytest.approx((tx, ty), abs=1e-9)


def test_averages_noisy_readings_and_accepts_near_angles() -> None:
    readings = _stage((0.3, -0.2), (0.05, 0.12), n=200, noise=0.01, seed=2)
    stage = readings.stage_deg + np.tile([0.5, -0.5], 200)  # 0.5 deg stage errors, 359.5 wraps to 0
    result = calibrate_reversal(ReversalReadings(stage, readings.tilt_deg))
    # standard error of the mean of 400 readings of sd 0.01: 0.0005 deg
    assert result.offset_deg == pytest.approx((0.05, 0.12), abs=0.002)
    assert result.tilt_at_zero_deg == pytest.approx((0.3, -0.2), abs=0.002)
    assert result.readings_at_0 == 200 and result.readings_at_180 == 200


def test_refusals() -> None:
    good = _stage((0.3, -0.2), (0.05, 0.12))
    with pytest.raises(CalibrationError, match="only at stage 0"):
        calibrate_reversal(ReversalReadings(good.stage_deg[:5], good.tilt_deg[:5]))
    with pytest.raises(InputError, match="stage angle 90.0 deg is neither"):
        calibrate_reversal(ReversalReadings(np.array([0.0, 90.0, 180.0]), np.ones((3, 2))))
    with pytest.raises(CalibrationError, match="tilt_y_deg is constant"):
        calibrate_reversal(
            ReversalReadings(good.stage_deg, np.column_stack([good.tilt_deg[:, 0], np.ones(10)]))
        )
    with pytest.raises(InputError, match="header"):
        parse_reversal_csv(b"angle,x,y\n0,1,2\n")
    with pytest.raises(InputError, match=r":2: tilt_x_deg 'a' is not a number"):
        parse_reversal_csv(b"stage_deg,tilt_x_deg,tilt_y_deg\n0,a,2\n")


def test_cli_writes_offsets_keeping_other_tables(tmp_path: Path, capsys) -> None:
    csv = tmp_path / "reversal.csv"
    csv.write_text(
        "stage_deg,tilt_x_deg,tilt_y_deg\n0,0.35,-0.08\n0,0.37,-0.10\n180,-0.25,0.32\n180,-0.23,0.30\n"
    )
    cal = tmp_path / "calibration.toml"
    head = "[compass]\nhard_iron_offset = [0.0, 0.0, 0.0]  # tesla\n"
    cal.write_text(head)
    assert main(["calibrate", "inclinometer", str(csv), "--output", str(cal), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # x: (0.36 + -0.24) / 2 = 0.06, tilt 0.30; y: (-0.09 + 0.31) / 2 = 0.11, tilt -0.20
    assert out["offset_x_deg"] == pytest.approx(0.06) and out["offset_y_deg"] == pytest.approx(0.11)
    assert out["tilt_x_at_zero_deg"] == pytest.approx(0.30) and out["tilt_y_at_zero_deg"] == pytest.approx(
        -0.20
    )
    text = cal.read_text()
    assert text.startswith(head) and "[inclinometer]" in text
    # the driver's keys: x axis = pitch, y axis = roll
    table = tomlkit.parse(text).unwrap()["inclinometer"]
    assert table == pytest.approx({"pitch_offset_deg": 0.06, "roll_offset_deg": 0.11})

    before = cal.read_bytes()
    csv.write_text("stage_deg,tilt_x_deg,tilt_y_deg\n0,0.35,-0.08\n0,0.37,-0.10\n")
    assert main(["calibrate", "inclinometer", str(csv), "--output", str(cal)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "180" in err
    assert cal.read_bytes() == before
