"""Configuration: TOML read once at the edge into frozen, typed objects.

Every section is a frozen dataclass; :func:`from_mapping` converts a parsed TOML table into one,
rejecting unknown keys and values of the wrong type with the key's dotted name.  Drivers and
procedures receive these objects and never read files or the environment themselves.  The sections
of the platform (``[platform]``, ``[devices]``, ``[sim]``) are in :mod:`appliance._config_platform`,
the checks of the values in :mod:`appliance._config_checks`; every name is imported from here.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, Union

from appliance._config_checks import (
    UDP_SCHEME,
    _choices,
    _finite,
    _non_negative,
    _positive,
    _require,
    _within,
    udp_address,
)
from appliance._config_platform import (
    CameraDeviceConfig,
    CompassConfig,
    CompassKind,
    DevicesConfig,
    GpsDeviceConfig,
    InclinometerConfig,
    InclinometerKind,
    OdometryDeviceConfig,
    OdometryKind,
    PlatformConfig,
    PlatformKind,
    PositionOutput,
    SimConfig,
    SimFaultsConfig,
    StageConfig,
    mavlink_udp_address,
)
from appliance.errors import ConfigError, InputError
from appliance.inputs import MAX_CONFIG_BYTES, NestingError, check_nesting, read_text_bounded

__all__ = [
    "CameraDeviceConfig", "CompassConfig", "CompassKind", "Compression", "Config", "DevicesConfig", "EstimatorConfig",
    "GpsDeviceConfig", "InclinometerConfig", "InclinometerKind", "LEAST_LOG_BYTES", "LogEncoding", "LogbookConfig",
    "OdometryDeviceConfig", "OdometryKind", "PlatformConfig", "PlatformKind", "PositionOutput", "SIGMA_MAX_DEG",
    "SIGMA_MIN_DEG", "SessionConfig", "SimConfig", "SimFaultsConfig", "StageConfig", "TraverseConfig", "UDP_SCHEME",
    "from_mapping", "load_config", "mavlink_udp_address", "override", "read_config_toml", "udp_address",
]

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

T = TypeVar("T")


class Compression(str, enum.Enum):
    """Chunk compression of the session logs."""

    ZSTD = "zstd"
    LZ4 = "lz4"
    NONE = "none"


class LogEncoding(str, enum.Enum):
    """The messages of the session logs: Foxglove's protobuf schemas, or standard ROS 2 messages (CDR)."""

    PROTOBUF = "protobuf"
    ROS2 = "ros2"


#: The least a session's log takes besides its reserve (bytes): the header, the camera's calibration and
#: the readings of level, compass and GPS truth (a session of the simulated platform with six frames of
#: 64 x 48 pixels writes about 27 kB).
LEAST_LOG_BYTES = 16_384

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
class LogbookConfig:
    """The session logs (one MCAP file per session): where they go and how often they are made durable."""

    log_dir: Path = Path("/var/lib/viper/logs")
    fsync_interval_s: float = 2.0
    chunk_size_bytes: int = 262_144
    compression: Compression = Compression.ZSTD
    reserve_bytes: int = 65_536  # freed on a full disk so the log can still be sealed
    encoding: LogEncoding = LogEncoding.PROTOBUF
    # retention (appliance.acquisition.retention): before and after every session the oldest complete logs
    # are removed until the disk keeps this much free and the logs take at most this much; 0 = no limit
    keep_free_bytes: int = 0
    max_total_bytes: int = 0
    keep_unreplayed: bool = False  # never remove a log `viper replay` has not marked replayed (LOG.replayed)
    max_clock_offset_s: float = 2.0  # a session whose clock is farther than this from the GPS time is flagged

    @property
    def least_log_bytes(self) -> int:
        """The least one session's log takes in the folder while it is written: its reserve beside it
        and :data:`LEAST_LOG_BYTES` (the header, the calibration, the readings of a session without frames)."""
        return self.reserve_bytes + LEAST_LOG_BYTES

    def __post_init__(self) -> None:
        _positive("logbook.fsync_interval_s", self.fsync_interval_s)
        _require(1024 <= self.chunk_size_bytes <= 1 << 26, "logbook.chunk_size_bytes",
                 "an integer in [1024, 67108864] (64 MiB)", self.chunk_size_bytes)
        _require(0 <= self.reserve_bytes <= 1 << 30, "logbook.reserve_bytes", "an integer in [0, 1073741824] (1 GiB)",
                 self.reserve_bytes)
        _require(isinstance(self.compression, Compression), "logbook.compression", _choices(Compression),
                 self.compression)
        _require(isinstance(self.encoding, LogEncoding), "logbook.encoding", _choices(LogEncoding), self.encoding)
        _require(0 <= self.keep_free_bytes <= _LARGEST_INT, "logbook.keep_free_bytes", "an integer >= 0 (0: no "
                 "limit)", self.keep_free_bytes)
        _require(self.max_total_bytes == 0 or self.least_log_bytes <= self.max_total_bytes <= _LARGEST_INT,
                 "logbook.max_total_bytes", f"0 (no cap) or at least one log: reserve_bytes + {LEAST_LOG_BYTES} = "
                 f"{self.least_log_bytes} bytes", self.max_total_bytes)
        _require(math.isfinite(self.max_clock_offset_s) and self.max_clock_offset_s > 0,
                 "logbook.max_clock_offset_s", "a finite number of seconds > 0", self.max_clock_offset_s)


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
        _require(3 <= self.compass_steps <= 360, "session.compass_steps", "an integer in [3, 360]", self.compass_steps)
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


#: the largest integer a configuration value may hold (a TOML integer is 64-bit signed)
_LARGEST_INT = 2**63 - 1


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
        if not -_LARGEST_INT <= value <= _LARGEST_INT:
            raise ConfigError(f"{key}: expected an integer within 64 bits, got one beyond")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if isinstance(value, int) and not -_LARGEST_INT <= value <= _LARGEST_INT:
            raise ConfigError(f"{key}: expected a number within 64-bit integers, got an integer beyond")
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
    """Read a TOML configuration file (a regular file of at most 1 MiB, nested at most 64 levels);
    ``None`` gives the defaults."""
    if path is None:
        return Config()
    p = Path(path)
    data = read_config_toml(p)
    try:
        return from_mapping(Config, data)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def read_config_toml(p: Path) -> dict[str, Any]:
    """The parsed TOML of the configuration file ``p``; every failure a :class:`ConfigError` line."""
    try:
        text = read_text_bounded(p, MAX_CONFIG_BYTES, "configuration file", ConfigError)
        check_nesting(text)
        return tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except (tomllib.TOMLDecodeError, NestingError) as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc}") from None

