"""The configuration of the platform the daemons drive (:mod:`appliance.config` reads it): which one
(``[platform]``), the devices of the hardware platform (``[devices]``), and the simulated world, its
twins and the faults they inject (``[sim]``)."""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from appliance._config_checks import (
    UDP_SCHEME,
    _baud,
    _choices,
    _finite,
    _non_negative,
    _positive,
    _require,
    _within,
    udp_address,
)
from appliance.inputs import MAX_IMAGE_PIXELS

#: The longest side of a camera's frame (px); a frame's pixels are capped by the images' own cap.
MAX_CAMERA_SIDE = 20_000


class PlatformKind(str, enum.Enum):
    """Which devices the daemons drive."""

    SIM = "sim"
    HARDWARE = "hardware"


class CompassKind(str, enum.Enum):
    HMC5883L = "hmc5883l"  # I2C magnetometer
    NMEA = "nmea"  # HDG/HDM/HDT/PTNTHTM sentences on a serial port


class InclinometerKind(str, enum.Enum):
    ADXL345 = "adxl345"  # I2C accelerometer
    NMEA = "nmea"  # XDR pitch and roll sentences


@dataclass(frozen=True)
class PlatformConfig:
    """Which platform the daemons drive: real hardware or the simulated twins."""

    kind: PlatformKind = PlatformKind.SIM

    def __post_init__(self) -> None:
        _require(isinstance(self.kind, PlatformKind), "platform.kind", _choices(PlatformKind), self.kind)


@dataclass(frozen=True)
class GpsDeviceConfig:
    """The GPS receiver: ``source`` is a device path, a pyserial URL or a recorded log ("" = none)."""

    source: str = ""
    baudrate: int = 9600
    read_timeout_s: float = 0.5
    reconnect_initial_s: float = 0.1
    reconnect_max_s: float = 5.0

    def __post_init__(self) -> None:
        _baud("devices.gps.baudrate", self.baudrate)
        _positive("devices.gps.read_timeout_s", self.read_timeout_s)
        _positive("devices.gps.reconnect_initial_s", self.reconnect_initial_s)
        _require(math.isfinite(self.reconnect_max_s) and self.reconnect_max_s >= self.reconnect_initial_s,
                 "devices.gps.reconnect_max_s", f"a number >= reconnect_initial_s ({self.reconnect_initial_s:g})",
                 self.reconnect_max_s)


class OdometryKind(str, enum.Enum):
    LINE = "line"  # one ODO line per stop (appliance.drivers.odometry)
    MAVLINK = "mavlink"  # the autopilot's MAVLink position, cut into stops where the rover stands still


class PositionOutput(str, enum.Enum):
    """What the MAVLink link sends the autopilot after each estimate."""

    NONE = "none"
    GPS_INPUT = "gps_input"
    VISION_POSITION_ESTIMATE = "vision_position_estimate"


_MAVLINK_UDP = re.compile(r"(udpin|udpout|udp):(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/\[\]]*)):(?P<port>\d{1,5})")


def mavlink_udp_address(url: str, key: str) -> tuple[str, str, int] | None:
    """(mode, host, port) of ``udpin:HOST:PORT``, ``udpout:HOST:PORT`` or ``udp:HOST:PORT`` (= udpin);
    None for anything else (a serial device path or pyserial URL).  A malformed UDP URL raises naming ``key``."""
    if not url.startswith(("udpin:", "udpout:", "udp:")):
        return None
    m = _MAVLINK_UDP.fullmatch(url)
    _require(m is not None and int(m.group("port")) <= 65535, key,
             "udpin:HOST:PORT, udpout:HOST:PORT or udp:HOST:PORT with a port in [0, 65535]", url)
    assert m is not None
    mode = "udpin" if m.group(1) == "udp" else m.group(1)
    return mode, m.group("v6") or m.group("host") or "0.0.0.0", int(m.group("port"))


@dataclass(frozen=True)
class OdometryDeviceConfig:
    """The rover's odometry.  ``kind = "line"``: one line per stop (``appliance.drivers.odometry``) from
    ``source``, a device path or pyserial URL, or ``udp://HOST:PORT`` to listen on ("" = none).
    ``kind = "mavlink"``: the autopilot's MAVLink stream at ``url`` (``udpin:HOST:PORT`` to listen,
    ``udpout:HOST:PORT`` to send to, or a serial device at ``baudrate``; "" = none), a stop being where
    the rover stands still (``appliance.drivers.mavlink_odometry``); each estimate goes back as ``output``."""

    kind: OdometryKind = OdometryKind.LINE
    source: str = ""
    baudrate: int = 9600
    read_timeout_s: float = 0.5
    url: str = ""
    system_id: int = 1  # the autopilot's MAVLink system id: messages from any other are ignored and counted
    component_id: int = 1  # the autopilot's component id (0: any component of that system)
    own_system_id: int = 1  # the ids the appliance's own messages carry
    own_component_id: int = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
    link_timeout_s: float = 5.0  # no message from the autopilot for this long is a fault (link silent)
    sigma_per_m: float = 0.05  # the displacement's 1-sigma per metre driven, where no covariance comes with it
    moving_speed_m_s: float = 0.3  # faster than this the rover is driving
    settle_s: float = 3.0  # a stop: still (below moving_speed_m_s) this long after driving
    reorder_window_s: float = 2.0  # a timestamp this much older than the last is a reboot, less is out of order
    output: PositionOutput = PositionOutput.NONE
    output_min_interval_s: float = 1.0  # at most one position sent per this interval
    output_ambiguous: bool = False  # also send estimates that are not ok (GPS_INPUT with fix_type 0)

    def __post_init__(self) -> None:
        _require(isinstance(self.kind, OdometryKind), "devices.odometry.kind", _choices(OdometryKind), self.kind)
        _require(isinstance(self.output, PositionOutput), "devices.odometry.output", _choices(PositionOutput),
                 self.output)
        _baud("devices.odometry.baudrate", self.baudrate)
        _positive("devices.odometry.read_timeout_s", self.read_timeout_s)
        if self.source.startswith(UDP_SCHEME):
            udp_address(self.source, "devices.odometry.source")
        mavlink_udp_address(self.url, "devices.odometry.url")
        for key in ("system_id", "own_system_id"):
            _require(1 <= getattr(self, key) <= 255, f"devices.odometry.{key}", "an integer in [1, 255]",
                     getattr(self, key))
        for key in ("component_id", "own_component_id"):
            _require(0 <= getattr(self, key) <= 255, f"devices.odometry.{key}", "an integer in [0, 255]",
                     getattr(self, key))
        for key in ("link_timeout_s", "moving_speed_m_s", "settle_s", "reorder_window_s"):
            _positive(f"devices.odometry.{key}", getattr(self, key))
        _within("devices.odometry.sigma_per_m", self.sigma_per_m, 0.0, 1.0)
        _non_negative("devices.odometry.output_min_interval_s", self.output_min_interval_s)


@dataclass(frozen=True)
class CompassConfig:
    """The compass: an I2C HMC5883L (``kind = "hmc5883l"``) or NMEA HDG/HDM/HDT/PTNTHTM (``"nmea"``)."""

    kind: CompassKind = CompassKind.HMC5883L
    i2c_bus: int = 1
    i2c_address: int = 0x1E
    gain: int = 1  # HMC5883L gain code 0..7
    nmea_source: str = ""  # device path or pyserial URL of an NMEA compass
    baudrate: int = 4800
    tnt_angle_scale_deg: float = 1.0  # degrees per unit of a TNT compass's $PTNTHTM angles
    hard_iron_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # tesla
    soft_iron_matrix: tuple[float, float, float, float, float, float, float, float, float] = (
        1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0,
    )

    def __post_init__(self) -> None:
        _require(isinstance(self.kind, CompassKind), "devices.compass.kind", _choices(CompassKind), self.kind)
        _require(self.i2c_bus >= 0, "devices.compass.i2c_bus", "an integer >= 0", self.i2c_bus)
        _require(0x03 <= self.i2c_address <= 0x77, "devices.compass.i2c_address", "a 7-bit address in [3, 119]",
                 self.i2c_address)
        _require(0 <= self.gain <= 7, "devices.compass.gain", "a gain code in [0, 7]", self.gain)
        _baud("devices.compass.baudrate", self.baudrate)
        _require(math.isfinite(self.tnt_angle_scale_deg) and self.tnt_angle_scale_deg != 0.0,
                 "devices.compass.tnt_angle_scale_deg", "a finite non-zero number", self.tnt_angle_scale_deg)
        for i, v in enumerate(self.hard_iron_offset):
            _finite(f"devices.compass.hard_iron_offset[{i}]", v)
        for i, v in enumerate(self.soft_iron_matrix):
            _finite(f"devices.compass.soft_iron_matrix[{i}]", v)


@dataclass(frozen=True)
class InclinometerConfig:
    """The inclinometer: an I2C ADXL345 (``kind = "adxl345"``) or NMEA XDR pitch/roll (``"nmea"``)."""

    kind: InclinometerKind = InclinometerKind.ADXL345
    i2c_bus: int = 1
    i2c_address: int = 0x53
    samples: int = 16  # readings averaged per tilt
    pitch_offset_deg: float = 0.0  # what the sensor reads when the head is level
    roll_offset_deg: float = 0.0
    nmea_source: str = ""
    baudrate: int = 4800

    def __post_init__(self) -> None:
        _require(isinstance(self.kind, InclinometerKind), "devices.inclinometer.kind", _choices(InclinometerKind),
                 self.kind)
        _require(self.i2c_bus >= 0, "devices.inclinometer.i2c_bus", "an integer >= 0", self.i2c_bus)
        _require(0x03 <= self.i2c_address <= 0x77, "devices.inclinometer.i2c_address",
                 "a 7-bit address in [3, 119]", self.i2c_address)
        _require(self.samples >= 1, "devices.inclinometer.samples", "an integer >= 1", self.samples)
        _within("devices.inclinometer.pitch_offset_deg", self.pitch_offset_deg, -90.0, 90.0)
        _within("devices.inclinometer.roll_offset_deg", self.roll_offset_deg, -90.0, 90.0)
        _baud("devices.inclinometer.baudrate", self.baudrate)


@dataclass(frozen=True)
class StageConfig:
    """The pan stage (FLIR/Directed Perception PTU) on a serial port or pyserial URL ("" = none)."""

    source: str = ""
    baudrate: int = 9600
    timeout_s: float = 2.0
    move_timeout_s: float = 30.0
    speed_deg_s: float = 30.0
    position_tolerance: int = 0  # positions a move may end from its target before it counts as missed

    def __post_init__(self) -> None:
        _baud("devices.stage.baudrate", self.baudrate)
        _positive("devices.stage.timeout_s", self.timeout_s)
        _positive("devices.stage.move_timeout_s", self.move_timeout_s)
        _positive("devices.stage.speed_deg_s", self.speed_deg_s)
        _require(self.position_tolerance >= 0, "devices.stage.position_tolerance", "an integer >= 0",
                 self.position_tolerance)


@dataclass(frozen=True)
class CameraDeviceConfig:
    """The camera, through OpenCV's V4L2 backend."""

    device: str = "/dev/video0"
    width: int = 1280
    height: int = 720
    exposure: float = 100.0  # V4L2 exposure_time_absolute, units of 100 us
    gain: float = 0.0
    flush_frames: int = 4  # frames read and dropped before each still
    intrinsics_file: Path | None = None  # camera calibration TOML

    def __post_init__(self) -> None:
        _require(1 <= self.width <= MAX_CAMERA_SIDE, "devices.camera.width", f"an integer in [1, {MAX_CAMERA_SIDE}]",
                 self.width)
        _require(1 <= self.height <= MAX_CAMERA_SIDE, "devices.camera.height", f"an integer in [1, {MAX_CAMERA_SIDE}]",
                 self.height)
        _require(self.width * self.height <= MAX_IMAGE_PIXELS, "devices.camera.width x height",
                 f"at most {MAX_IMAGE_PIXELS:,} pixels", f"{self.width} x {self.height}")
        _non_negative("devices.camera.exposure", self.exposure)
        _non_negative("devices.camera.gain", self.gain)
        _require(self.flush_frames >= 0, "devices.camera.flush_frames", "an integer >= 0", self.flush_frames)


@dataclass(frozen=True)
class DevicesConfig:
    """The devices of the hardware platform (``[platform] kind = "hardware"``)."""

    gps: GpsDeviceConfig = field(default_factory=GpsDeviceConfig)
    compass: CompassConfig = field(default_factory=CompassConfig)
    inclinometer: InclinometerConfig = field(default_factory=InclinometerConfig)
    stage: StageConfig = field(default_factory=StageConfig)
    camera: CameraDeviceConfig = field(default_factory=CameraDeviceConfig)
    odometry: OdometryDeviceConfig = field(default_factory=OdometryDeviceConfig)
    # calibration TOML written by `viper calibrate compass|inclinometer`: its [compass] table
    # (hard_iron_offset in tesla, soft_iron_matrix) and [inclinometer] table (pitch_offset_deg,
    # roll_offset_deg) replace the same keys of [devices.compass] / [devices.inclinometer]
    calibration_file: Path | None = None


@dataclass(frozen=True)
class SimFaultsConfig:
    """Faults the simulated twins inject (rates are per sentence; times in simulated seconds)."""

    gps_unplug_at_s: float | None = None
    gps_replug_after_s: float = 2.0
    gps_garbage_rate: float = 0.0  # probability of a burst of binary garbage before a sentence
    gps_bad_checksum_rate: float = 0.0
    gps_stuck_at_s: float | None = None  # the receiver repeats its last position from then on
    gps_drift_m_per_s: float = 0.0  # the reported position walks north at this speed
    clock_offset_s: float = 0.0  # the platform's clock runs this far ahead of the GPS time (s)
    compass_stuck: bool = False  # the magnetometer repeats its first reading
    compass_drift_deg_per_s: float = 0.0  # the field turns slowly (a nearby magnet moving)
    inclinometer_stuck: bool = False
    inclinometer_absent: bool = False  # no chip answers at the address
    stage_miss_step_every: int = 0  # every Nth move ends short (0 = never)
    stage_miss_positions: int = 20
    stage_stall_at_deg: float | None = None  # the pan axis cannot pass this angle (signed, -180..180)
    compass_metal_nearby: bool = False  # steel nearby distorts the field beyond any hard/soft iron fit
    camera_unplug_after: int | None = None  # the camera disappears after this many stills
    camera_black_frames: tuple[int, ...] = ()  # still numbers (from 0) that come back black
    autopilot_reboot_leg: int | None = None  # the MAVLink autopilot twin reboots halfway through this leg (from 1)

    def __post_init__(self) -> None:
        if self.gps_unplug_at_s is not None:
            _non_negative("sim.faults.gps_unplug_at_s", self.gps_unplug_at_s)
        _non_negative("sim.faults.gps_replug_after_s", self.gps_replug_after_s)
        _within("sim.faults.gps_garbage_rate", self.gps_garbage_rate, 0.0, 1.0)
        _within("sim.faults.gps_bad_checksum_rate", self.gps_bad_checksum_rate, 0.0, 1.0)
        if self.gps_stuck_at_s is not None:
            _non_negative("sim.faults.gps_stuck_at_s", self.gps_stuck_at_s)
        _finite("sim.faults.gps_drift_m_per_s", self.gps_drift_m_per_s)
        _within("sim.faults.clock_offset_s", self.clock_offset_s, -86_400.0, 86_400.0)
        _finite("sim.faults.compass_drift_deg_per_s", self.compass_drift_deg_per_s)
        _require(self.stage_miss_step_every >= 0, "sim.faults.stage_miss_step_every", "an integer >= 0",
                 self.stage_miss_step_every)
        _require(self.stage_miss_positions >= 0, "sim.faults.stage_miss_positions", "an integer >= 0",
                 self.stage_miss_positions)
        if self.stage_stall_at_deg is not None:
            _within("sim.faults.stage_stall_at_deg", self.stage_stall_at_deg, -180.0, 180.0)
        if self.camera_unplug_after is not None:
            _require(self.camera_unplug_after >= 0, "sim.faults.camera_unplug_after", "an integer >= 0",
                     self.camera_unplug_after)
        if self.autopilot_reboot_leg is not None:
            _require(self.autopilot_reboot_leg >= 1, "sim.faults.autopilot_reboot_leg", "an integer >= 1",
                     self.autopilot_reboot_leg)
        for i, n in enumerate(self.camera_black_frames):
            _require(n >= 0, f"sim.faults.camera_black_frames[{i}]", "an integer >= 0", n)


@dataclass(frozen=True)
class SimConfig:
    """The simulated world and twins (``[platform] kind = "sim"``)."""

    dem: str = "jacksboro"
    lat_deg: float = 36.6
    lon_deg: float = -84.25
    ground_elevation_m: float | None = None  # None: from the DEM at the position
    mast_height_m: float = 1.5
    geoid_separation_m: float = -30.0
    heading_deg: float = 30.0
    tilt_north_deg: float = 1.0
    tilt_east_deg: float = -0.5
    hard_iron_t: tuple[float, float, float] = (8e-6, -5e-6, 3e-6)
    soft_iron: tuple[float, float, float, float, float, float, float, float, float] = (
        1.08, 0.03, 0.0, 0.03, 0.94, 0.0, 0.0, 0.0, 1.0,
    )
    start_utc: str = "2026-06-01T12:00:00Z"
    time_rate: float = 1.0  # simulated seconds per real second
    gps_sigma_m: float = 2.0
    gps_hdop: float = 0.9
    gps_satellites: int = 9
    gps_rate_hz: float = 1.0
    seed: int = 0
    # the simulated rover of a traverse: legs of a random length in this range (m), in a random direction,
    # reported by its odometry with this 1-sigma noise per axis (m)
    leg_length_m: tuple[float, float] = (200.0, 400.0)
    odometry_sigma_m: float = 15.0
    faults: SimFaultsConfig = field(default_factory=SimFaultsConfig)

    def __post_init__(self) -> None:
        _within("sim.lat_deg", self.lat_deg, -90.0, 90.0)
        _within("sim.lon_deg", self.lon_deg, -180.0, 360.0)
        if self.ground_elevation_m is not None:
            _finite("sim.ground_elevation_m", self.ground_elevation_m)
        _non_negative("sim.mast_height_m", self.mast_height_m)
        _finite("sim.geoid_separation_m", self.geoid_separation_m)
        _finite("sim.heading_deg", self.heading_deg)
        _within("sim.tilt_north_deg", self.tilt_north_deg, -45.0, 45.0)
        _within("sim.tilt_east_deg", self.tilt_east_deg, -45.0, 45.0)
        for i, v in enumerate(self.hard_iron_t):
            _finite(f"sim.hard_iron_t[{i}]", v)
        for i, v in enumerate(self.soft_iron):
            _finite(f"sim.soft_iron[{i}]", v)
        _positive("sim.time_rate", self.time_rate)
        _non_negative("sim.gps_sigma_m", self.gps_sigma_m)
        _positive("sim.gps_hdop", self.gps_hdop)
        _require(0 <= self.gps_satellites <= 99, "sim.gps_satellites", "an integer in [0, 99]", self.gps_satellites)
        _require(math.isfinite(self.gps_rate_hz) and 0.0 < self.gps_rate_hz <= 100.0, "sim.gps_rate_hz",
                 "a number in (0, 100]", self.gps_rate_hz)
        lo, hi = self.leg_length_m
        _require(math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 10_000.0, "sim.leg_length_m",
                 "[lo, hi] metres with 0 <= lo <= hi <= 10000", [lo, hi])
        _require(math.isfinite(self.odometry_sigma_m) and 0.0 <= self.odometry_sigma_m <= 1000.0,
                 "sim.odometry_sigma_m", "metres in [0, 1000]", self.odometry_sigma_m)
