"""Procedures on the simulated platform: level guidance, compass fit, GPS gating, capture faults."""

from __future__ import annotations

import dataclasses
import datetime as dt
import math

import numpy as np
import pytest

from appliance.acquisition import procedures as pr
from appliance.acquisition.simulated import SimClock, SimFaults, SimWorld, simulated_platform
from appliance.config import SessionConfig
from appliance.drivers.gps import CovarianceType, FixQuality, GpsFix
from appliance.errors import CalibrationError, DeviceError
from appliance.vision.intrinsics import CameraIntrinsics


def world(**kw):
    base = dict(dem=None, lat_deg=36.6, lon_deg=-84.25, heading_deg=123.0, declination_deg=-6.0, seed=1)
    base.update(kw)
    w = SimWorld.__new__(SimWorld)  # skip the DEM rendering set-up: these tests never capture
    for f in dataclasses.fields(SimWorld):
        if f.name in base:
            setattr(w, f.name, base[f.name])
        elif f.default is not dataclasses.MISSING:
            setattr(w, f.name, f.default)
        else:
            setattr(w, f.name, f.default_factory())  # type: ignore[misc]
    w.rng = np.random.default_rng(w.seed)
    return w


def test_level_guidance_names_the_leg():
    assert pr.level_guidance(0.1, -0.2, 0.5) is None
    assert pr.level_guidance(1.2, 0.3, 0.5).startswith("raise the right leg")
    assert pr.level_guidance(-1.2, 0.3, 0.5).startswith("raise the left leg")
    assert pr.level_guidance(0.2, 0.9, 0.5).startswith("lower the front leg")
    assert pr.level_guidance(0.2, -0.9, 0.5).startswith("raise the front leg")


def test_level_converges_with_the_person_following_guidance():
    w = world(tilt_east_deg=2.0, tilt_north_deg=-1.5)
    p = simulated_platform(w, SimClock())
    res = pr.level(p.tilt, p.leveller, p.clock, SessionConfig(level_tolerance_deg=0.2))
    assert res.status is pr.Status.OK
    assert abs(res.roll_deg) <= 0.2 and abs(res.pitch_deg) <= 0.2
    assert res.instructions and res.instructions == tuple(p.leveller.heard)


def test_level_gives_up_after_timeout_with_reason():
    w = world(tilt_east_deg=3.0)
    p = simulated_platform(w, SimClock())
    res = pr.level(p.tilt, None, p.clock, SessionConfig(level_timeout_s=5.0, level_poll_s=1.0))
    assert res.status is pr.Status.DEGRADED and "not level after 5 s" in res.reason
    assert res.roll_deg is not None and abs(res.roll_deg) > 0.5


def test_hard_soft_iron_fit_recovers_heading_against_the_simulated_truth():
    w = world()
    p = simulated_platform(w, SimClock())
    res = pr.calibrate_compass(p.compass, p.stage, SessionConfig(compass_steps=24))
    assert res.status is pr.Status.OK and res.fit is not None
    assert res.fit.residual < 0.01
    assert res.fit.offset == pytest.approx(w.hard_iron, abs=0.5)
    magnetic_truth = (w.heading_deg - w.declination_deg) % 360
    assert abs((res.platform_heading_deg - magnetic_truth + 180) % 360 - 180) < 0.5


def test_compass_fit_rejected_near_metal():
    w = world(faults=SimFaults(metal_nearby=True))
    p = simulated_platform(w, SimClock())
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
    return np.full((48, 64, 3), 120, np.uint8)


def test_capture_ring_skips_stalled_steps_and_black_frames():
    w = world(faults=SimFaults(stage_stall_at_deg=250.0))
    p = simulated_platform(w, SimClock())
    black = {2, 3}  # the third step gets two black frames in a row
    cam = StubCamera(lambda n: np.zeros((48, 64, 3), np.uint8) if n in black else grey(n))
    seen, problems = [], []
    frames, probs = pr.capture_ring(p.stage, cam, p.tilt, p.clock, SessionConfig(), 100.0, seen.append, problems.append)
    assert [f.stage_deg for f in frames] == [0.0, 40.0, 120.0, 160.0, 200.0, 240.0]
    assert [pb.index for pb in probs] == [2, 7, 8] and "black frame" in probs[0].reason
    assert "stalled at 250.0" in probs[1].reason
    assert frames[1].heading_deg == pytest.approx(140.0) and seen == frames
    roll, pitch = frames[1].roll_deg, frames[1].pitch_deg
    assert math.isfinite(roll) and math.isfinite(pitch)


def test_capture_ring_unplugged_camera_raises_after_delivering_frames():
    w = world()
    p = simulated_platform(w, SimClock())
    seen = []
    with pytest.raises(DeviceError, match="unplugged"):
        pr.capture_ring(
            p.stage, StubCamera(grey, fail_after=3), p.tilt, p.clock, SessionConfig(), 0.0, seen.append, lambda pb: None
        )
    assert [f.index for f in seen] == [0, 1, 2]
