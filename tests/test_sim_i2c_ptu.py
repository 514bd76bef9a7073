"""I2C chip twins (HMC5883L, ADXL345) read by the real drivers, and the PTU twin over a real pty."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

import numpy as np
import pytest

from appliance.drivers.accelerometer import Adxl345, average_tilt, calibrate_level_offset, decode_adxl345_data
from appliance.drivers.attitude import tilt_compensated_heading
from appliance.drivers.magnetometer import HardSoftIron, Hmc5883l, decode_hmc5883l_data
from appliance.drivers.ptu import PanTiltUnit, parse_reply
from appliance.drivers.transport import open_serial
from appliance.errors import CalibrationError, DeviceError, ProtocolError
from appliance.sim.i2c_chips import FakeI2cBus, SimAdxl345, SimHmc5883l
from appliance.sim.ptu_twin import PtuTwin
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimClock, SimWorld

START = dt.datetime(2026, 6, 1, 12, tzinfo=dt.timezone.utc)
SOFT = (1.08, 0.03, 0.0, 0.03, 0.94, 0.0, 0.0, 0.0, 1.0)
HARD = (8e-6, -5e-6, 3e-6)


def world(**kw) -> SimWorld:
    args = dict(heading_deg=30.0, tilt_north_deg=1.0, tilt_east_deg=-0.5, hard_iron_t=HARD, soft_iron=SOFT,
                clock=SimClock(START, 1000.0))
    args.update(kw)
    return SimWorld(36.6, -84.25, 500.0, **args)


def perfect_calibration() -> HardSoftIron:
    inv = np.linalg.inv(np.array(SOFT).reshape(3, 3))
    return HardSoftIron(HARD, tuple(float(v) for v in inv.ravel()))  # type: ignore[arg-type]


def test_hard_soft_iron_apply_inverts_the_distortion() -> None:
    cal = perfect_calibration()
    true = (2e-5, -1e-5, -4e-5)
    raw = tuple(np.array(SOFT).reshape(3, 3) @ np.array(true) + np.array(HARD))
    assert cal.apply(raw) == pytest.approx(true, abs=1e-12)
    with pytest.raises(CalibrationError):
        HardSoftIron((0.0, 0.0), (1.0,) * 9)  # type: ignore[arg-type]


@pytest.mark.parametrize("stage_deg", [0.0, 75.0, 190.0, 300.0])
def test_compass_heading_through_the_i2c_twin(stage_deg: float) -> None:
    w = world()
    w.stage_deg = stage_deg
    bus = FakeI2cBus()
    bus.attach(0x1E, SimHmc5883l(w, noise_t=0.0))
    bus.attach(0x53, SimAdxl345(w, noise_g=0.003))
    mag, acc = Hmc5883l(bus), Adxl345(bus)
    tilt = acc.read_tilt(samples=64)
    pitch, roll = w.head_tilt()
    assert tilt.pitch_deg == pytest.approx(pitch, abs=0.15) and tilt.roll_deg == pytest.approx(roll, abs=0.15)
    heading_mag = tilt_compensated_heading(perfect_calibration().apply(mag.read_tesla()), tilt.pitch_deg,
                                           tilt.roll_deg)
    expected = (w.head_heading_deg - w.declination_deg) % 360.0
    assert (heading_mag - expected + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.5)


def iron_bias_deg(world: SimWorld, heading_mag_deg: float) -> float:
    """The heading error of an uncalibrated compass from the iron alone, on a level head: the
    horizontal field, ``B_h (cos h, sin h)`` on the head's forward and left axes, through the soft
    iron's horizontal block plus the hard iron's horizontal part, read back as a heading."""
    h = np.radians(heading_mag_deg)
    b_h = np.hypot(world.field_world_t[0], world.field_world_t[1])
    raw = np.array(SOFT).reshape(3, 3)[:2, :2] @ (b_h * np.array([np.cos(h), np.sin(h)])) + np.array(HARD[:2])
    return (float(np.degrees(np.arctan2(raw[1], raw[0]))) - heading_mag_deg + 180.0) % 360.0 - 180.0


def test_uncalibrated_compass_is_biased_by_the_iron() -> None:
    w = world()
    bus = FakeI2cBus()
    bus.attach(0x1E, SimHmc5883l(w, noise_t=0.0))
    mag = Hmc5883l(bus)
    errors, expected = [], []
    for stage in range(0, 360, 30):
        w.stage_deg = float(stage)
        pitch, roll = w.head_tilt()
        uncal = tilt_compensated_heading(mag.read_tesla(), pitch, roll)
        heading_mag = (w.head_heading_deg - w.declination_deg) % 360.0
        errors.append((uncal - heading_mag + 180.0) % 360.0 - 180.0)
        expected.append(iron_bias_deg(w, heading_mag))
    # sign and size at each heading; 0.75 deg for what the level model leaves out: the head's 1 deg
    # tilt carrying the vertical field through the iron, and the chip's 0.09 uT steps
    assert errors == pytest.approx(expected, abs=0.75)
    # the hard iron (9.4 uT across a 21.8 uT horizontal field) swings the heading by more than 20 deg each way
    assert min(expected) < -20.0 and max(expected) > 20.0


def test_wrong_chip_id_and_absent_chip_are_device_errors() -> None:
    w = world()
    bus = FakeI2cBus()
    bus.attach(0x53, SimAdxl345(w, devid=0x33))
    with pytest.raises(DeviceError, match="DEVID 0x33"):
        Adxl345(bus)
    with pytest.raises(DeviceError, match="I2C transfer failed"):
        Hmc5883l(bus)  # nothing at 0x1E


def test_register_decoding_matches_datasheet_examples() -> None:
    # HMC5883L: X=0x0100, Z=0xFF00, Y=0x0080 at gain 1 (1090 LSB/gauss)
    x, y, z = decode_hmc5883l_data([0x01, 0x00, 0xFF, 0x00, 0x00, 0x80], 1090.0)
    assert (x, y, z) == pytest.approx((256 / 1090 * 1e-4, 128 / 1090 * 1e-4, -256 / 1090 * 1e-4))
    with pytest.raises(DeviceError, match="overflow"):
        decode_hmc5883l_data([0xF0, 0x00, 0, 0, 0, 0], 1090.0)
    # ADXL345: 256 LSB on Z = 0.9984 g
    assert decode_adxl345_data([0, 0, 0, 0, 0x00, 0x01]) == pytest.approx((0.0, 0.0, 256 * 0.0039))


def test_level_offset_calibration_and_stuck_accelerometer(caplog: pytest.LogCaptureFixture) -> None:
    w = world(tilt_north_deg=0.0, tilt_east_deg=0.0)
    bus = FakeI2cBus()
    bus.attach(0x53, SimAdxl345(w, noise_g=0.002))
    acc = Adxl345(bus)
    offset = calibrate_level_offset([acc.read_g() for _ in range(64)])
    assert abs(offset.pitch_deg) < 0.2 and abs(offset.roll_deg) < 0.2
    assert acc.read_tilt(32, offset).pitch_deg == pytest.approx(0.0, abs=0.2)
    with pytest.raises(DeviceError, match="not at rest"):
        average_tilt([(0.0, 0.0, 0.0001)])
    stuck_bus = FakeI2cBus()
    stuck_bus.attach(0x53, SimAdxl345(w, stuck=True))
    stuck = Adxl345(stuck_bus)
    with caplog.at_level(logging.WARNING), pytest.raises(DeviceError, match="stuck"):
        stuck.read_tilt(8)
    assert "identical readings" in caplog.text


def ptu_pair(tmp_path: Path, **kw) -> tuple[PtuTwin, PtyPort, PanTiltUnit]:
    w = world()
    port = PtyPort(tmp_path / "ptu")
    twin = PtuTwin(w, port, **kw)
    twin.start()
    unit = PanTiltUnit(open_serial(str(port.path), 9600, 0.05), timeout_s=0.5, move_timeout_s=2.0)
    return twin, port, unit


def test_ptu_moves_and_reports_limits(tmp_path: Path) -> None:
    twin, port, unit = ptu_pair(tmp_path)
    try:
        assert unit.limits.arcsec_per_position == pytest.approx(92.5714)
        assert (unit.limits.min_position, unit.limits.max_position) == (-3090, 3090)
        unit.set_speed_deg_s(40.0)
        reached = unit.move_to_deg(45.0)
        assert reached == pytest.approx(45.0, abs=92.5714 / 3600)
        assert twin.world.stage_deg == pytest.approx(reached)
        assert unit.position_deg() == pytest.approx(reached)
        with pytest.raises(DeviceError, match="outside limits"):
            unit.move_to_deg(100.0)
        with pytest.raises(DeviceError, match="refused 'PPX'"):
            unit.command("PPX")
    finally:
        unit.close()
        twin.stop()
        port.close()


def test_ptu_missed_step_is_detected_and_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    twin, port, unit = ptu_pair(tmp_path, miss_step_every=2)
    try:
        unit.move_to_deg(10.0)
        with caplog.at_level(logging.WARNING), pytest.raises(DeviceError, match="missed steps"):
            unit.move_to_deg(20.0)
        assert unit.missed_moves == 1 and "missed steps" in caplog.text
        unit.move_to_deg(30.0)  # the next move is fine again
    finally:
        unit.close()
        twin.stop()
        port.close()


def test_ptu_that_never_answers_times_out(tmp_path: Path) -> None:
    w = world()
    port = PtyPort(tmp_path / "ptu")
    twin = PtuTwin(w, port, silent=True)
    twin.start()
    try:
        with pytest.raises(DeviceError, match="no answer within 0.2 s"):
            PanTiltUnit(open_serial(str(port.path), 9600, 0.05), timeout_s=0.2)
    finally:
        twin.stop()
        port.close()


def test_ptu_reply_parser() -> None:
    assert parse_reply(b"* 1200").value == "1200"
    assert not parse_reply(b"!P").ok
    with pytest.raises(ProtocolError):
        parse_reply(b"\x8f\x02garbage")


def test_compass_drift_fault_turns_the_heading_with_time() -> None:
    w = world(clock=SimClock(START, 1000.0))  # 1000 simulated seconds per real second
    bus = FakeI2cBus()
    chip = SimHmc5883l(w, noise_t=0.0, drift_deg_per_s=0.5)
    bus.attach(0x1E, chip)
    mag = Hmc5883l(bus)
    pitch, roll = w.head_tilt()
    cal = perfect_calibration()
    h0 = tilt_compensated_heading(cal.apply(mag.read_tesla()), pitch, roll)
    import time

    time.sleep(0.02)  # >= 20 simulated seconds: >= 10 degrees of drift
    h1 = tilt_compensated_heading(cal.apply(mag.read_tesla()), pitch, roll)
    assert abs((h1 - h0 + 180.0) % 360.0 - 180.0) > 5.0
