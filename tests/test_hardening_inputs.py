"""Bad values and damaged input files: one-line errors from the readers and the commands' checks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.cli.main import main

WINDOW = "--search-bounds=-84.30,36.55,-84.27,36.57"


def _pano(path):
    pano = np.full((360, 720, 3), 200, np.uint8)
    rows = (180 - 12 * np.sin(np.radians(np.arange(720)))).astype(int)
    for c, r in enumerate(rows):
        pano[r:, c] = (40, 90, 60)
    cv2.imwrite(str(path), pano)


def _one_line_error(capsys, rc):
    out = capsys.readouterr()
    lines = out.err.strip().splitlines()
    assert rc != 0 and len(lines) == 1 and "Traceback" not in out.err
    return lines[0]


@pytest.mark.parametrize("spacing", ["0.001", "0.5"])
def test_precompute_refuses_a_grid_too_large_before_allocating(tmp_path, capsys, spacing):
    out = tmp_path / "m.viperdb"
    rc = main(["precompute", "jacksboro", "--spacing", spacing, "--out", str(out)])
    line = _one_line_error(capsys, rc)
    assert rc == 2
    assert f"--spacing {float(spacing):.3g} m gives" in line and "at most 50,000,000 terrain nodes" in line
    assert list(tmp_path.iterdir()) == []


def test_precompute_a_fine_spacing_over_a_small_window_still_builds(tmp_path, capsys):
    out = tmp_path / "m.viperdb"
    assert main(["precompute", "jacksboro", WINDOW, "--spacing", "60", "--azimuths", "36", "--out", str(out)]) == 0
    assert "skylines" in capsys.readouterr().out and out.is_file()


@pytest.mark.parametrize("mask,bad", [("10-400", "400"), ("350-10,-500-20", "-500"), ("400:10", "400")])
def test_skyline_mask_beyond_a_turn_is_refused(tmp_path, capsys, mask, bad):
    _pano(tmp_path / "pano.png")
    rc = main(["skyline", str(tmp_path / "pano.png"), "--mask", mask, "--out", str(tmp_path / "s.csv")])
    line = _one_line_error(capsys, rc)
    assert line.endswith(f"azimuth {bad} outside [-360, 360] degrees")
    assert not (tmp_path / "s.csv").exists()


def test_skyline_mask_within_a_turn_is_accepted(tmp_path, capsys):
    _pano(tmp_path / "pano.png")
    rc = main(["skyline", str(tmp_path / "pano.png"), "--mask", "-10-20,350-360", "--out", str(tmp_path / "s.csv")])
    assert rc == 0, capsys.readouterr().err
    rows = (tmp_path / "s.csv").read_text().splitlines()
    assert len(rows) > 300


def test_skyline_csv_with_a_byte_order_mark_is_read(tmp_path):
    from appliance.skyline import read_skyline_csv

    p = tmp_path / "export.csv"
    p.write_bytes("\ufeffazimuth_deg,elevation_deg\r\n0,1.5\r\n90,2.25\r\n180,\r\n".encode())
    sky = read_skyline_csv(p)
    assert sky.azimuth_deg.tolist() == [0.0, 90.0, 180.0]
    assert sky.elevation_deg[:2].tolist() == [1.5, 2.25] and np.isnan(sky.elevation_deg[2])


def test_skyline_csv_identical_duplicates_merge_and_conflicts_are_refused(tmp_path):
    from appliance.errors import InputError
    from appliance.skyline import parse_skyline_csv

    sky = parse_skyline_csv("azimuth_deg,elevation_deg\n0,1.5\n10,2\n360,1.5\n10,2.0\n20,\n380,\n")
    assert sky.azimuth_deg.tolist() == [0.0, 10.0, 20.0]
    assert sky.elevation_deg[:2].tolist() == [1.5, 2.0]
    with pytest.raises(InputError) as err:
        parse_skyline_csv("azimuth_deg,elevation_deg\n0,1.5\n10,2\n10,2.5\n", name="s.csv")
    assert str(err.value) == ("s.csv: line 4: azimuth 10 deg already on line 3 with another value "
                              "(elevation 2 vs 2.5, confidence 1 vs 1)")
    with pytest.raises(InputError, match="azimuth 0 deg already on line 2.*elevation 1.5 vs missing"):
        parse_skyline_csv("azimuth_deg,elevation_deg\n0,1.5\n360,\n")
    with pytest.raises(InputError, match=r"confidence 0\.9 vs 0\.5"):
        parse_skyline_csv("azimuth_deg,elevation_deg,confidence\n5,1,0.9\n5,1,0.5\n")
    kept = parse_skyline_csv("azimuth_deg,elevation_deg,confidence\n5,1,0.9\n5,1,0.9\n6,2,0.4\n")
    assert kept.confidence is not None and kept.confidence.tolist() == [0.9, 0.4]



def test_simulated_platform_is_announced_unless_chosen(tmp_path):
    from appliance.cli._platform import simulated_notice
    from appliance.config import load_config

    bare = tmp_path / "bare.toml"
    bare.write_text("[estimator]\nheading_tolerance_deg = 4.0\n")
    chosen = tmp_path / "sim.toml"
    chosen.write_text("[platform]\nkind = \"sim\"\n")
    hw = tmp_path / "hw.toml"
    hw.write_text("[platform]\nkind = \"hardware\"\n")
    assert simulated_notice("capture", load_config(bare), bare) == (
        f"viper capture: running the SIMULATED platform ({bare} has no [platform] table); set [platform] kind = "
        "\"hardware\" to drive the devices")
    assert simulated_notice("daemon session", load_config(None), None) == (
        "viper daemon session: running the SIMULATED platform (no --config given); set [platform] kind = "
        "\"hardware\" to drive the devices")
    assert simulated_notice("capture", load_config(chosen), chosen) is None
    assert simulated_notice("capture", load_config(hw), hw) is None


def test_run_all_lists_the_quick_benchmarks(capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "run_all.py"
    spec = importlib.util.spec_from_file_location("run_all", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "$ bench/terrain_speed.py" in lines and not any("session_chain" in ln for ln in lines)
    for name in mod.QUICK:
        assert (path.parent / f"{name}.py").is_file(), name
    assert mod.main(["no_such_bench"]) == 2


NATIVE_SCRIPT = """
import json, os, sys, threading
from appliance.native import native_messages

class Noisy:
    def __del__(self):
        raise ValueError("raised in a callback")

import contextlib, io
elsewhere = io.StringIO()  # a caller's own sys.stderr (a test harness, a service's log)
with contextlib.redirect_stderr(elsewhere), native_messages() as alone:
    os.write(2, b"libtiff: Invalid argument.\\n\\n")
    sys.stderr.write("UnicodeDecodeError: printed through sys.stderr\\n")
    Noisy()
assert elsewhere.getvalue() == "", elsewhere.getvalue()
stop = threading.Event()
other = threading.Thread(target=stop.wait)
other.start()
with native_messages() as beside:
    os.write(2, b"libtiff: beside a thread.\\n")
stop.set()
other.join()
print(json.dumps({"alone": alone, "beside": beside}))
"""


def test_native_messages_gathers_what_compiled_code_prints_only_when_alone():
    """In a fresh process (the test run itself keeps other threads alive): what compiled code prints
    on file descriptor 2, and a callback's unraisable exception, are listed instead of printed; with
    another thread alive, which may log on the same descriptor, nothing is taken from it."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", NATIVE_SCRIPT], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    said = json.loads(out.stdout)
    assert said["alone"] == ["libtiff: Invalid argument.", "UnicodeDecodeError: printed through sys.stderr",
                             "ValueError: raised in a callback"]
    assert said["beside"] == []
    assert out.stderr == "libtiff: beside a thread.\n"
