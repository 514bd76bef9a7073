"""What the procedures need from the platform: small protocols over the devices, and their records.

The tilt sensor and the compass ride on the pan head with the camera, so their readings are in the
camera's frame: ``roll_deg`` positive when the right-hand side of the image goes down, ``pitch_deg``
positive nose up (as :mod:`appliance.vision.camera`), the magnetic field's ``x`` along the optical
axis (forward), ``y`` to the right, ``z`` down.  Stage angles are degrees clockwise seen from
above.  Times are UTC nanoseconds.  Every device call may raise :class:`DeviceError` (unplugged,
stalled); the session degrades instead of dying.  :func:`platform_of` takes the devices of
:func:`appliance.drivers.factory.build_devices` (the real drivers, on hardware or on the simulated
twins), whose records have these fields.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from appliance.drivers.autopilot import PositionFix, RoverState, SentPosition
from appliance.drivers.gps import GpsFix
from appliance.drivers.odometry import OdometryReport
from appliance.vision.intrinsics import CameraIntrinsics

if TYPE_CHECKING:
    from appliance.drivers.factory import Devices


class TiltReading(Protocol):
    @property
    def time_ns(self) -> int: ...

    @property
    def roll_deg(self) -> float: ...

    @property
    def pitch_deg(self) -> float: ...


class FieldReading(Protocol):
    """Magnetic field in the head's frame (x forward, y right, z down), any consistent unit."""

    @property
    def time_ns(self) -> int: ...

    @property
    def x(self) -> float: ...

    @property
    def y(self) -> float: ...

    @property
    def z(self) -> float: ...


class Still(Protocol):
    """One camera frame as the procedures see it: HxWx3 uint8 BGR and its time."""

    @property
    def time_ns(self) -> int: ...

    @property
    def image(self) -> np.ndarray: ...


@dataclass(frozen=True)
class Frame:
    """One camera frame: HxWx3 uint8 BGR (a :class:`Still`), e.g. read back from a log."""

    time_ns: int
    image: np.ndarray


class Clock(Protocol):
    def now_ns(self) -> int: ...

    def monotonic_s(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class TiltSensor(Protocol):
    def read_tilt(self) -> TiltReading: ...


class Compass(Protocol):
    def read_field(self) -> FieldReading: ...


class Stage(Protocol):
    def move_to(self, angle_deg: float) -> float:
        """Command an absolute angle; return the angle the stage reports when it stopped."""
        ...


class Camera(Protocol):
    @property
    def intrinsics(self) -> CameraIntrinsics: ...

    def capture(self) -> Still: ...


class GpsSource(Protocol):
    def poll(self) -> list[GpsFix]:
        """Fixes completed since the last call (may be empty)."""
        ...

    def discard_pending(self) -> None:
        """Drop the input received and not read yet (a measurement starts now)."""
        ...


class Autopilot(Protocol):
    """A rover's autopilot (:class:`appliance.drivers.mavlink_reader.MavlinkLink`): its faults since
    the last call (one line each) and counted by kind, what it last said of the rover, and the estimate
    sent back to it."""

    def faults(self) -> list[str]: ...

    def counts(self) -> dict[str, int]: ...

    def state(self) -> RoverState: ...

    def send_position(self, fix: PositionFix) -> SentPosition: ...


class OdometrySource(Protocol):
    def poll(self) -> list[OdometryReport]:
        """Odometry lines completed since the last call (may be empty; waits at most a read timeout)."""
        ...


class Leveller(Protocol):
    """Whoever adjusts the tripod: a person reading the guidance, or a motorised leveller."""

    def instruct(self, instruction: str) -> None: ...


@dataclass
class Platform:
    """The devices of one appliance; None for a device that is absent."""

    clock: Clock
    tilt: TiltSensor | None
    compass: Compass | None
    stage: Stage | None
    camera: Camera | None
    gps: GpsSource | None
    leveller: Leveller | None
    odometry: OdometrySource | None = None
    autopilot: Autopilot | None = None


def platform_of(devices: Devices) -> Platform:
    """The procedures' view of :class:`appliance.drivers.factory.Devices` (same attribute names)."""
    return Platform(
        clock=devices.clock,
        tilt=devices.tilt,
        compass=devices.compass,
        stage=devices.stage,
        camera=devices.camera,
        gps=devices.gps,
        leveller=devices.leveller,
        odometry=devices.odometry,
        autopilot=devices.autopilot,
    )
