"""The MAVLink link and the autopilot twin over real UDP sockets and a real pty, pymavlink encoding and
parsing on both ends: stops and their displacement, the estimate sent back as GPS_INPUT, a reboot
breaking the traverse's fusion, out-of-order, foreign and NaN messages counted and ignored, a silent
link, and a UDP port already taken."""

from __future__ import annotations

import datetime as dt
import json
import math
import socket
import time

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from appliance.acquisition.platform import Platform  # noqa: E402
from appliance.acquisition.rover_link import out_record, rover_record  # noqa: E402
from appliance.acquisition.session import Session, SessionResult  # noqa: E402
from appliance.acquisition.traverse import Traverse, TraverseResult  # noqa: E402
from appliance.cli.main import main  # noqa: E402
from appliance.config import Config, OdometryDeviceConfig, OdometryKind, PositionOutput, TraverseConfig  # noqa: E402
from appliance.drivers.autopilot import PositionFix  # noqa: E402
from appliance.drivers.mavlink_reader import open_mavlink  # noqa: E402
from appliance.errors import DeviceError  # noqa: E402
from appliance.locating.position import Move  # noqa: E402
from appliance.logbook import topics as t  # noqa: E402
from appliance.logbook.writer import Logbook  # noqa: E402
from appliance.sim.autopilot_twin import AutopilotTwin, PtyTwinLink, UdpTwinLink  # noqa: E402
from appliance.sim.pty_port import PtyPort  # noqa: E402
from appliance.sim.world import SimClock, SimWorld  # noqa: E402

RATE = 50.0  # simulated seconds per real second: a 100 m leg at 5 m/s takes 0.4 s
WAIT_S = 20.0  # real seconds any one wait may take on a busy machine before the test fails


def _world(heading_deg=30.0):
    clock = SimClock(dt.datetime(2026, 6, 1, tzinfo=dt.timezone.utc), time_rate=RATE)
    return SimWorld(36.6, -84.25, 500.0, heading_deg=heading_deg, tilt_north_deg=2.0, tilt_east_deg=0.0,
                    clock=clock)


def _cfg(**kw):
    base = dict(kind=OdometryKind.MAVLINK, read_timeout_s=0.05, link_timeout_s=5.0 * RATE,
                output=PositionOutput.GPS_INPUT, output_min_interval_s=0.0)
    base.update(kw)
    return OdometryDeviceConfig(**base)


def _until(cond, what):
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def udp_pair():
    world = _world()
    cfg = _cfg()
    link = open_mavlink("udpin:127.0.0.1:0", cfg, clock_ns=world.clock.now_ns)
    twin = AutopilotTwin(world, UdpTwinLink(("127.0.0.1", link.udp_port)), seed=5, drift_per_m=0.05)
    twin.start()
    yield world, link, twin
    twin.stop()
    link.close()


def _poll_stop(link):
    reports = []
    _until(lambda: reports.extend(link.poll()) or reports, "a stop")
    return reports


def test_the_twin_speaks_mavlink_to_pymavlinks_own_connection():
    """pymavlink's mavutil on the appliance's side: the twin's frames parse, and its GPS_INPUT arrives."""
    world = _world(heading_deg=250.0)
    conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", dialect="common", source_system=1, source_component=191)
    twin = AutopilotTwin(world, UdpTwinLink(("127.0.0.1", conn.port.getsockname()[1])), seed=1)
    twin.start()
    try:
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=WAIT_S)
        assert (hb.type, hb.autopilot, hb.get_srcSystem()) == (10, 3, 1)
        assert hb.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED and mavutil.mode_string_v10(hb) == "HOLD"
        att = conn.recv_match(type="ATTITUDE", blocking=True, timeout=WAIT_S)
        assert math.degrees(att.yaw) % 360.0 == pytest.approx(250.0, abs=1e-4)
        pos = conn.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=WAIT_S)
        assert (pos.lat, pos.lon, pos.hdg) == (366000000, -842500000, 25000)
        conn.mav.gps_input_send(1, 0, 0, 0, 0, 3, 366000100, -842500100, 0, 0, 0, 0, 0, 0, 0, 4.5, 0, 0)
        got = _until(lambda: twin.received, "the GPS_INPUT at the twin")
        assert (got[0].message.lat, got[0].message.horiz_accuracy) == (366000100, 4.5)
    finally:
        twin.stop()
        conn.close()


def test_the_link_reads_stops_state_and_sends_gps_input_over_udp(udp_pair):
    world, link, twin = udp_pair
    state = _until(lambda: (s := link.state()).mode is not None and s.lat_deg is not None and s, "the state")
    assert state.armed and state.mode == "HOLD" and state.heading_deg == pytest.approx(30.0, abs=1e-4)
    # 2 deg of tilt towards north seen from a heading of 30 deg: 1.73 deg of pitch, -1 deg of roll
    assert (state.pitch_deg, state.roll_deg) == pytest.approx((2 * math.cos(math.radians(30)),
                                                               -2 * math.sin(math.radians(30))), abs=1e-4)
    assert (state.lat_deg, state.lon_deg) == pytest.approx((36.6, -84.25), abs=1e-7)
    twin.drive(60.0, 80.0)
    (rep,) = _poll_stop(link)
    drift = twin.drift_ne  # the twin's dead-reckoning error on this leg (north, east)
    assert (rep.stop_id, rep.reset) == (1, False)
    assert (rep.north_m, rep.east_m) == pytest.approx((80.0 + drift[0], 60.0 + drift[1]), abs=1e-3)
    assert rep.sigma_m == pytest.approx(0.05 * math.hypot(rep.north_m, rep.east_m), rel=1e-6)
    assert 0.0 < np.hypot(*drift) < 5 * 0.05 * 100.0

    fix = PositionFix(36.6007, -84.2499, np.array([[9.0, 2.0], [2.0, 16.0]]), True, world.clock.now_ns())
    sent = link.send_position(fix)
    assert sent.sent and sent.fix_type == 3 and sent.horiz_accuracy_m == pytest.approx(5.0)
    (got,) = _until(lambda: twin.received, "the GPS_INPUT at the twin")
    m = got.message
    assert (m.fix_type, m.lat, m.lon, m.get_srcSystem(), m.get_srcComponent()) == (3, 366007000, -842499000, 1, 191)
    assert m.horiz_accuracy == pytest.approx(5.0)
    # an ambiguous estimate is not sent as a position
    ambiguous = PositionFix(36.6, -84.25, np.eye(2), False, world.clock.now_ns())
    assert not link.send_position(ambiguous).sent
    assert len(twin.received) == 1
    for name, rec in (("viper.RoverState", rover_record(1, state, link.counts())),
                      ("viper.PositionOut", out_record(1, fix, sent))):
        jsonschema = pytest.importorskip("jsonschema")
        assert not list(jsonschema.Draft202012Validator(t.JSON_SCHEMAS[name]).iter_errors(rec))


def test_ambiguous_estimates_go_with_fix_type_0_when_asked_and_sends_are_rate_limited(udp_pair):
    world, link, twin = udp_pair
    _until(lambda: link.state().mode, "a heartbeat")
    link.cfg = _cfg(output_ambiguous=True, output_min_interval_s=3600.0)
    ambiguous = PositionFix(36.6, -84.25, np.diag([400.0, 500.0]), False, world.clock.now_ns())
    sent = link.send_position(ambiguous)
    assert sent.sent and sent.fix_type == 0
    (got,) = _until(lambda: twin.received, "the GPS_INPUT at the twin")
    assert got.message.fix_type == 0 and got.message.horiz_accuracy == pytest.approx(30.0)
    again = link.send_position(PositionFix(36.6, -84.25, np.eye(2), True, world.clock.now_ns()))
    assert not again.sent and "rate limit" in again.reason


def test_vision_position_estimate_is_anchored_to_the_autopilots_frame(udp_pair):
    world, link, twin = udp_pair
    _until(lambda: link._local is not None, "a local position")
    link.cfg = _cfg(output=PositionOutput.VISION_POSITION_ESTIMATE)
    first = PositionFix(36.6, -84.25, np.diag([4.0, 9.0]), True, world.clock.now_ns())
    assert link.send_position(first).sent
    # 0.001 deg north of the first estimate: 111.2 m further north in the autopilot's frame
    second = PositionFix(36.601, -84.25, np.diag([4.0, 9.0]), True, world.clock.now_ns())
    assert link.send_position(second).sent
    a, b = _until(lambda: len(twin.received) >= 2 and twin.received, "two vision estimates")
    assert b.message.x - a.message.x == pytest.approx(111.19, abs=0.05)
    assert b.message.y - a.message.y == pytest.approx(0.0, abs=0.01)
    assert (b.message.covariance[0], b.message.covariance[6]) == (9.0, 4.0)  # north, east


def test_the_link_reads_the_twin_over_a_pty(tmp_path):
    world = _world()
    port = PtyPort(tmp_path / "autopilot")
    twin = AutopilotTwin(world, PtyTwinLink(port), seed=2, drift_per_m=0.0, send_odometry=True)
    twin.start()
    link = open_mavlink(str(port.path), _cfg(baudrate=57600), clock_ns=world.clock.now_ns)
    try:
        _until(lambda: link._odometry_seen, "an ODOMETRY message over the pty")
        twin.drive(-50.0, 20.0)  # no drift: the displacement is the leg's, its sigma from the covariance (0)
        twin_var = twin.var_m2
        (rep,) = _poll_stop(link)
        assert (rep.north_m, rep.east_m, rep.sigma_m) == pytest.approx((20.0, -50.0, math.sqrt(twin_var)),
                                                                       abs=1e-3)
        assert link.send_position(PositionFix(36.6, -84.25, np.diag([1.0, 3.0]), True, world.clock.now_ns())).sent
        (got,) = _until(lambda: twin.received, "the GPS_INPUT over the pty")
        assert got.message.horiz_accuracy == pytest.approx(2.0)
    finally:
        link.close()
        twin.stop()


def test_odometry_with_a_covariance_gives_the_sigma_it_grew_by(udp_pair):
    world, link, twin = udp_pair
    twin.send_odometry = True
    _until(lambda: link._odometry_seen, "an ODOMETRY message")
    twin.drive(0.0, 200.0)
    (rep,) = _poll_stop(link)
    assert rep.sigma_m == pytest.approx(0.05 * 200.0, rel=1e-5)  # sqrt of the variance the leg added


def _bare_traverse(tmp_path, world, link):
    config = Config(traverse=TraverseConfig(stops=4, odometry_timeout_s=600.0))
    platform = Platform(world.clock, None, None, None, None, None, None, odometry=link, autopilot=link)
    log = Logbook.create(tmp_path / "t.mcap")
    result = TraverseResult(tmp_path / "t.mcap", "test")
    trav = Traverse(platform, log, config, None, result, 4, lambda: False, lambda s: None, lambda i: None)
    head = Session(platform, log, config, None, SessionResult(result.log_path, "test"))
    return trav, head, log


def test_a_reboot_mid_leg_is_a_logged_fault_and_breaks_the_fusion(tmp_path, udp_pair):
    world, link, twin = udp_pair
    trav, head, log = _bare_traverse(tmp_path, world, link)
    try:
        twin.drive(0.0, 150.0)
        assert trav.next_odometry(head).stop_id == 1 and trav.moved is not None
        trav.chain.belief = object()  # an estimate at stop 1, whose posterior stop 2 would move
        trav.chain.moved = Move(0.0, 0.0, 0.0)
        twin.drive(200.0, 0.0)
        _until(lambda: twin.driving and twin.state(world.clock.monotonic_s())[0][1] > 20.0, "the rover under way")
        twin.reboot()
        rep = trav.next_odometry(head)
        assert rep.stop_id == 2 and rep.reset
        assert trav.chain.belief is None and trav.moved is None and "reset" in trav.note
        stop = trav.prepare_stop(2, rep)
        assert not stop.fused and "not fused across it" in stop.fusion_note
        assert any("autopilot reboot" in p for p in head.result.problems)
        # the next leg is measured in the new frame and joins stops 2 and 3 again
        twin.drive(0.0, -100.0)
        rep = trav.next_odometry(head)
        assert rep.stop_id == 3 and not rep.reset and rep.north_m == pytest.approx(-100.0, abs=10.0)
        # the move from stop 2 is taken whole; what it moves is stop 2's own estimate (none here)
        assert trav.chain.belief is None and trav.moved == Move(rep.east_m, rep.north_m, rep.sigma_m)
    finally:
        log.close()
    # the log, read back: the fault as a warning, the odometry of stop 2 marked reset, both schema-valid
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from mcap.reader import make_reader

    odometry, logs = [], []
    with open(tmp_path / "t.mcap", "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic == t.ODOMETRY:
                odometry.append(json.loads(message.data))
            elif channel.topic == t.LOG:
                logs.append(Log.FromString(message.data).message)
    assert [(o["stop_id"], o["reset"]) for o in odometry] == [(1, False), (2, True), (3, False)]
    assert any(text.startswith("autopilot: autopilot reboot: ") for text in logs)


def _sender(port, system=1):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    class Out:
        def write(self, b):
            sock.sendto(bytes(b), ("127.0.0.1", port))

    return sock, mavlink2.MAVLink(Out(), srcSystem=system, srcComponent=1)


def test_out_of_order_foreign_and_nan_messages_are_counted_and_ignored():
    clock = SimClock(dt.datetime(2026, 6, 1, tzinfo=dt.timezone.utc))
    link = open_mavlink("udpin:127.0.0.1:0", _cfg(link_timeout_s=60.0), clock_ns=clock.now_ns)
    sock, mav = _sender(link.udp_port)
    sock9, mav9 = _sender(link.udp_port, system=9)
    try:
        mav.send(mav.attitude_encode(5000, 0, 0, 0.0, 0, 0, 0))
        mav.send(mav.attitude_encode(4800, 0, 0, math.radians(90.0), 0, 0, 0))  # 200 ms late
        mav9.send(mav9.attitude_encode(9000, 0, 0, math.radians(180.0), 0, 0, 0))
        mav.send(mav.attitude_encode(5100, 0, 0, float("nan"), 0, 0, 0))
        mav.send(mav.local_position_ned_encode(5100, float("nan"), 0, 0, 0, 0, 0))
        mav.send(mav.attitude_encode(5200, 0, 0, math.radians(45.0), 0, 0, 0))
        _until(lambda: link.state().time_boot_ms == 5200, "the last attitude")
        assert link.state().heading_deg == pytest.approx(45.0)
        assert link.counts() == {"out-of-order message": 1, "message from another system id": 1,
                                 "message with NaN fields": 2}
        faults = link.faults()
        assert len(faults) == 4 and any("system 9" in f for f in faults) and any("yaw not finite" in f for f in faults)
        assert link.state().boots == 0
    finally:
        sock.close()
        sock9.close()
        link.close()


def test_a_silent_link_is_a_fault_not_an_error():
    link = open_mavlink("udpin:127.0.0.1:0", _cfg(link_timeout_s=0.2))  # the system's clock
    try:
        faults = _until(link.faults, "the silence")
        assert faults[0].startswith("link silent: no message from system 1")
    finally:
        link.close()


def test_a_taken_udp_port_is_a_one_line_error(tmp_path, capsys):
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    port = taken.getsockname()[1]
    try:
        with pytest.raises(DeviceError, match=f"UDP port {port} is taken"):
            open_mavlink(f"udpin:127.0.0.1:{port}", _cfg())
        cfg = tmp_path / "rover.toml"
        cfg.write_text('[platform]\nkind = "hardware"\n[traverse]\nstops = 2\n'
                       '[devices.compass]\nkind = "nmea"\n[devices.inclinometer]\nkind = "nmea"\n'
                       f'[devices.odometry]\nkind = "mavlink"\nurl = "udpin:127.0.0.1:{port}"\n')
        code = main(["capture", "--config", str(cfg), "--log-dir", str(tmp_path / "logs")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code != 0 and len(err) == 1 and f"UDP port {port} is taken" in err[0]
        assert not list(tmp_path.rglob("*.mcap"))
    finally:
        taken.close()


def test_mavlink_without_a_traverse_is_a_one_line_error(tmp_path, capsys):
    code = main(["demo", "--mavlink", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "--mavlink goes with --traverse N" in err[0]


def test_the_simulated_rover_reboots_its_autopilot_on_the_leg_asked(tmp_path, udp_pair):
    """[sim.faults] autopilot_reboot_leg = 2: the rover twin's second leg comes back reset, the others not."""
    from appliance.config import SimConfig
    from appliance.sim.autopilot_twin import MavlinkRover
    from appliance.sim.rover_twin import RoverTwin

    world, link, twin = udp_pair
    port = PtyPort(tmp_path / "odometry")
    try:
        rover = RoverTwin(world, port, SimConfig(leg_length_m=(50.0, 80.0)), lambda lat, lon: 500.0,
                          lambda lat, lon: True, seed=4)
        both = MavlinkRover(rover, twin, reboot_leg=2)
        resets = []
        for _ in range(3):
            leg = both.drive()
            (rep,) = _poll_stop(link)
            resets.append(rep.reset)
            if not rep.reset:
                assert math.hypot(rep.east_m - leg.east_m, rep.north_m - leg.north_m) < 5 * 0.05 * 80.0
        assert resets == [False, True, False] and twin.boots == 1 and link.state().boots == 1
    finally:
        port.close()
