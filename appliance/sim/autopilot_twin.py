"""The simulated autopilot: speaks MAVLink 2 (pymavlink) over a real UDP socket or a pty as ArduPilot
Rover or PX4 does, following the simulated rover.

It sends HEARTBEAT once a (simulated) second and LOCAL_POSITION_NED, ATTITUDE and GLOBAL_POSITION_INT
(and, with ``send_odometry``, ODOMETRY with its pose covariance, as PX4 does) a few times a second.  Its
local frame starts at zero where it boots; the position follows the rover's legs at ``speed_m_s``
(:meth:`AutopilotTwin.drive`, called when :class:`appliance.sim.rover_twin.RoverTwin` moves the world)
with a drift as dead reckoning's: each leg adds a Gaussian error of ``drift_per_m`` times its length
per axis, growing along the leg, and the covariance grows to match.  :meth:`AutopilotTwin.reboot`
restarts it: silent for ``reboot_silence_s``, then ``time_boot_ms`` from zero and the frame at zero
where the rover stands.  Every GPS_INPUT and VISION_POSITION_ESTIMATE it receives is kept in
:attr:`AutopilotTwin.received` (decoded by pymavlink).

Times are the simulated world's (:class:`appliance.sim.world.SimClock`): with ``time_rate`` 20 a
simulated second of heartbeat is a twentieth of a real one.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from appliance.drivers.mavlink import mavlink2
from appliance.drivers.mavlink_output import EARTH_RADIUS_M
from appliance.sim.pty_port import PtyPort
from appliance.sim.rover_twin import Leg, RoverTwin
from appliance.sim.world import SimWorld

MAV_TYPE_GROUND_ROVER = 10
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_STATE_ACTIVE = 4
ARMED_CUSTOM = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
ROVER_MODE_HOLD = 4  # ArduPilot Rover's HOLD
TICK_S = 0.02  # real seconds between two looks at the clock


class TwinLink(Protocol):
    def write(self, data: bytes) -> None: ...

    def read(self) -> bytes: ...

    def close(self) -> None: ...


class UdpTwinLink:
    """The autopilot's side of a UDP link: sends to the appliance's port, reads its replies."""

    def __init__(self, peer: tuple[str, int]) -> None:
        self.peer = peer
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.peer)
        except OSError:
            pass  # nobody listening: as a radio talking to no one

    def read(self) -> bytes:
        try:
            return self.sock.recv(65535)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        self.sock.close()


class PtyTwinLink:
    """The autopilot's side of a serial link on a :class:`PtyPort` (the appliance opens its path)."""

    def __init__(self, port: PtyPort) -> None:
        self.port = port

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def read(self) -> bytes:
        return self.port.read(4096, 0.0)

    def close(self) -> None:
        self.port.close()


@dataclass(frozen=True)
class Received:
    """A message the twin received, decoded, and its simulated time of arrival (s)."""

    message: Any
    time_s: float


class AutopilotTwin:
    def __init__(self, world: SimWorld, link: TwinLink, seed: int, drift_per_m: float = 0.05,
                 speed_m_s: float = 5.0, rate_hz: float = 4.0, system_id: int = 1, component_id: int = 1,
                 send_odometry: bool = False, reboot_silence_s: float = 2.0) -> None:
        self.world, self.link, self.clock = world, link, world.clock
        self.rng = np.random.default_rng(seed)
        self.drift_per_m, self.speed_m_s, self.period_s = drift_per_m, speed_m_s, 1.0 / rate_hz
        self.send_odometry, self.reboot_silence_s = send_odometry, reboot_silence_s
        self.mav = mavlink2.MAVLink(_Frames(), srcSystem=system_id, srcComponent=component_id)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.received: list[Received] = []
        self.boots = 0
        self._reboot_at: float | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._boot(self.clock.monotonic_s())

    # ---------------------------------------------------------------------------- the motion
    def _boot(self, now_s: float) -> None:
        self.boot_s = now_s
        self.quiet_until_s = now_s
        self.true_ne = np.zeros(2)  # true position in the frame (north, east) at the end of the last leg
        self.drift_ne = np.zeros(2)  # the reported position's error at the end of the last leg
        self.var_m2 = 0.0  # the variance the autopilot claims per axis
        self.leg: tuple[float, np.ndarray, np.ndarray, float, float] | None = None  # t0, delta, drift, duration, var
        self.home = (self.world.lat_deg, self.world.lon_deg)
        self._next_hb = self._next_pos = now_s

    def drive(self, east_m: float, north_m: float, reboot_at: float | None = None) -> None:
        """Start a leg of (east, north) metres from where the rover stands (in simulated time);
        ``reboot_at``: reboot when this fraction of the leg is driven (a fault to inject)."""
        with self._lock:
            now = self.clock.monotonic_s()
            self._reboot_at = reboot_at
            self._finish_leg(now)
            length = math.hypot(east_m, north_m)
            sigma = self.drift_per_m * length
            drift = self.rng.normal(0.0, sigma, 2) if sigma > 0 else np.zeros(2)
            self.leg = (now, np.array([north_m, east_m]), drift, max(length / self.speed_m_s, 1e-3), sigma ** 2)

    def _finish_leg(self, now_s: float) -> None:
        if self.leg is not None and now_s >= self.leg[0] + self.leg[3]:
            _, delta, drift, _, var = self.leg
            self.true_ne, self.drift_ne, self.var_m2 = self.true_ne + delta, self.drift_ne + drift, self.var_m2 + var
            self.leg = None

    def state(self, now_s: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(reported north/east (m), velocity north/east (m/s), variance per axis (m^2)) at ``now_s``."""
        self._finish_leg(now_s)
        if self.leg is None:
            return self.true_ne + self.drift_ne, np.zeros(2), self.var_m2
        t0, delta, drift, duration, var = self.leg
        frac = min(max((now_s - t0) / duration, 0.0), 1.0)
        pos = self.true_ne + self.drift_ne + frac * (delta + drift)
        return pos, (delta + drift) / duration, self.var_m2 + frac * var

    @property
    def driving(self) -> bool:
        with self._lock:
            self._finish_leg(self.clock.monotonic_s())
            return self.leg is not None

    def reboot(self) -> None:
        """Restart: silent for ``reboot_silence_s``, then time and frame from zero where the rover is (a
        leg under way goes on in the new frame)."""
        with self._lock:
            self._reboot(self.clock.monotonic_s())

    def _reboot(self, now: float) -> None:
        self._reboot_at = None
        self._finish_leg(now)
        rest = None
        if self.leg is not None:
            t0, delta, drift, duration, var = self.leg
            done = min(max((now - t0) / duration, 0.0), 1.0)
            rest = (1.0 - done) * delta, (1.0 - done) * drift, (1.0 - done) * duration, (1.0 - done) * var
        self.boots += 1
        self._boot(now + self.reboot_silence_s)
        self.quiet_until_s = self.boot_s
        if rest is not None:
            delta, drift, duration, var = rest
            self.leg = (self.boot_s, delta, drift, max(duration, 1e-3), var)
            # the world stands at the leg's end already: the new frame's zero is the rest of the leg back
            self.home = _offset(self.world.lat_deg, self.world.lon_deg, -delta[0], -delta[1])

    # ---------------------------------------------------------------------------- the wire
    def _send(self, msg: Any) -> None:
        frames = self.mav.file
        frames.data = b""
        self.mav.send(msg)
        self.link.write(frames.data)

    def _global(self, ne: np.ndarray) -> tuple[int, int]:
        lat, lon = _offset(*self.home, float(ne[0]), float(ne[1]))
        return int(round(lat * 1e7)), int(round(lon * 1e7))

    def _emit(self, now_s: float) -> None:
        leg = self.leg
        if self._reboot_at is not None and leg is not None and now_s >= leg[0] + self._reboot_at * leg[3]:
            self._reboot(now_s)
        if now_s < self.quiet_until_s:
            return
        ms = int((now_s - self.boot_s) * 1000)
        if now_s >= self._next_hb:
            self._next_hb = now_s + 1.0
            self._send(self.mav.heartbeat_encode(MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, ARMED_CUSTOM,
                                                 ROVER_MODE_HOLD, MAV_STATE_ACTIVE))
        if now_s < self._next_pos:
            return
        self._next_pos = now_s + self.period_s
        pos, vel, var = self.state(now_s)
        w = self.world
        heading = math.radians(w.heading_deg)
        # the tilts towards north and east seen along and across the rover's heading
        pitch = math.radians(w.tilt_north_deg * math.cos(heading) + w.tilt_east_deg * math.sin(heading))
        roll = math.radians(-w.tilt_north_deg * math.sin(heading) + w.tilt_east_deg * math.cos(heading))
        self._send(self.mav.local_position_ned_encode(ms, pos[0], pos[1], 0.0, vel[0], vel[1], 0.0))
        self._send(self.mav.attitude_encode(ms, roll, pitch, (heading + math.pi) % (2 * math.pi) - math.pi,
                                            0.0, 0.0, 0.0))
        lat, lon = self._global(pos)
        self._send(self.mav.global_position_int_encode(ms, lat, lon, int(w.ground_elevation_m * 1000), 1500,
                                                       int(vel[0] * 100), int(vel[1] * 100), 0,
                                                       int(round(w.heading_deg * 100)) % 36000))
        if self.send_odometry:
            cov = [float("nan")] * 21
            cov[0] = cov[6] = var
            cov[1] = 0.0
            self._send(self.mav.odometry_encode(ms * 1000, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD,
                                                pos[0], pos[1], 0.0, [1.0, 0.0, 0.0, 0.0], vel[0], vel[1], 0.0,
                                                0.0, 0.0, 0.0, cov, [float("nan")] * 21, self.boots % 256))

    def _receive(self) -> None:
        data = self.link.read()
        if not data:
            return
        now = self.clock.monotonic_s()
        for msg in self.parser.parse_buffer(data) or []:
            if msg.get_type() in ("GPS_INPUT", "VISION_POSITION_ESTIMATE"):
                self.received.append(Received(msg, now))

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                self._emit(self.clock.monotonic_s())
                self._receive()
            self._stop.wait(TICK_S)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="autopilot-twin", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.link.close()


def _offset(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    lat = lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    return lat, lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat_deg))))


class _Frames:
    """The file pymavlink's encoder writes one frame to."""

    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data += bytes(data)


class MavlinkRover:
    """The rover twin's legs told to the autopilot twin too: ``drive()`` as :meth:`RoverTwin.drive`;
    the autopilot reboots halfway through leg ``reboot_leg`` (from 1; None: never)."""

    def __init__(self, rover: RoverTwin, autopilot: AutopilotTwin, reboot_leg: int | None = None,
                 on_leg: Callable[[Leg], None] | None = None) -> None:
        self.rover, self.autopilot, self.reboot_leg, self.on_leg = rover, autopilot, reboot_leg, on_leg

    @property
    def legs(self) -> list[Leg]:
        return self.rover.legs

    def drive(self) -> Leg:
        leg = self.rover.drive()
        self.autopilot.drive(leg.east_m, leg.north_m, 0.5 if len(self.rover.legs) == self.reboot_leg else None)
        if self.on_leg is not None:
            self.on_leg(leg)
        return leg
