"""Theodolite sigma interval: chi-square table values, coverage, CLI and format-preserving config edit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from viper_calibration.theodolite import (
    ElevationPoint,
    calibrate_sigma,
    parse_points_csv,
    sigma_interval,
)

from appliance.cli.main import main
from appliance.config import load_config
from appliance.errors import CalibrationError, InputError

EXAMPLE = Path(__file__).resolve().parents[1] / "calibration" / "examples" / "theodolite_points.csv"

CONFIG_TEXT = """\
# Field configuration of the rover
[session]
level_tolerance_deg = 0.3   # the tripod's bubble

[estimator]
# interval from the last survey
sigma_deg = [0.2, 0.4]  # degrees
heading_tolerance_deg = 4.0

[platform]
kind = "sim"
"""


def _points(residuals_deg: list[float]) -> list[ElevationPoint]:
    return [ElevationPoint(f"P{i}", 1.0 + 0.5 * i + r, 1.0 + 0.5 * i) for i, r in enumerate(residuals_deg)]


@pytest.mark.parametrize(
    ("n", "confidence", "chi2_upper", "chi2_lower"),
    [
        # Printed chi-square tables (upper-tail critical values), 3 decimals.
        (17, 0.95, 28.845, 6.908),
        (10, 0.95, 19.023, 2.700),
        (17, 0.99, 34.267, 5.142),
        (4, 0.95, 9.348, 0.216),
    ],
)
def test_interval_matches_chi2_table(n: int, confidence: float, chi2_upper: float, chi2_lower: float) -> None:
    s = 30.0 / 3600.0  # thirty seconds of arc, as in the paper's survey
    lo, hi = sigma_interval(s, n, confidence)
    dof = n - 1
    assert lo == pytest.approx(math.sqrt(dof * s * s / chi2_upper), rel=2e-4)
    assert hi == pytest.approx(math.sqrt(dof * s * s / chi2_lower), rel=2e-3)


def test_paper_survey_seventeen_points_at_thirty_arcsec() -> None:
    lo, hi = sigma_interval(30.0 / 3600.0, 17, 0.95)
    # 30" * sqrt(16/28.845) = 22.34", 30" * sqrt(16/6.908) = 45.66"
    assert lo * 3600.0 == pytest.approx(22.34, abs=0.01)
    assert hi * 3600.0 == pytest.approx(45.66, abs=0.01)


def test_hand_computed_small_survey() -> None:
    result = calibrate_sigma(_points([1.0, 2.0, 3.0, 4.0]))
    # s^2 = 5/3; (n-1)s^2 = 5; 5/9.348 = 0.53487; 5/0.21580 = 23.170
    assert result.n == 4
    assert result.mean_residual_deg == pytest.approx(2.5)
    assert result.s_deg == pytest.approx(math.sqrt(5.0 / 3.0))
    assert result.sigma_deg[0] == pytest.approx(0.73135, rel=1e-4)
    assert result.sigma_deg[1] == pytest.approx(4.8135, rel=1e-3)


def test_interval_covers_true_sigma_at_nominal_rate() -> None:
    rng = np.random.default_rng(5)
    sigma = 0.01
    trials = 2000
    covered = 0
    for _ in range(trials):
        result = calibrate_sigma(_points(list(rng.normal(0.003, sigma, 17))))
        lo, hi = result.sigma_deg
        assert lo < result.s_deg < hi
        covered += lo <= sigma <= hi
    # binomial standard deviation sqrt(0.95 * 0.05 / 2000) = 0.0049
    assert covered / trials == pytest.approx(0.95, abs=0.02)


def test_refuses_too_few_and_degenerate_surveys() -> None:
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate_sigma(_points([0.1, 0.2]))
    with pytest.raises(CalibrationError, match="camera_elevation_deg is constant"):
        calibrate_sigma([ElevationPoint(f"P{i}", 5.0, 5.0 + 0.01 * i) for i in range(5)])
    with pytest.raises(CalibrationError, match="theodolite_elevation_deg is constant"):
        calibrate_sigma([ElevationPoint(f"P{i}", 5.0 + 0.01 * i, 5.0) for i in range(5)])
    with pytest.raises(CalibrationError, match="residuals are equal"):
        calibrate_sigma(_points([0.25] * 6))


def test_parser_rejects_bad_rows() -> None:
    header = b"point,camera_elevation_deg,theodolite_elevation_deg\n"
    with pytest.raises(InputError, match="header"):
        parse_points_csv(b"point,cam,theo\nA,1,2\n")
    with pytest.raises(InputError, match=r":2: camera_elevation_deg 'x' is not a number"):
        parse_points_csv(header + b"A,x,2\n")
    with pytest.raises(InputError, match="appears twice"):
        parse_points_csv(header + b"A,1,2\nA,2,3\n")
    with pytest.raises(InputError, match=r"not an elevation"):
        parse_points_csv(header + b"A,nan,2\n")
    points = parse_points_csv(header + b"A, 1.5 ,1.25\n\nB,2,2.5\n")
    assert [(p.point, p.residual_deg) for p in points] == [("A", 0.25), ("B", -0.5)]


def test_cli_writes_interval_and_keeps_the_rest_of_the_config(tmp_path: Path, capsys) -> None:
    config = tmp_path / "viper.toml"
    config.write_text(CONFIG_TEXT)
    assert main(["calibrate", "theodolite", str(EXAMPLE), "--config", str(config), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n"] == 17
    expected = calibrate_sigma(parse_points_csv(EXAMPLE.read_bytes()))
    assert out["s_deg"] == pytest.approx(expected.s_deg, rel=1e-12)
    assert out["sensor_sigma_deg"] == pytest.approx(list(expected.sigma_deg), rel=1e-5)
    # no map share: the floor of the estimator's learned sigma is the sensor's own interval
    assert out["map_sigma_deg"] == [0.0, 0.0]
    assert out["sigma_deg"] == out["sensor_sigma_deg"]
    assert out["sigma_deg"] == pytest.approx([0.0084, 0.0172], abs=1e-4)
    slo, shi = out["sensor_sigma_deg"]
    text = config.read_text()
    # the search's sigma_deg is left as it was; the floor is added
    assert text.replace(f"\nsensor_sigma_deg = [{slo!r}, {shi!r}]", "") == CONFIG_TEXT
    cfg = load_config(config).estimator
    assert cfg.sigma_deg == (0.2, 0.4) and cfg.sensor_sigma_deg == (slo, shi) and cfg.sigma_floor_deg == slo
    assert [p.name for p in tmp_path.iterdir()] == ["viper.toml"]  # no temporary file left behind


def test_cli_prints_a_table(capsys) -> None:
    assert main(["calibrate", "theodolite", str(EXAMPLE)]) == 0
    out = capsys.readouterr().out
    assert "P17" in out and "95% interval for sigma" in out


BAD_INPUTS = {
    "too_few": "point,camera_elevation_deg,theodolite_elevation_deg\nA,1.0,1.01\nB,2.0,2.02\n",
    "constant": "point,camera_elevation_deg,theodolite_elevation_deg\nA,1.0,1.01\nB,1.0,2.02\nC,1.0,3.0\n",
    "not_a_number": "point,camera_elevation_deg,theodolite_elevation_deg\nA,1.0,one\n",
    "empty": "",
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_cli_bad_input_is_one_line_and_config_untouched(tmp_path: Path, capsys, case: str) -> None:
    config = tmp_path / "viper.toml"
    config.write_text(CONFIG_TEXT)
    before = config.read_bytes()
    points = tmp_path / "points.csv"
    points.write_text(BAD_INPUTS[case])
    assert main(["calibrate", "theodolite", str(points), "--config", str(config)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("viper calibrate: error:")
    assert config.read_bytes() == before


def test_cli_missing_points_file_and_missing_config(tmp_path: Path, capsys) -> None:
    assert main(["calibrate", "theodolite", str(tmp_path / "absent.csv")]) == 2
    assert "absent.csv: file not found" in capsys.readouterr().err
    missing = tmp_path / "absent.toml"
    assert main(["calibrate", "theodolite", str(EXAMPLE), "--config", str(missing)]) == 2
    assert "absent.toml: file not found" in capsys.readouterr().err
    assert not missing.exists()


def test_cli_refuses_an_invalid_config_and_leaves_it(tmp_path: Path, capsys) -> None:
    config = tmp_path / "viper.toml"
    config.write_text(CONFIG_TEXT + "[estimator.extra]\nunknown = 1\n")
    before = config.read_bytes()
    assert main(["calibrate", "theodolite", str(EXAMPLE), "--config", str(config)]) == 2
    assert "unknown key estimator.extra" in capsys.readouterr().err
    assert config.read_bytes() == before


def test_estimator_sigma_is_sensor_and_map_in_quadrature() -> None:
    from viper_calibration.theodolite import MAP_SIGMA_DEG, combine_sigma

    result = calibrate_sigma(_points([0.3, -0.2, 0.1, -0.4, 0.25]), map_sigma_deg=(0.4, 0.5))
    lo, hi = result.sigma_deg
    assert result.estimator_sigma_deg == pytest.approx(((lo**2 + 0.16) ** 0.5, (hi**2 + 0.25) ** 0.5), rel=1e-12)
    assert combine_sigma((0.3, 0.4), (0.4, 0.3)) == pytest.approx((0.5, 0.5))
    assert MAP_SIGMA_DEG == (0.0, 0.0)
    with pytest.raises(InputError, match="map share 0.5,0.2 deg"):
        calibrate_sigma(_points([0.3, -0.2, 0.1]), map_sigma_deg=(0.5, 0.2))


def test_cli_map_share_option_and_report(tmp_path: Path, capsys) -> None:
    assert main(["calibrate", "theodolite", str(EXAMPLE), "--map-share", "0.3,0.8", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # a map share asked for: the sensor's [0.0084, 0.0172] and the map's [0.3, 0.8] in quadrature
    assert out["sigma_deg"] == pytest.approx([0.300118, 0.800186], abs=1e-6)
    assert main(["calibrate", "theodolite", str(EXAMPLE)]) == 0
    text = capsys.readouterr().out
    assert "the sensor's share" in text and "map's share: [0, 0] deg" in text
    assert "floor of the estimator's learned sigma (sensor and map in quadrature): [0.008" in text
    with pytest.raises(SystemExit) as exited:
        main(["calibrate", "theodolite", str(EXAMPLE), "--map-share", "0.8,0.3"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0 <= LO <= HI" in err
