"""The MAVLink half of ``bench/traverse.py --mavlink``: one traverse's odometry through a real autopilot
twin and the appliance's MAVLink link over UDP (pymavlink both ends), and each estimate sent back as
GPS_INPUT and checked where the twin receives it.

:class:`MavlinkLeg` drives the twin along the true leg (its dead-reckoning drift 0.05 m per metre
driven, the link's sigma 0.05 m/m too: 10-20 m on legs of 200-400 m, against the line's fixed 15 m),
waits for the stop the link reports and returns it as the traverse's move; a reboot halfway
through a leg comes back as a reset (no move).  :meth:`MavlinkLeg.send` sends an estimate (ambiguous
ones too, as fix_type 0: ``output_ambiguous``) and checks what arrived: fix_type 3 exactly for the
estimates that say ok, horiz_accuracy = sqrt(trace(covariance_m2)) (float32).
"""

from __future__ import annotations

import datetime as dt
import math
import time

import numpy as np

from appliance.acquisition.rover_link import position_fix
from appliance.config import OdometryDeviceConfig, OdometryKind, PositionOutput
from appliance.drivers.mavlink_output import horizontal_accuracy_m
from appliance.drivers.mavlink_reader import open_mavlink
from appliance.locating.position import Move
from appliance.sim.autopilot_twin import AutopilotTwin, UdpTwinLink
from appliance.sim.world import SimClock, SimWorld

TIME_RATE = 100.0  # simulated seconds per real second: a 300 m leg at 5 m/s takes 0.6 s
WAIT_S = 120.0  # real seconds a stop or a message may take on a loaded machine before the run says so
DRIFT_PER_M = 0.05


class MavlinkLeg:
    """A twin and a link for one traverse starting at (lat, lon)."""

    def __init__(self, lat: float, lon: float, seed: int) -> None:
        clock = SimClock(dt.datetime(2026, 6, 1, tzinfo=dt.timezone.utc), time_rate=TIME_RATE)
        self.world = SimWorld(lat, lon, 0.0, clock=clock)
        cfg = OdometryDeviceConfig(kind=OdometryKind.MAVLINK, read_timeout_s=0.05, sigma_per_m=DRIFT_PER_M,
                                   link_timeout_s=5.0 * TIME_RATE, output=PositionOutput.GPS_INPUT,
                                   output_ambiguous=True, output_min_interval_s=0.0)
        self.link = open_mavlink("udpin:127.0.0.1:0", cfg, clock_ns=clock.now_ns)
        assert self.link.udp_port is not None
        self.twin = AutopilotTwin(self.world, UdpTwinLink(("127.0.0.1", self.link.udp_port)), seed, DRIFT_PER_M)
        self.twin.start()
        self.faults: list[str] = []
        self.checks = {"sent": 0, "sent_ok": 0, "received": 0, "fix3_ok": 0, "fix0_not_ok": 0, "good_from_not_ok": 0,
                       "accuracy_mismatch": 0, "max_accuracy_error_m": 0.0}

    def leg(self, east_m: float, north_m: float, lat: float, lon: float, reboot: bool) -> tuple[Move | None, bool]:
        """Drive the true leg to (lat, lon); (the move the link measured, or None after a reset; reset)."""
        self.world.lat_deg, self.world.lon_deg = lat, lon
        self.twin.drive(east_m, north_m, 0.5 if reboot else None)
        deadline = time.monotonic() + WAIT_S
        reports = []
        while not reports:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no stop from the MAVLink link within {WAIT_S:g} s")
            reports = self.link.poll()
        self.faults += self.link.faults()
        (rep,) = reports
        return (None if rep.reset else Move(rep.east_m, rep.north_m, rep.sigma_m)), rep.reset

    def send(self, pos: object) -> None:
        """Send ``pos`` (a Position) as GPS_INPUT and check what the twin received."""
        fix = position_fix(pos, self.world.clock.now_ns())  # type: ignore[arg-type]
        before = len(self.twin.received)
        sent = self.link.send_position(fix)
        c = self.checks
        if not sent.sent:
            return
        c["sent"] += 1
        c["sent_ok"] += fix.ok
        deadline = time.monotonic() + WAIT_S
        while len(self.twin.received) == before and time.monotonic() < deadline:
            time.sleep(0.002)
        if len(self.twin.received) == before:
            return
        c["received"] += 1
        m = self.twin.received[-1].message
        if fix.ok:
            c["fix3_ok"] += m.fix_type == 3
            want = horizontal_accuracy_m(fix.covariance_m2)
            err = abs(float(m.horiz_accuracy) - float(want))
            c["max_accuracy_error_m"] = max(c["max_accuracy_error_m"], err)
            c["accuracy_mismatch"] += not math.isclose(m.horiz_accuracy, want, rel_tol=1e-6, abs_tol=1e-6)
        else:
            c["fix0_not_ok"] += m.fix_type == 0
            c["good_from_not_ok"] += m.fix_type >= 2

    def close(self) -> None:
        self.link.close()
        self.twin.stop()


def sum_checks(checks: list[dict]) -> dict:
    out: dict = {}
    for c in checks:
        for k, v in c.items():
            out[k] = max(out.get(k, 0.0), v) if k.startswith("max_") else out.get(k, 0) + v
    return out


def p90(values: list[float]) -> float:
    return float(np.percentile(np.asarray(values), 90))
