"""``open_platform(config)``: the appliance's devices, real or simulated, behind one interface.

``[platform] kind = "hardware"`` opens the devices named in ``[devices.*]``; ``kind = "sim"`` starts
the simulated twins of ``[sim]`` (:mod:`appliance.sim.platform`), which speak the same wire
protocols, so the same drivers run in both cases.  The returned :class:`Devices` has the attributes
the acquisition layer's ``Platform`` has (``clock``, ``tilt``, ``compass``, ``stage``, ``camera``,
``gps``, ``leveller``, ``camera_height_m``) plus ``heading``; see :mod:`appliance.drivers.devices`
for each device's methods.  A device not configured (empty ``source``) is ``None``.  Always
``close()`` it (or use it as a context manager): that stops the twins and closes the ports.

Example::

    with open_platform(load_config("viper.toml")) as p:
        fixes = p.gps.poll()
        p.stage.move_to(90.0)
        frame = p.camera.capture()
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomlkit
import tomlkit.exceptions

from appliance.config import Config
from appliance.drivers.accelerometer import CALIBRATION_TABLE as INCLINOMETER_TABLE
from appliance.drivers.accelerometer import Adxl345, TiltOffset
from appliance.drivers.devices import AccelTilt, MagnetometerCompass, NmeaCompass, PtuStage, SystemClock
from appliance.drivers.gps_reader import GpsReader, GpsSourceOptions, open_gps
from appliance.drivers.i2c import I2cBus, open_smbus
from appliance.drivers.magnetometer import CALIBRATION_TABLE as MAGNETOMETER_TABLE
from appliance.drivers.magnetometer import HardSoftIron, Hmc5883l
from appliance.drivers.ptu import PanTiltUnit
from appliance.drivers.transport import Backoff, ReconnectingStream, open_serial
from appliance.errors import ConfigError, DeviceError

log = logging.getLogger(__name__)


@dataclass
class Devices:
    clock: Any
    gps: GpsReader | None
    tilt: Any
    compass: Any
    heading: Any
    stage: PtuStage | None
    camera: Any
    leveller: Any = None
    camera_height_m: float = 1.5
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


def _calibration_table(config: Config, name: str) -> tuple[dict[str, Any] | None, str]:
    """The ``[name]`` table of ``[devices] calibration_file`` (None if no file or no such table)."""
    path = config.devices.calibration_file
    if path is None:
        return None, ""
    try:
        doc = tomlkit.parse(Path(path).read_text(encoding="utf-8")).unwrap()
    except FileNotFoundError:
        raise ConfigError(f"devices.calibration_file: {path}: file not found") from None
    except tomlkit.exceptions.ParseError as exc:
        raise ConfigError(f"devices.calibration_file: {path}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"devices.calibration_file: {path}: cannot read: {exc}") from None
    table = doc.get(name)
    if table is not None and not isinstance(table, dict):
        raise ConfigError(f"{path}: {name} is not a table")
    return table, f"{path} [{name}]"


def calibration_of(config: Config) -> HardSoftIron:
    """The magnetometer's hard/soft iron (tesla): the calibration file's [compass], else [devices.compass]."""
    c = config.devices.compass
    inline = HardSoftIron(c.hard_iron_offset, c.soft_iron_matrix)
    table, source = _calibration_table(config, MAGNETOMETER_TABLE)
    if table is None:
        return inline
    if inline != HardSoftIron():
        raise ConfigError(f"compass calibration given twice: in [devices.compass] and in {source}; keep one")
    return HardSoftIron.from_table(table, source)


def tilt_offset_of(config: Config) -> TiltOffset:
    """The inclinometer's offsets (deg): the calibration file's [inclinometer], else [devices.inclinometer]."""
    c = config.devices.inclinometer
    inline = TiltOffset(c.pitch_offset_deg, c.roll_offset_deg)
    table, source = _calibration_table(config, INCLINOMETER_TABLE)
    if table is None:
        return inline
    if inline != TiltOffset():
        raise ConfigError(f"inclinometer offsets given twice: in [devices.inclinometer] and in {source}; keep one")
    return TiltOffset.from_table(table, source)


def build_devices(
    config: Config,
    gps_source: str,
    stage_source: str,
    compass_nmea_source: str,
    bus: I2cBus | None,
    camera: Any,
    clock: Any,
) -> Devices:
    """Wire the drivers to the given sources (shared by the hardware and the simulated platform)."""
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
        tilt: Any = None
        compass: Any = None
        heading: Any = None
        if d.inclinometer.kind == "adxl345" and bus is not None:
            try:
                tilt = AccelTilt(Adxl345(bus, d.inclinometer.i2c_address), d.inclinometer.samples,
                                 tilt_offset_of(config),
                                 clock_ns)
            except DeviceError as exc:
                log.warning("inclinometer absent: %s", exc)
        nmea_compass = None
        if compass_nmea_source:
            src = compass_nmea_source
            stream = ReconnectingStream(lambda: open_serial(src, d.compass.baudrate, 0.05), backoff, name=src,
                                        initial=open_serial(src, d.compass.baudrate, 0.05))
            closers.append(stream.close)
            nmea_compass = NmeaCompass(stream, d.compass.tnt_angle_scale_deg, clock_ns)
        if d.compass.kind == "hmc5883l" and bus is not None:
            try:
                compass = MagnetometerCompass(Hmc5883l(bus, d.compass.i2c_address, d.compass.gain),
                                              calibration_of(config), tilt, clock_ns)
                heading = compass
            except DeviceError as exc:
                log.warning("magnetometer absent: %s", exc)
        elif d.compass.kind == "nmea":
            heading = nmea_compass
        if d.inclinometer.kind == "nmea" and nmea_compass is not None:
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
    except BaseException:
        for c in reversed(closers):
            c()
        raise
    return Devices(clock, gps, tilt, compass, heading, stage, camera,
                   camera_height_m=config.terrain.camera_height_m, _closers=closers)


def open_hardware_platform(config: Config) -> Devices:
    d = config.devices
    bus = None
    if d.compass.kind == "hmc5883l" or d.inclinometer.kind == "adxl345":
        try:
            bus = open_smbus(d.compass.i2c_bus)
        except DeviceError as exc:
            log.warning("no I2C devices: %s", exc)
    camera = None
    if d.camera.intrinsics_file is not None:
        from appliance.drivers.camera import V4l2Camera
        from appliance.vision.intrinsics import load_intrinsics

        try:
            camera = V4l2Camera(d.camera, load_intrinsics(d.camera.intrinsics_file))
        except DeviceError as exc:
            log.warning("camera absent: %s", exc)
    compass_src = d.compass.nmea_source if "nmea" in (d.compass.kind, d.inclinometer.kind) else ""
    return build_devices(config, d.gps.source, d.stage.source, compass_src, bus, camera, SystemClock())


def open_platform(config: Config) -> Devices:
    """The devices of ``config.platform.kind`` ("hardware" or "sim")."""
    for name, kind in (("compass", config.devices.compass.kind), ("inclinometer", config.devices.inclinometer.kind)):
        allowed = ("hmc5883l", "nmea") if name == "compass" else ("adxl345", "nmea")
        if kind not in allowed:
            raise ConfigError(f"devices.{name}.kind: expected one of {allowed}, got {kind!r}")
    if config.platform.kind == "hardware":
        return open_hardware_platform(config)
    from appliance.sim.platform import open_sim_platform

    return open_sim_platform(config)
