"""Configuration: TOML read once at the edge into frozen, typed objects.

Every section is a frozen dataclass; :func:`from_mapping` converts a parsed TOML table into one,
rejecting unknown keys and values of the wrong type with the key's dotted name.  Drivers and
procedures receive these objects and never read files or the environment themselves.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, Union

from appliance.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

T = TypeVar("T")


def _require(ok: bool, key: str, expected: str, value: Any) -> None:
    """Raise a ConfigError naming ``key`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{key}: expected {expected}, got {value!r}")


def _positive(key: str, value: float) -> None:
    _require(math.isfinite(value) and value > 0, key, "a finite number > 0", value)


def _non_negative(key: str, value: float) -> None:
    _require(math.isfinite(value) and value >= 0, key, "a finite number >= 0", value)


def _within(key: str, value: float, lo: float, hi: float) -> None:
    _require(math.isfinite(value) and lo <= value <= hi, key, f"a number in [{lo:g}, {hi:g}]", value)


def _finite(key: str, value: float) -> None:
    _require(math.isfinite(value), key, "a finite number", value)


def _baud(key: str, value: int) -> None:
    _require(50 <= value <= 4_000_000, key, "a baud rate in [50, 4000000]", value)


UDP_SCHEME = "udp://"
_UDP = re.compile(r"udp://(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/\[\]]*)):(?P<port>\d{1,5})")


def udp_address(source: str, key: str) -> tuple[str, int]:
    """(host, port) of ``udp://HOST:PORT`` (``udp://:5600``: every IPv4 interface); raises naming ``key``."""
    m = _UDP.fullmatch(source)
    _require(m is not None and int(m.group("port")) <= 65535, key, "udp://HOST:PORT with a port in [0, 65535]",
             source)
    assert m is not None
    return m.group("v6") or m.group("host") or "0.0.0.0", int(m.group("port"))


def _choices(kind: type[enum.Enum]) -> str:
    names = [repr(m.value) for m in kind]
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


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


class Compression(str, enum.Enum):
    """Chunk compression of the session logs."""

    ZSTD = "zstd"
    LZ4 = "lz4"
    NONE = "none"


#: The physical range of a skyline's sigma (deg): a thousandth of a degree (far below any sensor's
#: arc-second survey) to 30 degrees (a skyline that says nothing).
SIGMA_MIN_DEG = 1e-3
SIGMA_MAX_DEG = 30.0


@dataclass(frozen=True)
class EstimatorConfig:
    """The position estimator (paper section 4)."""

    # sensor noise plus the skyline's change between grid nodes (0.5-1 deg on a 90 m map, camera 1.5 m)
    sigma_deg: tuple[float, float] = (0.3, 0.8)  # the search's interval; the estimate's is learned from the skyline
    heading_tolerance_deg: float = 4.0
    min_valid_fraction: float = 20.0 / 360.0  # the estimator's least field of view: 20 deg of the circle
    # prior share of azimuths hidden by what the map lacks (trees, buildings): one-sided likelihood
    occlusion_weight: float = 0.05
    map_vertical_sigma_m: float = 0.0  # the map's own height error (1 sigma)
    # the sensor's sigma from `viper calibrate theodolite`: the floor of the sigma the estimator learns
    sensor_sigma_deg: tuple[float, float] | None = None

    @property
    def sigma_floor_deg(self) -> float | None:
        """The floor of the sigma the estimator learns: the calibrated sensor's lower bound, if any."""
        return None if self.sensor_sigma_deg is None else self.sensor_sigma_deg[0]

    def __post_init__(self) -> None:
        lo, hi = self.sigma_deg
        _require(math.isfinite(lo) and math.isfinite(hi) and SIGMA_MIN_DEG <= lo <= hi <= SIGMA_MAX_DEG,
                 "estimator.sigma_deg", f"[lo, hi] in degrees with {SIGMA_MIN_DEG:g} <= lo <= hi <= {SIGMA_MAX_DEG:g}",
                 [lo, hi])
        if self.sensor_sigma_deg is not None:
            a, b = self.sensor_sigma_deg
            _require(math.isfinite(a) and math.isfinite(b) and SIGMA_MIN_DEG <= a <= b <= SIGMA_MAX_DEG,
                     "estimator.sensor_sigma_deg",
                     f"[lo, hi] in degrees with {SIGMA_MIN_DEG:g} <= lo <= hi <= {SIGMA_MAX_DEG:g}", [a, b])
        _within("estimator.heading_tolerance_deg", self.heading_tolerance_deg, 0.0, 180.0)
        _within("estimator.min_valid_fraction", self.min_valid_fraction, 0.0, 1.0)
        _require(math.isfinite(self.occlusion_weight) and 0.0 <= self.occlusion_weight < 1.0,
                 "estimator.occlusion_weight", "a number in [0, 1)", self.occlusion_weight)
        _require(math.isfinite(self.map_vertical_sigma_m) and 0.0 <= self.map_vertical_sigma_m < 1000.0,
                 "estimator.map_vertical_sigma_m", "metres in [0, 1000)", self.map_vertical_sigma_m)


@dataclass(frozen=True)
class PlatformConfig:
    """Which platform the daemons drive: real hardware or the simulated twins."""

    kind: PlatformKind = PlatformKind.SIM

    def __post_init__(self) -> None:
        _require(isinstance(self.kind, PlatformKind), "platform.kind", _choices(PlatformKind), self.kind)


@dataclass(frozen=True)
class LogbookConfig:
    """The session logs (one MCAP file per session): where they go and how often they are made durable."""

    log_dir: Path = Path("/var/lib/viper/logs")
    fsync_interval_s: float = 2.0
    chunk_size_bytes: int = 262_144
    compression: Compression = Compression.ZSTD
    reserve_bytes: int = 65_536  # freed on a full disk so the log can still be sealed

    def __post_init__(self) -> None:
        _positive("logbook.fsync_interval_s", self.fsync_interval_s)
        _require(self.chunk_size_bytes >= 1024, "logbook.chunk_size_bytes", "an integer >= 1024",
                 self.chunk_size_bytes)
        _require(self.reserve_bytes >= 0, "logbook.reserve_bytes", "an integer >= 0", self.reserve_bytes)
        _require(isinstance(self.compression, Compression), "logbook.compression", _choices(Compression),
                 self.compression)


@dataclass(frozen=True)
class SessionConfig:
    """Unattended sessions and the tolerances of their procedures (paper section 5.2)."""

    interval_s: float = 3600.0  # the session daemon starts a session this often
    max_sessions: int = 0  # the daemon stops after this many sessions; 0 = never
    watchdog_margin: float = 0.5  # WATCHDOG=1 every margin * WatchdogSec
    step_timeout_s: float = 900.0  # the watchdog is fed while the session reported progress this recently
    level_tolerance_deg: float = 0.5  # |roll| and |pitch| must both be within this
    level_timeout_s: float = 120.0
    level_poll_s: float = 0.5
    compass_steps: int = 24  # stage positions over the full circle for the hard/soft iron fit
    compass_max_residual: float = 0.05  # RMS of the fit, relative to the field's magnitude
    truth_duration_s: float = 30.0  # GPS ground truth: averaging time
    truth_min_fixes: int = 5
    truth_max_hdop: float = 5.0
    capture_overlap: float = 0.3  # fraction of the horizontal field of view shared by neighbours
    settle_s: float = 0.5  # wait after every stage move before capturing
    stage_tolerance_deg: float = 1.0  # stage considered stalled if it ends farther than this
    black_frame_max_mean: float = 8.0  # a frame whose mean grey level is below this is rejected
    database: Path | None = None  # skyline database of the onboard estimate (None: the demo map's, in sim)
    # stage angles (deg, [from, to]) where the platform's own body, mast or antenna stands in the view
    body_mask_deg: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        _positive("session.interval_s", self.interval_s)
        _require(self.max_sessions >= 0, "session.max_sessions", "an integer >= 0", self.max_sessions)
        _require(math.isfinite(self.watchdog_margin) and 0.0 < self.watchdog_margin <= 1.0,
                 "session.watchdog_margin", "a number in (0, 1]", self.watchdog_margin)
        _positive("session.step_timeout_s", self.step_timeout_s)
        _within("session.level_tolerance_deg", self.level_tolerance_deg, 0.0, 90.0)
        _non_negative("session.level_timeout_s", self.level_timeout_s)
        _positive("session.level_poll_s", self.level_poll_s)
        _require(self.compass_steps >= 3, "session.compass_steps", "an integer >= 3", self.compass_steps)
        _positive("session.compass_max_residual", self.compass_max_residual)
        _non_negative("session.truth_duration_s", self.truth_duration_s)
        _require(self.truth_min_fixes >= 1, "session.truth_min_fixes", "an integer >= 1", self.truth_min_fixes)
        _positive("session.truth_max_hdop", self.truth_max_hdop)
        _require(math.isfinite(self.capture_overlap) and 0.0 <= self.capture_overlap < 1.0,
                 "session.capture_overlap", "a number in [0, 1)", self.capture_overlap)
        _non_negative("session.settle_s", self.settle_s)
        _positive("session.stage_tolerance_deg", self.stage_tolerance_deg)
        _within("session.black_frame_max_mean", self.black_frame_max_mean, 0.0, 255.0)
        for i, (a, b) in enumerate(self.body_mask_deg):
            _finite(f"session.body_mask_deg[{i}][0]", a)
            _finite(f"session.body_mask_deg[{i}][1]", b)


@dataclass(frozen=True)
class TraverseConfig:
    """Rover traverses: a session is a series of stops, each stop's estimate fused with the last one's
    posterior moved by the rover's odometry (paper section 6.4)."""

    stops: int = 0  # 0: every session is one stop on its own; N >= 1: a session is a traverse of N stops
    odometry_timeout_s: float = 900.0  # each stop after the first waits this long for the odometry line

    def __post_init__(self) -> None:
        _require(0 <= self.stops <= 100_000, "traverse.stops", "an integer in [0, 100000]", self.stops)
        _positive("traverse.odometry_timeout_s", self.odometry_timeout_s)


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


@dataclass(frozen=True)
class OdometryDeviceConfig:
    """The rover's odometry, one line per stop (``appliance.drivers.odometry``): a device path or
    pyserial URL, or ``udp://HOST:PORT`` to listen on ("" = none)."""

    source: str = ""
    baudrate: int = 9600
    read_timeout_s: float = 0.5

    def __post_init__(self) -> None:
        _baud("devices.odometry.baudrate", self.baudrate)
        _positive("devices.odometry.read_timeout_s", self.read_timeout_s)
        if self.source.startswith(UDP_SCHEME):
            udp_address(self.source, "devices.odometry.source")


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
        _require(self.width >= 1, "devices.camera.width", "an integer >= 1", self.width)
        _require(self.height >= 1, "devices.camera.height", "an integer >= 1", self.height)
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

    def __post_init__(self) -> None:
        if self.gps_unplug_at_s is not None:
            _non_negative("sim.faults.gps_unplug_at_s", self.gps_unplug_at_s)
        _non_negative("sim.faults.gps_replug_after_s", self.gps_replug_after_s)
        _within("sim.faults.gps_garbage_rate", self.gps_garbage_rate, 0.0, 1.0)
        _within("sim.faults.gps_bad_checksum_rate", self.gps_bad_checksum_rate, 0.0, 1.0)
        if self.gps_stuck_at_s is not None:
            _non_negative("sim.faults.gps_stuck_at_s", self.gps_stuck_at_s)
        _finite("sim.faults.gps_drift_m_per_s", self.gps_drift_m_per_s)
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


@dataclass(frozen=True)
class Config:
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    platform: PlatformConfig = field(default_factory=PlatformConfig)
    logbook: LogbookConfig = field(default_factory=LogbookConfig)
    session: SessionConfig = field(default_factory=SessionConfig)
    traverse: TraverseConfig = field(default_factory=TraverseConfig)
    devices: DevicesConfig = field(default_factory=DevicesConfig)
    sim: SimConfig = field(default_factory=SimConfig)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(value: Any, tp: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for alt in args:
            if alt is type(None):
                continue
            try:
                return _convert(value, alt, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{key}: invalid value {value!r}")
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        return from_mapping(tp, value, prefix=key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected an array, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        return {str(k): _convert(v, args[1], f"{key}.{k}") for k, v in value.items()}
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(value)
        except ValueError:
            raise ConfigError(f"{key}: expected {_choices(tp)}, got {value!r}") from None
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a path string, got {value!r}")
        return Path(value)
    raise ConfigError(f"{key}: unsupported type {_type_name(tp)}")


def override(obj: T, flag: str, **changes: Any) -> T:
    """``obj`` with ``changes`` given on the command line, checked as the file's values are (by the
    section's ``__post_init__``); a value out of range is an :class:`InputError` naming ``flag``."""
    from appliance.errors import InputError

    try:
        return dataclasses.replace(obj, **changes)  # type: ignore[type-var]
    except ConfigError as exc:
        raise InputError(f"{flag}: {exc}") from None


def from_mapping(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build the frozen dataclass ``cls`` from ``data``; unknown keys and wrong types raise."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(f"unknown key {where}{unknown[0]} (known: {', '.join(sorted(names))})")
    kwargs = {
        name: _convert(value, hints[name], f"{prefix}.{name}" if prefix else name)
        for name, value in data.items()
    }
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{prefix or 'config'}: {exc}") from None


def load_config(path: str | Path | None) -> Config:
    """Read a TOML configuration file; ``None`` gives the defaults."""
    if path is None:
        return Config()
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc}") from None
    try:
        return from_mapping(Config, data)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None
