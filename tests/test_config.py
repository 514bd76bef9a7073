"""Configuration: TOML into frozen objects, unknown keys and wrong types refused by name."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from appliance.config import Config, EstimatorConfig, load_config
from appliance.errors import ConfigError


def test_defaults_without_a_file():
    cfg = load_config(None)
    assert cfg.estimator.sigma_deg == (0.3, 0.8)
    assert cfg.terrain.camera_height_m == 1.5
    assert cfg.platform.kind == "sim"


def test_values_are_read_and_frozen(tmp_path):
    p = tmp_path / "viper.toml"
    p.write_text("# field kit\n[estimator]\nsigma_deg = [0.25, 0.5]\nheading_tolerance_deg = 6\n"
                 "[terrain]\ncamera_height_m = 1.2\n")
    cfg = load_config(p)
    assert cfg.estimator == EstimatorConfig(sigma_deg=(0.25, 0.5), heading_tolerance_deg=6.0)
    assert isinstance(cfg.estimator.heading_tolerance_deg, float)
    assert cfg.terrain.camera_height_m == 1.2
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.estimator.sigma_deg = (1.0, 2.0)  # type: ignore[misc]


@pytest.mark.parametrize("text,name", [
    ("[estimator]\nsigmadeg = [0.2, 0.4]\n", "estimator.sigmadeg"),
    ("[estimatr]\nsigma_deg = [0.2, 0.4]\n", "estimatr"),
    ("[estimator]\nsigma_deg = 0.2\n", "estimator.sigma_deg"),
    ("[estimator]\nsigma_deg = [0.2, \"x\"]\n", "estimator.sigma_deg[1]"),
    ("[estimator]\nsigma_deg = [0.2, 0.3, 0.4]\n", "estimator.sigma_deg"),
    ("[terrain]\nazimuths = 360.5\n", "terrain.azimuths"),
    ("[terrain]\ncamera_height_m = true\n", "terrain.camera_height_m"),
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


def test_every_section_has_defaults():
    cfg = Config()
    for f in dataclasses.fields(cfg):
        assert dataclasses.is_dataclass(getattr(cfg, f.name))


def test_the_example_configurations_load():
    examples = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.toml"))
    assert len(examples) >= 2
    tripod = load_config(examples[[p.name for p in examples].index("tripod.toml")])
    assert tripod.platform.kind == "hardware" and tripod.session.body_mask_deg == ((170.0, 190.0),)
    assert tripod.estimator.occlusion_weight == 0.05 and tripod.estimator.map_vertical_sigma_m == 5.0
    for p in examples:
        load_config(p)


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
