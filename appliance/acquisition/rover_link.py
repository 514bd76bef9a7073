"""A traverse's exchanges with the rover's autopilot (:class:`appliance.acquisition.platform.Autopilot`,
the MAVLink link): its faults logged as the session's warnings, what it says of the rover at each
stop's session and capture begin (``/traverse/rover``), and each stop's estimate sent back (``/traverse/position_out``).

An estimate is sent as ok when it says so itself: not ambiguous and with a covariance (the GPS truth
the simulator logs plays no part: on a rover there is none).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from appliance.acquisition.platform import Autopilot
from appliance.drivers.autopilot import PositionFix, RoverState, SentPosition
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook

if TYPE_CHECKING:
    from appliance.acquisition.session import Session
    from appliance.locating.position import Position


def say_faults(autopilot: Autopilot | None, head: Session) -> None:
    """Every fault the link has seen since the last call, as a warning of the traverse."""
    if autopilot is None:
        return
    for text in autopilot.faults():
        head.say("warning", f"autopilot: {text}")


def rover_record(stop: int, s: RoverState, faults: dict[str, int]) -> dict[str, Any]:
    """The ``/traverse/rover`` record (``viper.RoverState``)."""
    return {"stop": stop, "heading_deg": s.heading_deg, "roll_deg": s.roll_deg, "pitch_deg": s.pitch_deg,
            "armed": s.armed, "mode": s.mode, "lat": s.lat_deg, "lon": s.lon_deg, "time_boot_ms": s.time_boot_ms,
            "boots": s.boots, "faults": dict(faults)}


def log_rover_state(autopilot: Autopilot | None, log: Logbook, stop: int, now_ns: int) -> RoverState | None:
    """What the autopilot says of the rover as stop ``stop``'s session (and its capture) begins, logged."""
    if autopilot is None:
        return None
    state = autopilot.state()
    log.write_json(t.ROVER_STATE, "viper.RoverState", rover_record(stop, state, autopilot.counts()), now_ns)
    return state


def position_fix(pos: Position, time_ns: int) -> PositionFix:
    """The estimate as the autopilot is told it: ok only when it says so itself."""
    r = pos.result
    cov = r.covariance_m2
    finite = cov is not None and bool(np.all(np.isfinite(cov)))
    return PositionFix(pos.lat, pos.lon, cov if finite else None, ok=finite and not r.ambiguous, time_ns=time_ns)


def out_record(stop: int, fix: PositionFix, sent: SentPosition) -> dict[str, Any]:
    """The ``/traverse/position_out`` record (``viper.PositionOut``)."""
    return {"stop": stop, "message": sent.message, "sent": sent.sent, "reason": sent.reason,
            "fix_type": sent.fix_type, "horiz_accuracy_m": sent.horiz_accuracy_m, "lat": fix.lat_deg,
            "lon": fix.lon_deg, "ok": fix.ok}


def send_estimate(autopilot: Autopilot | None, log: Logbook, head: Session, stop: int, pos: Position | None,
                  now_ns: int) -> SentPosition | None:
    """Send stop ``stop``'s estimate to the autopilot (as configured) and log what became of it."""
    if autopilot is None or pos is None or pos.estimate is None:
        return None
    fix = position_fix(pos, now_ns)
    sent = autopilot.send_position(fix)
    if sent.message:
        log.write_json(t.POSITION_OUT, "viper.PositionOut", out_record(stop, fix, sent), now_ns)
        if sent.sent:
            acc = "" if sent.horiz_accuracy_m is None else f", accuracy {sent.horiz_accuracy_m:.1f} m"
            fix_type = "" if sent.fix_type is None else f", fix_type {sent.fix_type}"
            head.say("info", f"traverse stop {stop}: estimate sent to the autopilot as {sent.message}{fix_type}{acc}")
        else:
            head.say("info", f"traverse stop {stop}: estimate not sent to the autopilot: {sent.reason}")
    return sent
