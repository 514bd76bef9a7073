"""Procedures on the simulated platform (the real drivers over the twins): level guidance, compass
fit, GPS gating, capture faults."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest

from appliance.acquisition import procedures as pr
from appliance.acquisition.platform import platform_of
from appliance.config import Config, SessionConfig, from_mapping
from appliance.drivers.gps import CovarianceType, FixQuality, GpsFix
from appliance.errors import CalibrationError, DeviceError
from appliance.sim.platform import open_sim_platform
from appliance.vision.intrinsics import CameraIntrinsics


def sim_config(sim: dict | None = None, **faults) -> Config:
    """The twins without a camera or DEM (ground elevation given), fast simulated time."""
    base = {"time_rate": 50.0, "ground_elevation_m": 400.0, "heading_deg": 123.0, "tilt_north_deg": 0.0,
            "tilt_east_deg": 0.0, "faults": faults}
    base.update(sim or {})
    return from_mapping(Config, {"platform": {"kind": "sim"}, "devices": {"stage": {"speed_deg_s": 120.0}},
                                 "sim": base})


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_level_guidance_names_the_leg():
    assert pr.level_guidance(0.1, -0.2, 0.5) is None
    assert pr.level_guidance(1.2, 0.3, 0.5).startswith("raise the right leg")
    assert pr.level_guidance(-1.2, 0.3, 0.5).startswith("raise the left leg")
    assert pr.level_guidance(0.2, 0.9, 0.5).startswith("lower the front leg")
    assert pr.level_guidance(0.2, -0.9, 0.5).startswith("raise the front leg")


def test_level_converges_with_the_person_following_guidance():
    with open_sim_platform(sim_config({"tilt_east_deg": 2.0, "tilt_north_deg": -1.5}), with_camera=False) as d:
        p = platform_of(d)
        res = pr.level(p.tilt, p.leveller, p.clock, SessionConfig(level_tolerance_deg=0.2, level_poll_s=0.2))
        true_pitch, true_roll = d.world.head_tilt()
    assert res.status is pr.Status.OK
    assert abs(res.roll_deg) <= 0.2 and abs(res.pitch_deg) <= 0.2
    # the accelerometer's reading agrees with the world's true tilt (noise 0.004 g over 16 samples)
    assert res.roll_deg == pytest.approx(true_roll, abs=0.1) and res.pitch_deg == pytest.approx(true_pitch, abs=0.1)
    assert res.instructions and res.instructions == tuple(d.leveller.heard)


def test_level_gives_up_after_timeout_with_reason():
    with open_sim_platform(sim_config({"tilt_east_deg": 3.0}), with_camera=False) as d:
        p = platform_of(d)
        res = pr.level(p.tilt, None, p.clock, SessionConfig(level_timeout_s=5.0, level_poll_s=1.0))
    assert res.status is pr.Status.DEGRADED and "not level after 5 s" in res.reason
    assert res.roll_deg is not None and math.hypot(res.roll_deg, res.pitch_deg) > 2.5


def test_hard_soft_iron_fit_recovers_heading_against_the_simulated_truth():
    with open_sim_platform(sim_config(), with_camera=False) as d:
        p = platform_of(d)
        res = pr.calibrate_compass(p.compass, p.stage, SessionConfig(compass_steps=24))
        w = d.world
    assert res.status is pr.Status.OK and res.fit is not None
    assert res.fit.residual < 0.01
    # the fitted hard iron is the simulated one, seen in the head's frame (x forward, y right)
    assert res.fit.offset[0] == pytest.approx(w.hard_iron_t[0], abs=3e-7)
    assert res.fit.offset[1] == pytest.approx(-w.hard_iron_t[1], abs=3e-7)
    magnetic_truth = (w.heading_deg - w.declination_deg) % 360
    assert angle_diff(res.platform_heading_deg, magnetic_truth) < 0.5


def test_compass_fit_rejected_near_metal():
    with open_sim_platform(sim_config(compass_metal_nearby=True), with_camera=False) as d:
        p = platform_of(d)
        res = pr.calibrate_compass(p.compass, p.stage, SessionConfig())
    assert res.status is pr.Status.FAILED and "metal" in res.reason and res.fit.residual > 0.05


def test_fit_refuses_too_few_points():
    with pytest.raises(CalibrationError, match="at least 6"):
        pr.fit_hard_soft_iron(np.ones(3), np.ones(3))


def fix(lat, lon, quality=FixQuality.GPS, hdop=1.0):
    utc = dt.datetime(2025, 6, 1, tzinfo=dt.timezone.utc)
    return GpsFix(utc, utc.time(), lat, lon, 100.0, None, quality, 8, hdop, None, CovarianceType.UNKNOWN, 0)


def test_average_fixes_gates_quality_and_hdop():
    good = [fix(36.0 + d * 1e-5, -84.0) for d in (-1, 0, 1, 0)]
    bad = [fix(37.0, -84.0, FixQuality.INVALID), fix(37.0, -84.0, hdop=9.0)]
    res = pr.average_fixes(good + bad, max_hdop=3.0, min_fixes=3)
    assert res.status is pr.Status.OK and (res.used, res.rejected) == (4, 2)
    assert res.lat_deg == pytest.approx(36.0) and res.fix_type == "GPS"
    # spread: sample std of north offsets (-1.11, 0, 1.11, 0 m) = 0.908 m
    assert res.spread_m == pytest.approx(0.9078, abs=1e-3)
    assert res.sigma_m == pytest.approx(res.spread_m / 2)
    few = pr.average_fixes(bad, 3.0, 3)
    assert few.status is pr.Status.DEGRADED and "0 of 2" in few.reason and few.lat_deg is None


def test_capture_angles_cover_the_circle_with_overlap():
    a = pr.capture_angles(60.0, 0.3)
    assert len(a) == 9 and a[1] == pytest.approx(40.0)
    assert 360 / len(a) <= 60 * 0.7 + 1e-9


class StubCamera:
    def __init__(self, frames, fail_after=None):
        self.intrinsics = CameraIntrinsics.from_fov(64, 48, 60.0)
        self.frames, self.n, self.fail_after = frames, 0, fail_after

    def capture(self):
        if self.fail_after is not None and self.n >= self.fail_after:
            raise DeviceError("camera: /dev/video0 disappeared (unplugged?)")
        img = self.frames(self.n)
        self.n += 1
        from appliance.acquisition.platform import Frame

        return Frame(self.n, img)


def grey(n):
    """A plain frame with some structure (a vertical gradient): not black, saturated or featureless."""
    return np.repeat(np.linspace(100, 140, 48).astype(np.uint8)[:, None, None], 64, axis=1).repeat(3, axis=2)


def test_capture_ring_skips_stalled_steps_and_black_frames():
    # an obstacle stops the pan axis at 250 deg (-110 signed): the moves 160 -> 200 (the PTU turns
    # through 0, its range being -180..180) and 240 -> 280 end there
    with open_sim_platform(sim_config(stage_stall_at_deg=-110.0), with_camera=False) as d:
        p = platform_of(d)
        black = {2, 3}  # the third step gets two black frames in a row
        cam = StubCamera(lambda n: np.zeros((48, 64, 3), np.uint8) if n in black else grey(n))
        seen, problems = [], []
        frames, probs = pr.capture_ring(p.stage, cam, p.tilt, p.clock, SessionConfig(settle_s=0.1), 100.0,
                                        seen.append, problems.append)
    assert [f.stage_deg for f in frames] == pytest.approx([0.0, 40.0, 120.0, 160.0, 240.0, 320.0], abs=0.02)
    assert [pb.index for pb in probs] == [2, 5, 7] and "black frame" in probs[0].reason
    assert "stalled at 250.0" in probs[1].reason and "stalled at 250.0" in probs[2].reason
    assert frames[1].heading_deg == pytest.approx(140.0, abs=0.02) and seen == frames
    roll, pitch = frames[1].roll_deg, frames[1].pitch_deg
    assert abs(roll) < 0.2 and abs(pitch) < 0.2  # a level tripod


def test_capture_ring_skips_over_exposed_and_featureless_frames_twice_and_says_why():
    with open_sim_platform(sim_config(), with_camera=False) as d:
        p = platform_of(d)
        white = {0, 1}  # the first step: over-exposed twice
        flat = {3, 4}  # the second step's frames: featureless (a fogged lens) twice
        cam = StubCamera(lambda n: np.full((48, 64, 3), 255, np.uint8) if n in white else
                         np.full((48, 64, 3), 128, np.uint8) if n in flat else grey(n))
        frames, probs = pr.capture_ring(p.stage, cam, p.tilt, p.clock, SessionConfig(settle_s=0.1), 0.0,
                                        lambda f: None, lambda pb: None)
    assert [pb.index for pb in probs] == [0, 2]
    assert probs[0].reason == "over-exposed frame (100% of pixels saturated) twice"
    assert probs[1].reason == "featureless frame (grey level std 0.00) twice"
    assert [f.index for f in frames] == [1, 3, 4, 5, 6, 7, 8]


def test_capture_ring_unplugged_camera_raises_after_delivering_frames():
    with open_sim_platform(sim_config(), with_camera=False) as d:
        p = platform_of(d)
        seen = []
        with pytest.raises(DeviceError, match="unplugged"):
            pr.capture_ring(p.stage, StubCamera(grey, fail_after=3), p.tilt, p.clock, SessionConfig(settle_s=0.1),
                            0.0, seen.append, lambda pb: None)
    assert [f.index for f in seen] == [0, 1, 2]
