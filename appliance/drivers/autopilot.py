"""What passes between the appliance and a rover's autopilot, whatever the protocol: the estimate to
send (:class:`PositionFix`), what became of it (:class:`SentPosition`), and what the autopilot last
said of the rover (:class:`RoverState`).  Plain records: no protocol library is needed to read them
(the MAVLink link, :mod:`appliance.drivers.mavlink_reader`, makes and takes them)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PositionFix:
    """An estimate to send: where (deg), its (east, north) covariance (m^2; None: none), whether it
    says ok (not ambiguous, with a covariance), and when (UTC ns)."""

    lat_deg: float
    lon_deg: float
    covariance_m2: np.ndarray | None
    ok: bool
    time_ns: int


@dataclass(frozen=True)
class RoverState:
    """What the autopilot last said: attitude (deg; heading clockwise from true north), armed state and
    mode, global position (deg), its time since boot (ms) and the reboots seen; None where not heard."""

    heading_deg: float | None
    roll_deg: float | None
    pitch_deg: float | None
    armed: bool | None
    mode: str | None
    lat_deg: float | None
    lon_deg: float | None
    time_boot_ms: int | None
    boots: int


@dataclass(frozen=True)
class SentPosition:
    """What :meth:`MavlinkLink.send_position` did with an estimate."""

    message: str  # "GPS_INPUT", "VISION_POSITION_ESTIMATE" or "" (nothing sent)
    sent: bool
    reason: str  # why not sent ("" when sent)
    fix_type: int | None = None
    horiz_accuracy_m: float | None = None
