"""The MAVLink protocol layer, pure: frames encoded by pymavlink and decoded by pymavlink's own parser
become readings; the link's fault rules; stops and their sigma from local positions; the GPS_INPUT
and VISION_POSITION_ESTIMATE fields of an estimate."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from appliance.config import OdometryDeviceConfig, load_config  # noqa: E402
from appliance.drivers.autopilot import PositionFix  # noqa: E402
from appliance.drivers.mavlink import (  # noqa: E402
    Attitude,
    FaultKind,
    GlobalPosition,
    Heartbeat,
    LinkMonitor,
    LocalPosition,
    reading_of,
)
from appliance.drivers.mavlink_odometry import StopRules, StopTracker, displacement_sigma_m  # noqa: E402
from appliance.drivers.mavlink_output import (  # noqa: E402
    FIX_3D,
    FIX_NONE,
    IGNORE_HORIZONTAL_ACCURACY,
    gps_input_fields,
    gps_time,
    horizontal_accuracy_m,
    north_east_m,
    origin_of,
    vision_position_fields,
)
from appliance.errors import ConfigError, ProtocolError  # noqa: E402

NAN = float("nan")


class _Frames:
    def __init__(self):
        self.data = b""

    def write(self, b):
        self.data += bytes(b)


def wire(encode, system=1, component=1):
    """One frame encoded by pymavlink and decoded back by pymavlink's parser."""
    out = _Frames()
    mav = mavlink2.MAVLink(out, srcSystem=system, srcComponent=component)
    mav.send(encode(mav))
    (msg,) = mavlink2.MAVLink(None).parse_buffer(out.data)
    return msg


def test_readings_from_the_wire():
    p = reading_of(wire(lambda m: m.local_position_ned_encode(1234, 10.5, -3.25, 0.5, 0.3, 0.4, 0.0)), 7)
    assert p == LocalPosition(1234, 10.5, -3.25, 0.5, pytest.approx(0.5), receive_time_ns=7)
    # yaw -90 deg (west) is a heading of 270 clockwise from north
    a = reading_of(wire(lambda m: m.attitude_encode(99, math.radians(2.0), math.radians(-1.0), -math.pi / 2,
                                                    0, 0, 0)))
    assert isinstance(a, Attitude)
    assert (a.roll_deg, a.pitch_deg, a.heading_deg) == pytest.approx((2.0, -1.0, 270.0), abs=1e-4)
    g = reading_of(wire(lambda m: m.global_position_int_encode(5, 366000000, -842500000, 512345, 0, 0, 0, 0,
                                                               65535)))
    assert g == GlobalPosition(5, pytest.approx(36.6), pytest.approx(-84.25), pytest.approx(512.345), None)
    # ArduPilot Rover armed in HOLD (custom mode 4); PX4's modes decode too
    h = reading_of(wire(lambda m: m.heartbeat_encode(10, 3, 128 | 1, 4, 4)))
    assert h == Heartbeat(1, True, "HOLD", 3, 10)
    h = reading_of(wire(lambda m: m.heartbeat_encode(10, 3, 1, 0, 3)))
    assert isinstance(h, Heartbeat) and not h.armed and h.mode == "MANUAL"
    assert reading_of(wire(lambda m: m.system_time_encode(0, 5))) is None


def test_odometry_carries_its_covariance_and_must_be_in_ned():
    cov = [NAN] * 21
    cov[0], cov[6] = 4.0, 9.0
    msg = wire(lambda m: m.odometry_encode(2_000_000, 1, 12, 1.0, 2.0, 0.0, [1, 0, 0, 0], 0.1, 0.0, 0.0,
                                           0, 0, 0, cov, [NAN] * 21, 3))
    p = reading_of(msg)
    assert (p.time_boot_ms, p.north_m, p.east_m, p.var_north_m2, p.var_east_m2, p.reset_counter) == \
        (2000, 1.0, 2.0, 4.0, 9.0, 3)
    # unknown covariance: NaN first element
    msg = wire(lambda m: m.odometry_encode(1000, 1, 12, 1.0, 2.0, 0.0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0,
                                           [NAN] * 21, [NAN] * 21, 0))
    assert reading_of(msg).var_north_m2 is None
    msg = wire(lambda m: m.odometry_encode(1000, 20, 12, 1.0, 2.0, 0.0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0,
                                           [NAN] * 21, [NAN] * 21, 0))
    with pytest.raises(ProtocolError, match="frame_id 20 is not MAV_FRAME_LOCAL_NED"):
        reading_of(msg)


@pytest.mark.parametrize("encode,fields", [
    (lambda m: m.local_position_ned_encode(10, NAN, 1.0, 0.0, 0, 0, 0), "x"),
    (lambda m: m.attitude_encode(10, 0.0, NAN, NAN, 0, 0, 0), "pitch, yaw"),
])
def test_nan_fields_are_rejected_naming_them(encode, fields):
    with pytest.raises(ProtocolError, match=f"{fields} not finite"):
        reading_of(wire(encode))


def _monitor():
    return LinkMonitor(system_id=1, component_id=1, reorder_window_ms=2000, link_timeout_ns=5_000_000_000)


def test_link_rules_foreign_system_other_component_out_of_order_and_reboot():
    mon = _monitor()
    assert mon.check(1, 1, "ATTITUDE", 10_000, 0) == (True, None)
    taken, fault = mon.check(7, 1, "ATTITUDE", 20_000, 0)
    assert not taken and fault.kind is FaultKind.FOREIGN_SYSTEM and "system 7" in fault.detail
    assert mon.check(1, 154, "ATTITUDE", 20_000, 0) == (False, None) and mon.other_components == 1
    # 500 ms back: a late message, ignored; another type's stream is its own
    taken, fault = mon.check(1, 1, "ATTITUDE", 9_500, 0)
    assert not taken and fault.kind is FaultKind.OUT_OF_ORDER
    assert mon.check(1, 1, "LOCAL_POSITION_NED", 9_400, 0) == (True, None)
    assert mon.boots == 0
    # 9.9 s back: the autopilot restarted; every stream starts again
    taken, fault = mon.check(1, 1, "ATTITUDE", 100, 0)
    assert taken and fault.kind is FaultKind.REBOOT and mon.boots == 1
    assert mon.check(1, 1, "LOCAL_POSITION_NED", 120, 0) == (True, None)
    assert mon.counts == {"message from another system id": 1, "out-of-order message": 1, "autopilot reboot": 1}


def test_a_silent_link_is_one_fault_per_silence():
    mon = _monitor()
    assert mon.silence(4_000_000_000) is None
    f = mon.silence(6_000_000_000)
    assert f.kind is FaultKind.LINK_SILENT and "6.0 s" in f.detail
    assert mon.silence(9_000_000_000) is None  # the same silence
    mon.check(1, 1, "HEARTBEAT", None, 9_500_000_000)
    assert mon.silence(14_000_000_000) is None
    assert mon.silence(15_000_000_000) is not None and mon.counts["link silent"] == 2


def _track(tracker, samples):
    """Feed (t_ms, north, east, speed[, var]) samples; the reports."""
    out = []
    for s in samples:
        var = s[4] if len(s) > 4 else None
        rep, _ = tracker.update(LocalPosition(s[0], s[1], s[2], 0.0, s[3], var, var))
        if rep is not None:
            out.append(rep)
    return out


def _leg(t0, start, end, var0=None, var1=None, still_s=4):
    """Samples of a leg from start to end (north, east) at 1 Hz, then still for ``still_s`` s."""
    s = [(t0, *start, 0.0, var0)]
    for k in range(1, 11):
        f = k / 10
        v = None if var0 is None else var0 + f * (var1 - var0)
        s.append((t0 + 1000 * k, start[0] + f * (end[0] - start[0]), start[1] + f * (end[1] - start[1]), 5.0, v))
    s += [(t0 + 11000 + 1000 * k, *end, 0.0, var1) for k in range(still_s + 1)]
    return s


def test_a_stop_is_still_after_driving_and_its_sigma_grows_with_distance():
    tracker = StopTracker(StopRules(moving_speed_m_s=0.3, settle_ms=3000, sigma_per_m=0.05))
    assert _track(tracker, [(0, 5.0, 5.0, 0.0), (1000, 5.0, 5.0, 0.0), (5000, 5.0, 5.0, 0.0)]) == []  # never drove
    (rep,) = _track(tracker, _leg(6000, (5.0, 5.0), (305.0, -395.0)))
    assert (rep.stop_id, rep.north_m, rep.east_m, rep.reset) == (1, 300.0, -400.0, False)
    assert rep.sigma_m == pytest.approx(0.05 * 500.0)
    (rep,) = _track(tracker, _leg(30_000, (305.0, -395.0), (305.0, -295.0)))
    assert (rep.stop_id, rep.north_m, rep.east_m) == (2, 0.0, 100.0)


def test_a_pause_shorter_than_the_settling_is_no_stop():
    tracker = StopTracker(StopRules(0.3, 3000, 0.05))
    samples = _leg(0, (0.0, 0.0), (100.0, 0.0), still_s=2)  # 2 s still
    samples += [(s[0] + 13_000, s[1] + 100.0, s[2], s[3]) for s in _leg(0, (0.0, 0.0), (100.0, 0.0))[1:]]
    (rep,) = _track(tracker, samples)
    assert rep.north_m == pytest.approx(200.0)


def test_sigma_from_the_covariance():
    then = LocalPosition(0, 0, 0, 0, 0, 100.0, 100.0)
    # dead reckoning: the covariance grew by 225 m^2 per axis
    assert displacement_sigma_m(then, LocalPosition(0, 300, 0, 0, 0, 325.0, 325.0), 0.05) == pytest.approx(15.0)
    # an aided filter whose covariance shrank: independent errors at both ends
    assert displacement_sigma_m(then, LocalPosition(0, 300, 0, 0, 0, 44.0, 44.0), 0.05) == pytest.approx(12.0)
    tracker = StopTracker(StopRules(0.3, 3000, 0.05))
    (rep,) = _track(tracker, _leg(0, (0.0, 0.0), (0.0, 200.0), var0=16.0, var1=16.0 + 81.0))
    assert rep.sigma_m == pytest.approx(9.0)


def test_a_reset_marks_the_next_stop_and_only_that_one():
    tracker = StopTracker(StopRules(0.3, 3000, 0.05))
    _track(tracker, _leg(0, (0.0, 0.0), (100.0, 0.0))[:5])  # half a leg, then the autopilot reboots
    tracker.reset()
    (rep,) = _track(tracker, _leg(0, (0.0, 0.0), (40.0, 0.0)))
    assert rep.reset and rep.stop_id == 1 and rep.north_m == pytest.approx(40.0)
    (rep,) = _track(tracker, _leg(20_000, (40.0, 0.0), (40.0, 60.0)))
    assert not rep.reset and rep.east_m == pytest.approx(60.0)


def test_a_changed_reset_counter_is_a_frame_reset():
    tracker = StopTracker(StopRules(0.3, 3000, 0.05))
    assert tracker.update(LocalPosition(0, 0, 0, 0, 0, reset_counter=2)) == (None, False)
    assert tracker.update(LocalPosition(10, 0, 0, 0, 0, reset_counter=2)) == (None, False)
    rep, reset = tracker.update(LocalPosition(20, 0, 0, 0, 0, reset_counter=3))
    assert rep is None and reset and tracker.broken


def _fix(cov, ok=True, lat=36.6, lon=-84.25):
    return PositionFix(lat, lon, None if cov is None else np.asarray(cov, float), ok,
                       int(dt.datetime(2026, 6, 1, 12, tzinfo=dt.timezone.utc).timestamp() * 1e9))


def test_gps_input_accuracy_is_the_rms_radius_of_the_covariance():
    # sigma east 3 m, north 4 m, correlated: the RMS radial error is sqrt(9 + 16) = 5 m whatever the correlation
    f = gps_input_fields(_fix([[9.0, 5.0], [5.0, 16.0]]))
    assert f["horiz_accuracy"] == pytest.approx(5.0) and f["fix_type"] == FIX_3D
    assert (f["lat"], f["lon"]) == (366000000, -842500000)
    # altitude, hdop, vdop, velocities, speed and vertical accuracy ignored; horizontal accuracy given
    assert f["ignore_flags"] == 1 | 2 | 4 | 8 | 16 | 32 | 128
    assert horizontal_accuracy_m(np.array([[NAN, 0], [0, 1.0]])) is None


def test_gps_input_of_an_estimate_that_is_not_ok_has_no_fix():
    assert gps_input_fields(_fix([[9.0, 0.0], [0.0, 16.0]], ok=False))["fix_type"] == FIX_NONE
    f = gps_input_fields(_fix(None, ok=True))  # no covariance: no fix, accuracy flagged unknown
    assert f["fix_type"] == FIX_NONE and f["ignore_flags"] & IGNORE_HORIZONTAL_ACCURACY


def test_gps_time_against_the_week_2048_rollover():
    # GPS week 2048 began 2019-04-07 00:00:00 GPS time, 18 s before that in UTC
    start = dt.datetime(2019, 4, 7, tzinfo=dt.timezone.utc) - dt.timedelta(seconds=18)
    ns = int(start.timestamp()) * 1_000_000_000
    assert gps_time(ns) == (2048, 0)
    assert gps_time(ns + 90_061_500_000_000) == (2048, 90_061_500)  # 1 d 1 h 1 min 1.5 s into the week


def test_gps_input_round_trips_through_pymavlink():
    fields = gps_input_fields(_fix([[4.0, 0.0], [0.0, 5.0]]))
    msg = wire(lambda m: m.gps_input_encode(**fields), component=191)
    assert (msg.fix_type, msg.lat, msg.lon, msg.ignore_flags) == (3, 366000000, -842500000, fields["ignore_flags"])
    assert msg.horiz_accuracy == pytest.approx(3.0) and msg.get_srcComponent() == 191


def test_vision_position_is_the_offset_from_the_origin_with_the_covariance():
    origin = origin_of(36.6, -84.25, 100.0, -50.0)  # the frame's zero 100 m south and 50 m east of here
    north, east = north_east_m(36.6, -84.25, *origin)
    assert (north, east) == pytest.approx((100.0, -50.0), abs=0.01)
    f = vision_position_fields(_fix([[9.0, 1.5], [1.5, 16.0]]), origin, 1)
    assert (f["x"], f["y"]) == pytest.approx((100.0, -50.0), abs=0.01)
    cov = f["covariance"]
    assert (cov[0], cov[1], cov[6]) == (16.0, 1.5, 9.0)  # x-x north, x-y, y-y east
    # 0.001 deg of latitude is 111.2 m on the mean sphere
    assert north_east_m(36.601, -84.25, 36.6, -84.25)[0] == pytest.approx(111.195, abs=0.01)


@pytest.mark.parametrize("text,fragment", [
    ('[devices.odometry]\nkind = "mavlnk"\n', "devices.odometry.kind"),
    ('[devices.odometry]\nurl = "udpin:0.0.0.0"\n', "devices.odometry.url"),
    ('[devices.odometry]\nurl = "udpout:host:70000"\n', "devices.odometry.url"),
    ("[devices.odometry]\nsystem_id = 0\n", "devices.odometry.system_id"),
    ("[devices.odometry]\nsettle_s = 0\n", "devices.odometry.settle_s"),
    ('[devices.odometry]\noutput = "gps"\n', "devices.odometry.output"),
])
def test_bad_mavlink_settings_name_the_key(tmp_path, text, fragment):
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=fragment.replace(".", r"\.")):
        load_config(p)


def test_a_serial_url_is_not_a_udp_one():
    assert OdometryDeviceConfig(url="/dev/ttyACM0").url == "/dev/ttyACM0"
