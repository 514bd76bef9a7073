"""The appliance's devices behind one interface: :func:`build_devices` wires the drivers to their
sources, :func:`open_hardware_platform` to the devices named in ``[devices.*]``.

The simulated twins (:func:`appliance.sim.platform.open_sim_platform`) speak the same wire
protocols and call :func:`build_devices` too, so the same drivers run in both cases; the caller
(the command line, :mod:`appliance.cli._platform`) chooses between them.  The returned
:class:`Devices` has the attributes the acquisition layer's ``Platform`` has (``clock``, ``tilt``,
``compass``, ``stage``, ``camera``, ``gps``, ``leveller``, ``odometry``) plus ``heading``; see
:mod:`appliance.drivers.devices` for each device's methods.  A device not configured (empty
``source``) is ``None``.  Always ``close()`` it (or use it as a context manager): that stops the
twins and closes the ports.  Calibrations arrive as objects (:class:`DeviceCalibration`); the
drivers read no file.

Example::

    with open_hardware_platform(config, load_device_calibration(config.devices)) as p:
        fixes = p.gps.poll()
        p.stage.move_to(90.0)
        frame = p.camera.capture()
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from appliance.config import CompassKind, Config, InclinometerKind, OdometryKind
from appliance.drivers.accelerometer import Adxl345, TiltOffset
from appliance.drivers.devices import AccelTilt, MagnetometerCompass, NmeaCompass, PtuStage, SystemClock
from appliance.drivers.gps_reader import GpsReader, GpsSourceOptions, open_gps
from appliance.drivers.i2c import I2cBus, open_smbus
from appliance.drivers.magnetometer import HardSoftIron, Hmc5883l
from appliance.drivers.odometry_reader import OdometryReader, open_odometry
from appliance.drivers.ptu import PanTiltUnit
from appliance.drivers.transport import Backoff, ReconnectingStream, open_serial
from appliance.errors import DeviceError

if TYPE_CHECKING:
    from appliance.drivers.camera import V4l2Camera
    from appliance.drivers.mavlink_reader import MavlinkLink

log = logging.getLogger(__name__)


class Clock(Protocol):
    """UTC time (ns), a monotonic clock and sleep: the system's, or the simulated world's."""

    def now_ns(self) -> int: ...

    def monotonic_s(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class Leveller(Protocol):
    """Whoever adjusts the tripod: a person reading the guidance, or the simulated one."""

    def instruct(self, instruction: str) -> None: ...


@dataclass
class Devices:
    clock: Clock
    gps: GpsReader | None
    tilt: AccelTilt | NmeaCompass | None
    compass: MagnetometerCompass | None
    heading: MagnetometerCompass | NmeaCompass | None
    stage: PtuStage | None
    camera: V4l2Camera | None
    leveller: Leveller | None = None
    odometry: OdometryReader | MavlinkLink | None = None
    autopilot: MavlinkLink | None = None  # the MAVLink link, also the odometry ([devices.odometry] kind = "mavlink")
    _closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        for c in reversed(self._closers):
            try:
                c()
            except (OSError, DeviceError) as exc:
                log.warning("closing a device: %s", exc)
        self._closers.clear()

    def __enter__(self) -> Devices:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class DeviceCalibration:
    """The calibrations the drivers apply: the magnetometer's hard/soft iron, the inclinometer's offsets."""

    hard_soft_iron: HardSoftIron = field(default_factory=HardSoftIron)
    tilt_offset: TiltOffset = field(default_factory=TiltOffset)


def build_devices(
    config: Config,
    gps_source: str,
    stage_source: str,
    compass_nmea_source: str,
    bus: I2cBus | None,
    camera: V4l2Camera | None,
    clock: Clock,
    calibration: DeviceCalibration,
    odometry_source: str = "",
) -> Devices:
    """Wire the drivers to the given sources (shared by the hardware and the simulated platform);
    ``odometry_source`` is the line's source or, for ``[devices.odometry] kind = "mavlink"``, the link's URL."""
    d = config.devices
    clock_ns = clock.now_ns
    closers: list[Callable[[], None]] = []
    backoff = Backoff(d.gps.reconnect_initial_s, d.gps.reconnect_max_s)
    try:
        gps = None
        if gps_source:
            gps = open_gps(gps_source, GpsSourceOptions(d.gps.baudrate, d.gps.read_timeout_s), backoff=backoff,
                           clock_ns=clock_ns)
            closers.append(gps.close)
        accel_tilt: AccelTilt | None = None
        compass: MagnetometerCompass | None = None
        heading: MagnetometerCompass | NmeaCompass | None = None
        if d.inclinometer.kind is InclinometerKind.ADXL345 and bus is not None:
            try:
                accel_tilt = AccelTilt(Adxl345(bus, d.inclinometer.i2c_address), d.inclinometer.samples,
                                 calibration.tilt_offset, clock_ns)
            except DeviceError as exc:
                log.warning("inclinometer absent: %s", exc)
        nmea_compass = None
        if compass_nmea_source:
            src = compass_nmea_source
            stream = ReconnectingStream(lambda: open_serial(src, d.compass.baudrate, 0.05), backoff, name=src,
                                        initial=open_serial(src, d.compass.baudrate, 0.05))
            closers.append(stream.close)
            nmea_compass = NmeaCompass(stream, d.compass.tnt_angle_scale_deg, clock_ns)
        if d.compass.kind is CompassKind.HMC5883L and bus is not None:
            try:
                compass = MagnetometerCompass(Hmc5883l(bus, d.compass.i2c_address, d.compass.gain),
                                              calibration.hard_soft_iron, accel_tilt, clock_ns)
                heading = compass
            except DeviceError as exc:
                log.warning("magnetometer absent: %s", exc)
        elif d.compass.kind is CompassKind.NMEA:
            heading = nmea_compass
        tilt: AccelTilt | NmeaCompass | None = accel_tilt
        if d.inclinometer.kind is InclinometerKind.NMEA and nmea_compass is not None:
            tilt = nmea_compass
        stage = None
        if stage_source:
            unit = PanTiltUnit(open_serial(stage_source, d.stage.baudrate, 0.05), d.stage.timeout_s,
                               d.stage.move_timeout_s, d.stage.position_tolerance)
            closers.append(unit.close)
            unit.set_speed_deg_s(d.stage.speed_deg_s)
            stage = PtuStage(unit)
        if camera is not None and hasattr(camera, "close"):
            closers.append(camera.close)
        odometry: OdometryReader | MavlinkLink | None = None
        autopilot = None
        o = d.odometry
        if odometry_source and o.kind is OdometryKind.MAVLINK:
            # pymavlink (an optional library, seconds of imports) loads only for a MAVLink autopilot
            from appliance.drivers.mavlink_reader import open_mavlink

            odometry = autopilot = open_mavlink(odometry_source, o, backoff=backoff, clock_ns=clock_ns)
            closers.append(autopilot.close)
        elif odometry_source:
            odometry = open_odometry(odometry_source, o.baudrate, o.read_timeout_s, backoff=backoff,
                                     clock_ns=clock_ns)
            closers.append(odometry.close)
    except BaseException:
        for c in reversed(closers):
            c()
        raise
    return Devices(clock, gps, tilt, compass, heading, stage, camera, odometry=odometry, autopilot=autopilot,
                   _closers=closers)


def uses_nmea_compass(config: Config) -> bool:
    """Whether the NMEA compass's port is needed (as the heading or as the inclinometer)."""
    d = config.devices
    return d.compass.kind is CompassKind.NMEA or d.inclinometer.kind is InclinometerKind.NMEA


def open_hardware_platform(config: Config, calibration: DeviceCalibration) -> Devices:
    """The devices of ``[devices.*]``; one that does not answer is logged and left out (None)."""
    d = config.devices
    bus = None
    if d.compass.kind is CompassKind.HMC5883L or d.inclinometer.kind is InclinometerKind.ADXL345:
        try:
            bus = open_smbus(d.compass.i2c_bus)
        except DeviceError as exc:
            log.warning("no I2C devices: %s", exc)
    camera = None
    if d.camera.intrinsics_file is not None:
        # the camera's driver and OpenCV load only when a camera is configured
        from appliance.drivers.camera import V4l2Camera
        from appliance.vision.intrinsics import load_intrinsics

        try:
            camera = V4l2Camera(d.camera, load_intrinsics(d.camera.intrinsics_file))
        except DeviceError as exc:
            log.warning("camera absent: %s", exc)
    compass_src = d.compass.nmea_source if uses_nmea_compass(config) else ""
    odometry_src = d.odometry.url if d.odometry.kind is OdometryKind.MAVLINK else d.odometry.source
    return build_devices(config, d.gps.source, d.stage.source, compass_src, bus, camera, SystemClock(), calibration,
                         odometry_src)
