"""MAVLink from a rover's autopilot (ArduPilot Rover, PX4): the messages the appliance reads, decoded
into typed readings, and the link's fault rules.  Pure: pymavlink's decoded message objects (or
fields) and a receive time in, frozen records and :class:`Fault` records out; no clock, no port.

Read (common dialect, MAVLink 2; pymavlink decodes and encodes every frame):

- ``HEARTBEAT``: armed state (``base_mode & MAV_MODE_FLAG_SAFETY_ARMED``) and mode (pymavlink's
  ``mode_string_v10``: ArduPilot's or PX4's mode name) -> :class:`Heartbeat`.
- ``LOCAL_POSITION_NED`` (x north, y east, metres from the autopilot's origin; NED, true north) or
  ``ODOMETRY`` in ``MAV_FRAME_LOCAL_NED`` with its pose covariance where given -> :class:`LocalPosition`.
- ``ATTITUDE`` (roll, pitch, yaw in radians; yaw clockwise from north) -> :class:`Attitude` in degrees.
- ``GLOBAL_POSITION_INT`` -> :class:`GlobalPosition`.

Fault rules (:class:`LinkMonitor`), each a :class:`Fault` to log and count, never an exception:
a message from another system id than the autopilot's is ignored; a message whose fields are NaN is
rejected (:func:`reading_of` raises :class:`ProtocolError`, the caller counts it); per message type,
``time_boot_ms`` going back by less than the reorder window is an out-of-order message (ignored),
by more is a reboot (every stream's clock restarts); no message for longer than the link timeout is
a silent link (once per silence).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any, Union

from appliance.errors import ProtocolError
from appliance.extras import require

mavlink2 = require("pymavlink.dialects.v20.common", "MAVLink odometry ([devices.odometry] kind = \"mavlink\")")
mavutil = require("pymavlink.mavutil", "MAVLink odometry ([devices.odometry] kind = \"mavlink\")")

#: message types read from the autopilot
READ_TYPES = ("HEARTBEAT", "LOCAL_POSITION_NED", "ODOMETRY", "ATTITUDE", "GLOBAL_POSITION_INT")


class FaultKind(str, enum.Enum):
    FOREIGN_SYSTEM = "message from another system id"
    NAN_FIELD = "message with NaN fields"
    OUT_OF_ORDER = "out-of-order message"
    REBOOT = "autopilot reboot"
    FRAME_RESET = "position frame reset"
    LINK_SILENT = "link silent"
    LINK_ERROR = "link error"
    BAD_FRAME = "bad MAVLink frame"
    UNSUPPORTED = "unsupported message content"


@dataclass(frozen=True)
class Fault:
    """One fault of the link: what and a one-line detail built from the offending values."""

    kind: FaultKind
    detail: str

    def text(self) -> str:
        return f"{self.kind.value}: {self.detail}"


@dataclass(frozen=True)
class Heartbeat:
    system_id: int
    armed: bool
    mode: str
    autopilot: int  # MAV_AUTOPILOT
    vehicle_type: int  # MAV_TYPE
    receive_time_ns: int = 0


@dataclass(frozen=True)
class LocalPosition:
    """The autopilot's position in its local frame (m, north and east of its origin, down), its
    horizontal speed (m/s; NaN when not given) and, from ODOMETRY, the variances of north and east
    (m^2; None when not given) and the estimator's reset counter (None when not given)."""

    time_boot_ms: int
    north_m: float
    east_m: float
    down_m: float
    speed_m_s: float
    var_north_m2: float | None = None
    var_east_m2: float | None = None
    reset_counter: int | None = None
    receive_time_ns: int = 0


@dataclass(frozen=True)
class Attitude:
    """Roll and pitch (deg) and heading (deg clockwise from true north, [0, 360))."""

    time_boot_ms: int
    roll_deg: float
    pitch_deg: float
    heading_deg: float
    receive_time_ns: int = 0


@dataclass(frozen=True)
class GlobalPosition:
    time_boot_ms: int
    lat_deg: float
    lon_deg: float
    alt_m: float  # above mean sea level
    heading_deg: float | None  # None: unknown (UINT16_MAX)
    receive_time_ns: int = 0


Reading = Union[Heartbeat, LocalPosition, Attitude, GlobalPosition]  # noqa: UP007 (a runtime alias on 3.10)


def _finite(msg_type: str, **values: float) -> None:
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ProtocolError(f"{msg_type}: {', '.join(bad)} not finite ({', '.join(f'{k}={values[k]}' for k in bad)})")


def _odometry(msg: Any, now_ns: int) -> LocalPosition:
    if msg.frame_id != mavlink2.MAV_FRAME_LOCAL_NED:
        raise ProtocolError(f"ODOMETRY: frame_id {msg.frame_id} is not MAV_FRAME_LOCAL_NED "
                            f"({mavlink2.MAV_FRAME_LOCAL_NED}); not read")
    _finite("ODOMETRY", x=msg.x, y=msg.y, z=msg.z)
    cov = list(msg.pose_covariance)
    # the upper triangle of the 6x6 pose covariance, row-major: [0] is x-x (north), [6] is y-y (east)
    var_n = float(cov[0]) if math.isfinite(cov[0]) and cov[0] >= 0 else None
    var_e = float(cov[6]) if var_n is not None and math.isfinite(cov[6]) and cov[6] >= 0 else None
    speed = math.hypot(msg.vx, msg.vy)  # NaN when unknown, whatever the velocity's frame
    time_ms = int(msg.time_usec // 1000)
    return LocalPosition(time_ms, float(msg.x), float(msg.y), float(msg.z), speed,
                         var_n if var_e is not None else None, var_e, int(msg.reset_counter), now_ns)


def reading_of(msg: Any, receive_time_ns: int = 0) -> Reading | None:
    """The reading of one decoded pymavlink message (None for a type not read); a message whose
    fields are NaN raises :class:`ProtocolError` naming them."""
    kind = msg.get_type()
    if kind == "HEARTBEAT":
        armed = bool(msg.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)
        return Heartbeat(msg.get_srcSystem(), armed, str(mavutil.mode_string_v10(msg)), int(msg.autopilot),
                         int(msg.type), receive_time_ns)
    if kind == "LOCAL_POSITION_NED":
        _finite(kind, x=msg.x, y=msg.y, z=msg.z)
        return LocalPosition(int(msg.time_boot_ms), float(msg.x), float(msg.y), float(msg.z),
                             math.hypot(msg.vx, msg.vy), receive_time_ns=receive_time_ns)
    if kind == "ODOMETRY":
        return _odometry(msg, receive_time_ns)
    if kind == "ATTITUDE":
        _finite(kind, roll=msg.roll, pitch=msg.pitch, yaw=msg.yaw)
        return Attitude(int(msg.time_boot_ms), math.degrees(msg.roll), math.degrees(msg.pitch),
                        math.degrees(msg.yaw) % 360.0, receive_time_ns)
    if kind == "GLOBAL_POSITION_INT":
        hdg = None if msg.hdg == 65535 else msg.hdg / 100.0
        return GlobalPosition(int(msg.time_boot_ms), msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1000.0, hdg,
                              receive_time_ns)
    return None


def time_boot_ms_of(msg: Any) -> int | None:
    """The autopilot's time since boot a message carries (ms), or None (HEARTBEAT carries none)."""
    if hasattr(msg, "time_boot_ms"):
        return int(msg.time_boot_ms)
    if msg.get_type() == "ODOMETRY":
        return int(msg.time_usec // 1000)
    return None


@dataclass
class LinkMonitor:
    """The link's fault rules over the messages received (sender, type, time since boot, receive time).

    ``check`` says whether a message is taken and which fault it raises; ``silence`` whether the
    link has been silent for longer than ``link_timeout_ns`` (one fault per silence).  ``boots``
    counts the reboots seen; ``counts`` every fault by kind."""

    system_id: int
    component_id: int  # 0: any component of the system
    reorder_window_ms: int
    link_timeout_ns: int
    start_ns: int = 0
    boots: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    other_components: int = 0
    _last_ms: dict[str, int] = field(default_factory=dict)
    _last_rx_ns: int | None = None
    _silent: bool = False

    def count(self, kind: FaultKind) -> None:
        self.counts[kind.value] = self.counts.get(kind.value, 0) + 1

    def check(self, src_system: int, src_component: int, msg_type: str, time_boot_ms: int | None,
              receive_time_ns: int) -> tuple[bool, Fault | None]:
        """(taken, fault): whether the message is read, and the fault it is (None for none)."""
        if src_system != self.system_id:
            self.count(FaultKind.FOREIGN_SYSTEM)
            return False, Fault(FaultKind.FOREIGN_SYSTEM, f"{msg_type} from system {src_system} "
                                                          f"(the autopilot is system {self.system_id}): ignored")
        if self.component_id and src_component != self.component_id:
            self.other_components += 1  # a camera or gimbal of the same vehicle: not the autopilot, not a fault
            return False, None
        self._last_rx_ns = receive_time_ns
        self._silent = False
        if time_boot_ms is None:
            return True, None
        last = self._last_ms.get(msg_type)
        if last is not None and time_boot_ms < last:
            if last - time_boot_ms > self.reorder_window_ms:
                self.boots += 1
                self._last_ms = {msg_type: time_boot_ms}
                self.count(FaultKind.REBOOT)
                return True, Fault(FaultKind.REBOOT, f"{msg_type} time_boot_ms went back from {last} to "
                                                     f"{time_boot_ms}: the position frame restarts")
            self.count(FaultKind.OUT_OF_ORDER)
            return False, Fault(FaultKind.OUT_OF_ORDER, f"{msg_type} time_boot_ms {time_boot_ms} after {last}: "
                                                        "ignored")
        self._last_ms[msg_type] = time_boot_ms
        return True, None

    def silence(self, now_ns: int) -> Fault | None:
        """A LINK_SILENT fault the first time the link has been silent for longer than the timeout."""
        since = self._last_rx_ns if self._last_rx_ns is not None else self.start_ns
        if self._silent or now_ns - since <= self.link_timeout_ns:
            return None
        self._silent = True
        self.count(FaultKind.LINK_SILENT)
        silent_s, timeout_s = (now_ns - since) / 1e9, self.link_timeout_ns / 1e9
        return Fault(FaultKind.LINK_SILENT, f"no message from system {self.system_id} for {silent_s:.1f} s "
                                            f"(timeout {timeout_s:g} s)")
