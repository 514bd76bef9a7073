"""``open_devices`` with ``kind = "sim"``: the real drivers on the twins, end to end, with faults."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest

from appliance.cli._platform import open_devices
from appliance.config import Config, from_mapping
from appliance.errors import ConfigError


def sim_config(**faults) -> Config:
    return from_mapping(Config, {
        "platform": {"kind": "sim"},
        "devices": {"camera": {"width": 160, "height": 120}, "stage": {"speed_deg_s": 90.0}},
        "sim": {"time_rate": 20.0, "gps_sigma_m": 1.0, "faults": faults},
    })


def first_fix(p, timeout_s: float = 3.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        fixes = p.gps.poll()
        if fixes:
            return fixes[-1]
    raise AssertionError("no GPS fix from the twin")


def test_sim_platform_end_to_end() -> None:
    with open_devices(sim_config()) as p:
        w = p.world
        fix = first_fix(p)
        dn = math.radians(fix.lat_deg - w.lat_deg) * 6_371_008.8
        assert abs(dn) < 6.0 and fix.alt_msl_m == pytest.approx(w.alt_msl_m, abs=0.01)
        assert 236.0 <= w.ground_elevation_m <= 1076.0  # within the demo DEM's range

        reached = p.stage.move_to(90.0)
        assert reached == pytest.approx(90.0, abs=0.03) and w.stage_deg == pytest.approx(90.0, abs=0.03)
        reached = p.stage.move_to(270.0)  # past 180: the signed range of the unit
        assert reached == pytest.approx(270.0, abs=0.03)

        tilt = p.tilt.read_tilt()
        pitch, roll = w.head_tilt()
        assert tilt.pitch_deg == pytest.approx(pitch, abs=0.3) and tilt.roll_deg == pytest.approx(roll, abs=0.3)

        field = p.compass.read_field()
        assert 2e-5 < math.sqrt(field.x**2 + field.y**2 + field.z**2) < 8e-5  # tesla, Earth's field + iron
        p.compass.position = fix
        h = p.heading.read_heading()
        assert h.model == "WMM-2025" and h.declination_deg == pytest.approx(w.declination_deg, abs=0.01)
        # uncalibrated (identity) compass: the iron biases the heading, but only by degrees
        assert abs((h.true_deg - w.head_heading_deg + 180.0) % 360.0 - 180.0) < 15.0

        frame = p.camera.capture()
        assert frame.image.shape == (120, 160, 3) and frame.image.dtype == np.uint8
        sky, ground = frame.image[:10].mean(), frame.image[-10:].mean()
        assert sky != pytest.approx(ground, abs=5.0)  # a skyline scene, not a flat frame


def test_missed_step_and_absent_inclinometer_are_warnings(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        with open_devices(sim_config(stage_miss_step_every=1, inclinometer_absent=True)) as p:
            assert p.tilt is None
            reached = p.stage.move_to(40.0)
            assert abs(reached - 40.0) > 0.3  # the stage tells where it really stopped
            assert p.stage.unit.missed_moves == 1
    assert "missed steps" in caplog.text and "inclinometer absent" in caplog.text


def test_stuck_compass_raises_after_repeats(caplog: pytest.LogCaptureFixture) -> None:
    from appliance.errors import DeviceError

    with open_devices(sim_config(compass_stuck=True)) as p:
        with caplog.at_level(logging.WARNING), pytest.raises(DeviceError, match="stuck"):
            for _ in range(5):
                p.compass.read_field()
    assert "identical readings" in caplog.text


def test_unknown_compass_kind_is_a_config_error() -> None:
    # refused where the configuration is read, before any device is opened
    with pytest.raises(ConfigError, match="devices.compass.kind: expected 'hmc5883l' or 'nmea', got 'fluxgate'"):
        from_mapping(Config, {"devices": {"compass": {"kind": "fluxgate"}}})


def test_nmea_compass_as_heading_and_inclinometer() -> None:
    cfg = from_mapping(Config, {
        "devices": {"compass": {"kind": "nmea"}, "inclinometer": {"kind": "nmea"}},
        "sim": {"time_rate": 20.0},
    })
    from appliance.sim.platform import open_sim_platform

    with open_sim_platform(cfg, with_camera=False) as p:
        w = p.world
        end = time.monotonic() + 2.0
        h = tilt = None
        while time.monotonic() < end and (h is None or tilt is None):
            try:
                h = p.heading.read_heading()
                tilt = p.tilt.read_tilt()
            except Exception:  # noqa: BLE001 - no sentence yet
                time.sleep(0.05)
        assert h is not None and tilt is not None
        assert h.magnetic_deg == pytest.approx((w.head_heading_deg - w.declination_deg) % 360.0, abs=0.1)
        pitch, roll = w.head_tilt()
        assert tilt.pitch_deg == pytest.approx(pitch, abs=0.01) and tilt.roll_deg == pytest.approx(roll, abs=0.01)
