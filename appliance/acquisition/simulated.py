"""A simulated platform for whole sessions: the DEM's scene, a tilted tripod, an iron-disturbed compass,
a pan stage, a GPS receiver, and faults to inject (unplugged device, stalled stage, black frames).

Time is simulated (:class:`SimClock` advances on ``sleep``), so a session with 30 s of GPS averaging
runs in the time its rendering takes.  Frames are rendered with :mod:`appliance.vision.synth` from
the DEM at the true position and pose; the compass sees the horizontal field of the true magnetic
heading (true heading minus declination) through a hard and soft iron distortion.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance.acquisition.platform import FieldReading, Frame, Platform, TiltReading
from appliance.drivers.gps import CovarianceType, FixQuality, GpsFix
from appliance.errors import DeviceError
from appliance.vision.camera import CameraPose
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.synth import SkylineFn, dem_skyline_fn, render_photo_from


class SimClock:
    def __init__(self, start_ns: int = 1_750_000_000_000_000_000) -> None:
        self._t_ns = start_ns

    def now_ns(self) -> int:
        return self._t_ns

    def monotonic_s(self) -> float:
        return self._t_ns / 1e9

    def sleep(self, seconds: float) -> None:
        self._t_ns += int(max(seconds, 0.0) * 1e9) + 1_000


@dataclass
class SimFaults:
    """Faults to inject: devices that vanish after N uses, a stage that stalls, black frames."""

    camera_unplugged_after: int | None = None  # captures before the camera disappears
    tilt_unplugged: bool = False
    gps_silent: bool = False
    stage_stall_at_deg: float | None = None  # the stage cannot pass this angle
    black_frames: frozenset[int] = frozenset()  # capture call numbers that return a black frame
    metal_nearby: bool = False  # distorts the field beyond any ellipse fit


@dataclass
class SimWorld:
    dem: Any
    lat_deg: float
    lon_deg: float
    heading_deg: float  # true heading of the head at stage angle 0
    declination_deg: float
    camera_height_m: float = 1.5
    tilt_east_deg: float = 1.5  # slope of the tripod's head plane (deg), up towards east
    tilt_north_deg: float = -1.0
    hard_iron: tuple[float, float] = (12.0, -7.0)
    soft_iron: tuple[tuple[float, float], tuple[float, float]] = ((1.1, 0.05), (0.05, 0.92))
    field_strength: float = 50.0
    gps_sigma_m: float = 2.0
    intrinsics: CameraIntrinsics = field(default_factory=lambda: CameraIntrinsics.from_fov(320, 240, 60.0))
    seed: int = 0
    faults: SimFaults = field(default_factory=SimFaults)
    stage_deg: float = 0.0
    captures: int = 0

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self._skyline_fn = tabulated_skyline_fn(
            dem_skyline_fn(self.dem, self.lat_deg, self.lon_deg, self.camera_height_m)
        )

    @property
    def yaw_deg(self) -> float:
        return (self.heading_deg + self.stage_deg) % 360.0

    def head_tilt(self) -> tuple[float, float]:
        """(roll, pitch) in degrees of the head at its current yaw (small angles)."""
        y = math.radians(self.yaw_deg)
        pitch = self.tilt_east_deg * math.sin(y) + self.tilt_north_deg * math.cos(y)
        roll = -(self.tilt_east_deg * math.cos(y) - self.tilt_north_deg * math.sin(y))
        return roll, pitch

    def render(self) -> np.ndarray:
        roll, pitch = self.head_tilt()
        pose = CameraPose(self.yaw_deg, pitch, roll)
        return render_photo_from(self._skyline_fn, pose, self.intrinsics, self.rng, scene_seed=self.seed)


def tabulated_skyline_fn(fn: SkylineFn, step_deg: float = 0.05) -> SkylineFn:
    """``fn`` rendered once every ``step_deg`` and interpolated (periodic) for every later call."""
    az = np.arange(0.0, 360.0, step_deg)
    el, dist = fn(az)
    el_filled = np.where(np.isfinite(el), el, -90.0)
    dist_filled = np.where(np.isfinite(dist), dist, np.nan)

    def tabulated(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.asarray(azimuth_deg, dtype=np.float64) % 360.0
        e = np.interp(a, az, el_filled, period=360.0)
        d = np.interp(a, az, np.nan_to_num(dist_filled, nan=0.0), period=360.0)
        return e, np.where(d > 0, d, np.nan)

    return tabulated


class SimTilt:
    def __init__(self, world: SimWorld, clock: SimClock, noise_deg: float = 0.02) -> None:
        self.world, self.clock, self.noise = world, clock, noise_deg

    def read_tilt(self) -> TiltReading:
        if self.world.faults.tilt_unplugged:
            raise DeviceError("inclinometer: no answer on the I2C bus (unplugged?)")
        roll, pitch = self.world.head_tilt()
        n = self.world.rng.normal(0.0, self.noise, 2)
        return TiltReading(self.clock.now_ns(), roll + float(n[0]), pitch + float(n[1]))


class SimCompass:
    def __init__(self, world: SimWorld, clock: SimClock, noise: float = 0.1) -> None:
        self.world, self.clock, self.noise = world, clock, noise

    def read_field(self) -> FieldReading:
        w = self.world
        mag = math.radians(w.yaw_deg - w.declination_deg)
        true_xy = np.array([math.cos(mag), -math.sin(mag)]) * w.field_strength
        xy = np.asarray(w.soft_iron) @ true_xy + np.asarray(w.hard_iron)
        if w.faults.metal_nearby:
            xy = xy + 0.4 * w.field_strength * np.array([math.cos(3 * mag), math.sin(2 * mag)])
        xy = xy + w.rng.normal(0.0, self.noise, 2)
        return FieldReading(self.clock.now_ns(), float(xy[0]), float(xy[1]), 30.0)


class SimStage:
    def __init__(self, world: SimWorld, clock: SimClock, speed_deg_s: float = 60.0) -> None:
        self.world, self.clock, self.speed = world, clock, speed_deg_s

    def move_to(self, angle_deg: float) -> float:
        w = self.world
        target = angle_deg % 360.0
        stall = w.faults.stage_stall_at_deg
        if stall is not None and w.stage_deg <= stall < target:
            target = stall
        self.clock.sleep(abs(target - w.stage_deg) / self.speed)
        w.stage_deg = target
        return target


class SimCamera:
    def __init__(self, world: SimWorld, clock: SimClock) -> None:
        self.world, self.clock = world, clock

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.world.intrinsics

    def capture(self) -> Frame:
        w = self.world
        if w.faults.camera_unplugged_after is not None and w.captures >= w.faults.camera_unplugged_after:
            raise DeviceError("camera: /dev/video0 disappeared (unplugged?)")
        n = w.captures
        w.captures += 1
        if n in w.faults.black_frames:
            return Frame(self.clock.now_ns(), np.zeros((w.intrinsics.height, w.intrinsics.width, 3), np.uint8))
        return Frame(self.clock.now_ns(), w.render())


class SimGps:
    """One fix per second around the true position, with the receiver's noise."""

    def __init__(self, world: SimWorld, clock: SimClock) -> None:
        self.world, self.clock = world, clock
        self._last_s: int | None = None

    def poll(self) -> list[GpsFix]:
        if self.world.faults.gps_silent:
            return []
        now = self.clock.now_ns()
        sec = now // 1_000_000_000
        if self._last_s is not None and sec == self._last_s:
            return []
        self._last_s = sec
        w = self.world
        dn, de = w.rng.normal(0.0, w.gps_sigma_m / math.sqrt(2), 2)
        lat = w.lat_deg + math.degrees(dn / 6_371_008.8)
        lon = w.lon_deg + math.degrees(de / (6_371_008.8 * math.cos(math.radians(w.lat_deg))))
        utc = dt.datetime.fromtimestamp(now / 1e9, tz=dt.timezone.utc)
        var = (w.gps_sigma_m**2) / 2
        return [
            GpsFix(
                utc,
                utc.time(),
                lat,
                lon,
                300.0,
                None,
                FixQuality.GPS,
                9,
                0.9,
                (var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, 4 * var),
                CovarianceType.DIAGONAL_KNOWN,
                now,
            )
        ]


class SimLeveller:
    """The person at the tripod: follows each instruction, correcting most of the error."""

    def __init__(self, world: SimWorld, gain: float = 0.7) -> None:
        self.world, self.gain = world, gain
        self.heard: list[str] = []

    def instruct(self, instruction: str) -> None:
        self.heard.append(instruction)
        w = self.world
        roll, pitch = w.head_tilt()
        if "leg (roll" in instruction:
            roll *= 1 - self.gain
        else:
            pitch *= 1 - self.gain
        y = math.radians(w.yaw_deg)
        # invert head_tilt: (pitch, -roll) = R(y) @ (east, north)
        w.tilt_east_deg = pitch * math.sin(y) - roll * math.cos(y)
        w.tilt_north_deg = pitch * math.cos(y) + roll * math.sin(y)


def simulated_platform(world: SimWorld, clock: SimClock | None = None) -> Platform:
    clock = clock or SimClock()
    return Platform(
        clock=clock,
        tilt=SimTilt(world, clock),
        compass=SimCompass(world, clock),
        stage=SimStage(world, clock),
        camera=SimCamera(world, clock),
        gps=SimGps(world, clock),
        leveller=SimLeveller(world),
        camera_height_m=world.camera_height_m,
    )
