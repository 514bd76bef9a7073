"""Configuration: TOML into frozen objects, unknown keys and wrong types refused by name."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path

import pytest

from appliance.config import CompassKind, Compression, Config, EstimatorConfig, PlatformKind, load_config
from appliance.errors import ConfigError


def test_defaults_without_a_file():
    cfg = load_config(None)
    assert cfg.estimator.sigma_deg == (0.3, 0.8)
    assert cfg.platform.kind is PlatformKind.SIM
    assert cfg.devices.compass.kind is CompassKind.HMC5883L and cfg.logbook.compression is Compression.ZSTD


def test_values_are_read_and_frozen(tmp_path):
    p = tmp_path / "viper.toml"
    p.write_text("# field kit\n[estimator]\nsigma_deg = [0.25, 0.5]\nheading_tolerance_deg = 6\n"
                 "[devices.compass]\nkind = \"nmea\"\n[logbook]\ncompression = \"lz4\"\n")
    cfg = load_config(p)
    assert cfg.estimator == EstimatorConfig(sigma_deg=(0.25, 0.5), heading_tolerance_deg=6.0)
    assert isinstance(cfg.estimator.heading_tolerance_deg, float)
    assert cfg.devices.compass.kind is CompassKind.NMEA and cfg.logbook.compression is Compression.LZ4
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.estimator.sigma_deg = (1.0, 2.0)  # type: ignore[misc]


@pytest.mark.parametrize("text,name", [
    ("[estimator]\nsigmadeg = [0.2, 0.4]\n", "estimator.sigmadeg"),
    ("[estimatr]\nsigma_deg = [0.2, 0.4]\n", "estimatr"),
    ("[estimator]\nsigma_deg = 0.2\n", "estimator.sigma_deg"),
    ("[estimator]\nsigma_deg = [0.2, \"x\"]\n", "estimator.sigma_deg[1]"),
    ("[estimator]\nsigma_deg = [0.2, 0.3, 0.4]\n", "estimator.sigma_deg"),
    ("[terrain]\ncamera_height_m = 1.5\n", "terrain"),
    ("[estimator]\nheading_step_deg = 1.0\n", "estimator.heading_step_deg"),
    ("[session]\nsettle_s = true\n", "session.settle_s"),
    ("[platform]\nkind = \"rover9000\"\n", "platform.kind"),
])
def test_bad_keys_and_types_name_the_key(tmp_path, text, name):
    p = tmp_path / "viper.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert name in str(err.value)
    assert str(p) in str(err.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[estimator\nsigma_deg = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


#: keys kept as a record of where a value came from; nothing is meant to act on them
RECORD_ONLY: set[str] = set()


def _keys(cls: type, prefix: str = "") -> list[str]:
    out = []
    for f in dataclasses.fields(cls):
        tp = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(tp):
            out += _keys(tp, f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


def test_every_key_is_read_somewhere():
    # a key that nothing reads says more than the configuration does
    repo = Path(__file__).resolve().parents[1]
    config_modules = ("config.py", "_config_platform.py", "_config_checks.py")
    code = "\n".join(p.read_text(encoding="utf-8") for folder in ("appliance", "calibration")
                     for p in (repo / folder).rglob("*.py") if p.name not in config_modules)
    unread = [k for k in _keys(Config) if k.rsplit(".", 1)[-1] not in RECORD_ONLY
              and not re.search(rf"\.{k.rsplit('.', 1)[-1]}\b", code)]
    assert unread == []


def test_the_example_configurations_load():
    examples = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.toml"))
    assert len(examples) >= 2
    tripod = load_config(examples[[p.name for p in examples].index("tripod.toml")])
    assert tripod.platform.kind == "hardware" and tripod.session.body_mask_deg == ((170.0, 190.0),)
    assert tripod.estimator.occlusion_weight == 0.05 and tripod.estimator.map_vertical_sigma_m == 5.0
    for p in examples:
        load_config(p)


def _written_keys(path):
    """Keys set or shown commented out (``# key = value``) in a TOML example, with their table."""
    keys, table = set(), ""
    for line in path.read_text().splitlines():
        head = re.match(r"^\[([\w.]+)\]", line)
        if head:
            table = head.group(1) + "."
            continue
        key = re.match(r"^#? ?(\w+) = ", line)
        if key:
            keys.add(table + key.group(1))
    return keys


@pytest.mark.parametrize("name,kind,skip", [("hardware.toml", "hardware", "sim."), ("sim.toml", "sim", None)])
def test_the_complete_examples_show_every_key(name, kind, skip):
    path = Path(__file__).resolve().parents[1] / "examples" / name
    assert load_config(path).platform.kind == kind
    expected = {k for k in _keys(Config) if skip is None or not k.startswith(skip)}
    assert sorted(expected - _written_keys(path)) == []
    assert sorted(_written_keys(path) - set(_keys(Config))) == []


@pytest.mark.parametrize("text,name", [
    ("[estimator]\nocclusion_weight = 1.0\n", "estimator.occlusion_weight"),
    ("[estimator]\nmap_vertical_sigma_m = -1.0\n", "estimator.map_vertical_sigma_m"),
    ("[session]\nbody_mask_deg = [[1.0]]\n", "session.body_mask_deg"),
])
def test_estimator_and_mask_settings_are_checked(tmp_path, text, name):
    p = tmp_path / "v.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=name.replace(".", r"\.")):
        load_config(p)


@pytest.mark.parametrize("text,name", [
    ("[sim]\ntime_rate = 0\n", "sim.time_rate"),
    ("[sim]\ntime_rate = -2.0\n", "sim.time_rate"),
    ("[sim]\ntime_rate = nan\n", "sim.time_rate"),
    ("[sim]\ngps_rate_hz = 0\n", "sim.gps_rate_hz"),
    ("[sim]\nlat_deg = 91.0\n", "sim.lat_deg"),
    ("[sim]\nmast_height_m = -1.0\n", "sim.mast_height_m"),
    ("[sim]\ngps_satellites = -3\n", "sim.gps_satellites"),
    ("[sim.faults]\ngps_garbage_rate = 1.5\n", "sim.faults.gps_garbage_rate"),
    ("[sim.faults]\ngps_unplug_at_s = -1.0\n", "sim.faults.gps_unplug_at_s"),
    ("[sim.faults]\nstage_stall_at_deg = 270.0\n", "sim.faults.stage_stall_at_deg"),
    ("[sim.faults]\ncamera_black_frames = [2, -1]\n", "sim.faults.camera_black_frames[1]"),
    ("[session]\ninterval_s = -60.0\n", "session.interval_s"),
    ("[session]\ninterval_s = 0\n", "session.interval_s"),
    ("[session]\nmax_sessions = -1\n", "session.max_sessions"),
    ("[session]\nwatchdog_margin = 1.5\n", "session.watchdog_margin"),
    ("[session]\nstep_timeout_s = 0\n", "session.step_timeout_s"),
    ("[session]\nlevel_timeout_s = -1.0\n", "session.level_timeout_s"),
    ("[session]\nlevel_poll_s = 0\n", "session.level_poll_s"),
    ("[session]\ncompass_steps = 2\n", "session.compass_steps"),
    ("[session]\ntruth_duration_s = -30.0\n", "session.truth_duration_s"),
    ("[session]\ntruth_min_fixes = 0\n", "session.truth_min_fixes"),
    ("[session]\ncapture_overlap = 1.0\n", "session.capture_overlap"),
    ("[session]\nsettle_s = -0.5\n", "session.settle_s"),
    ("[session]\nblack_frame_max_mean = 300.0\n", "session.black_frame_max_mean"),
    ("[session]\nbody_mask_deg = [[1.0, inf]]\n", "session.body_mask_deg[0][1]"),
    ("[estimator]\nmin_valid_fraction = -1.0\n", "estimator.min_valid_fraction"),
    ("[estimator]\nmin_valid_fraction = 1.2\n", "estimator.min_valid_fraction"),
    ("[estimator]\nheading_tolerance_deg = -4.0\n", "estimator.heading_tolerance_deg"),
    ("[estimator]\nsigma_deg = [0.8, 0.3]\n", "estimator.sigma_deg"),
    ("[estimator]\nsigma_deg = [0.0, 0.3]\n", "estimator.sigma_deg"),
    ("[estimator]\nmap_vertical_sigma_m = 1e6\n", "estimator.map_vertical_sigma_m"),
    ("[logbook]\nfsync_interval_s = 0\n", "logbook.fsync_interval_s"),
    ("[logbook]\nchunk_size_bytes = 10\n", "logbook.chunk_size_bytes"),
    ("[logbook]\nreserve_bytes = -1\n", "logbook.reserve_bytes"),
    ("[devices.gps]\nbaudrate = 0\n", "devices.gps.baudrate"),
    ("[devices.gps]\nread_timeout_s = 0\n", "devices.gps.read_timeout_s"),
    ("[devices.gps]\nreconnect_initial_s = 2.0\nreconnect_max_s = 1.0\n", "devices.gps.reconnect_max_s"),
    ("[devices.compass]\nkind = \"qmc\"\n", "devices.compass.kind"),
    ("[devices.compass]\ngain = 8\n", "devices.compass.gain"),
    ("[devices.compass]\ni2c_address = 200\n", "devices.compass.i2c_address"),
    ("[devices.compass]\ntnt_angle_scale_deg = 0\n", "devices.compass.tnt_angle_scale_deg"),
    ("[devices.inclinometer]\nsamples = 0\n", "devices.inclinometer.samples"),
    ("[devices.inclinometer]\nroll_offset_deg = 95.0\n", "devices.inclinometer.roll_offset_deg"),
    ("[devices.stage]\nmove_timeout_s = -1.0\n", "devices.stage.move_timeout_s"),
    ("[devices.stage]\nspeed_deg_s = 0\n", "devices.stage.speed_deg_s"),
    ("[devices.stage]\nposition_tolerance = -1\n", "devices.stage.position_tolerance"),
    ("[devices.camera]\nwidth = 0\n", "devices.camera.width"),
    ("[devices.camera]\nflush_frames = -1\n", "devices.camera.flush_frames"),
    ("[devices.camera]\nexposure = -5.0\n", "devices.camera.exposure"),
])
def test_ranges_are_checked_by_the_schema(tmp_path, text, name):
    p = tmp_path / "v.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: {name}: expected ")
    assert "\n" not in msg


def test_range_limits_themselves_are_accepted(tmp_path):
    p = tmp_path / "v.toml"
    p.write_text("[estimator]\nmin_valid_fraction = 1.0\nsigma_deg = [0.4, 0.4]\nheading_tolerance_deg = 0\n"
                 "[session]\nsettle_s = 0\nlevel_timeout_s = 0\nmax_sessions = 0\ncapture_overlap = 0\n"
                 "[sim]\ntime_rate = 0.001\n[sim.faults]\ngps_garbage_rate = 1.0\nstage_stall_at_deg = -180.0\n")
    cfg = load_config(p)
    assert cfg.estimator.min_valid_fraction == 1.0 and cfg.estimator.sigma_deg == (0.4, 0.4)
    assert cfg.session.settle_s == 0.0 and cfg.sim.time_rate == 0.001
    assert cfg.sim.faults.stage_stall_at_deg == -180.0


def test_the_estimators_default_sigma_is_the_configurations():
    import inspect

    from appliance.config import EstimatorConfig
    from appliance.estimator import estimate

    assert inspect.signature(estimate).parameters["sigma_deg"].default == EstimatorConfig().sigma_deg


def test_the_estimator_and_the_configuration_share_one_set_of_defaults():
    import inspect

    from appliance.config import EstimatorConfig
    from appliance.estimator import estimate
    from appliance.locating.position import locate
    from appliance.locating.tile_cache import SearchParams

    cfg = EstimatorConfig()
    given = inspect.signature(estimate).parameters
    assert given["sigma_deg"].default == cfg.sigma_deg
    assert given["heading_tolerance_deg"].default == cfg.heading_tolerance_deg
    assert given["occlusion_weight"].default == cfg.occlusion_weight
    assert given["map_sigma_m"].default == cfg.map_vertical_sigma_m
    assert inspect.signature(locate).parameters["occlusion_weight"].default == cfg.occlusion_weight
    assert SearchParams((0.3, 0.8), 4.0).occlusion_weight == cfg.occlusion_weight
