"""A rover's stops and the displacement between them, from the autopilot's stream of local positions.
Pure: :class:`LocalPosition` readings in, :class:`appliance.drivers.odometry.OdometryReport` out (the
same record the odometry line gives, so the traverse fuses either alike).

A stop is where the rover stands still (horizontal speed at most ``moving_speed_m_s``) for
``settle_s`` of the autopilot's time after having driven (faster than that).  The displacement
reported is the local position there minus the position at the previous stop (the first position
received for the first).  Its 1-sigma per axis:

- with ODOMETRY's covariance at both ends: ``sqrt(var_now - var_then)`` (the mean of the north and
  east variances) when the covariance grew, as dead reckoning's does; an aided filter's covariance
  need not grow, and then ``sqrt(var_now + var_then)`` (independent errors at both ends);
- without: ``sigma_per_m`` times the distance between the two stops.

A reboot of the autopilot or a reset of its position frame (:meth:`StopTracker.reset`, or ODOMETRY's
``reset_counter`` changing) leaves no valid previous stop: the next stop is reported with
``reset=True`` (its displacement measured from the first position after the reset, not to be fused),
and the stop after that is measured normally again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.drivers.mavlink import LocalPosition
from appliance.drivers.odometry import MAX_STOP_ID, OdometryReport


@dataclass(frozen=True)
class StopRules:
    moving_speed_m_s: float = 0.3
    settle_ms: int = 3000
    sigma_per_m: float = 0.05


def _mean_var(p: LocalPosition) -> float | None:
    if p.var_north_m2 is None or p.var_east_m2 is None:
        return None
    return 0.5 * (p.var_north_m2 + p.var_east_m2)


def displacement_sigma_m(then: LocalPosition, now: LocalPosition, sigma_per_m: float) -> float:
    """The 1-sigma per axis (m) of the displacement from ``then`` to ``now`` (see the module's rules)."""
    v0, v1 = _mean_var(then), _mean_var(now)
    if v0 is None or v1 is None:
        return sigma_per_m * math.hypot(now.north_m - then.north_m, now.east_m - then.east_m)
    grown = v1 - v0
    return math.sqrt(grown if grown > 0 else v1 + v0)


class StopTracker:
    """Local positions in, one :class:`OdometryReport` per stop out (stop ids from 1)."""

    def __init__(self, rules: StopRules) -> None:
        self.rules = rules
        self.stop_id = 0
        self.mark: LocalPosition | None = None  # the position at the previous stop
        self.broken = False  # a reset since the previous stop: the next report is not to be fused
        self.moving = False
        self._still_since_ms: int | None = None
        self._last: LocalPosition | None = None
        self._reset_counter: int | None = None

    def reset(self) -> None:
        """The autopilot rebooted or reset its frame: positions before and after do not compare."""
        self.broken = True
        self.mark = None
        self._last = None
        self._still_since_ms = None
        self._reset_counter = None

    def _speed(self, p: LocalPosition) -> float:
        if math.isfinite(p.speed_m_s):
            return p.speed_m_s
        last = self._last
        if last is None or p.time_boot_ms <= last.time_boot_ms:
            return 0.0
        return math.hypot(p.north_m - last.north_m, p.east_m - last.east_m) / ((p.time_boot_ms - last.time_boot_ms)
                                                                              / 1000.0)

    def update(self, p: LocalPosition) -> tuple[OdometryReport | None, bool]:
        """(the stop ``p`` completes or None, whether ``p`` reveals a frame reset by its reset counter)."""
        frame_reset = False
        if p.reset_counter is not None:
            if self._reset_counter is not None and p.reset_counter != self._reset_counter:
                self.reset()
                frame_reset = True
            self._reset_counter = p.reset_counter
        speed = self._speed(p)
        self._last = p
        if self.mark is None or (not self.moving and _mean_var(self.mark) is None and _mean_var(p) is not None):
            self.mark = p  # the first position, or the first with a covariance while the rover still stands
        if speed > self.rules.moving_speed_m_s:
            self.moving, self._still_since_ms = True, None
            return None, frame_reset
        if not self.moving:
            return None, frame_reset
        if self._still_since_ms is None:
            self._still_since_ms = p.time_boot_ms
        if p.time_boot_ms - self._still_since_ms < self.rules.settle_ms:
            return None, frame_reset
        return self._report(p), frame_reset

    def _report(self, p: LocalPosition) -> OdometryReport:
        mark = self.mark
        assert mark is not None
        self.stop_id = min(self.stop_id + 1, MAX_STOP_ID)
        report = OdometryReport(self.stop_id, p.east_m - mark.east_m, p.north_m - mark.north_m,
                                displacement_sigma_m(mark, p, self.rules.sigma_per_m), p.receive_time_ns,
                                reset=self.broken)
        self.mark, self.moving, self.broken, self._still_since_ms = p, False, False, None
        return report

