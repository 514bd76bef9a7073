"""A command whose optional library is not installed says, in one line, which extra brings it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from appliance.cli.main import main
from appliance.extras import MissingExtraError, missing_extra, require


def _run_without(module: str, argv: list[str]) -> subprocess.CompletedProcess[str]:
    """``viper ARGV`` in a fresh process where importing ``module`` fails as if it were not installed."""
    code = (f"import sys\nsys.modules[{module!r}] = None\nfrom appliance.cli.main import main\n"
            f"sys.exit(main({argv!r}))")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_a_command_module_that_imports_opencv_at_its_top_names_the_vision_extra():
    proc = _run_without("cv2", ["stitch", "--help"])
    assert proc.returncode == 1
    assert proc.stderr == ("viper stitch: error: this command needs OpenCV, which is not installed: "
                           "pip install 'viper-appliance[vision]'\n")
    assert proc.stdout == ""


def test_the_live_view_without_foxglove_is_one_line(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "foxglove", None)
    assert main(["capture", "--live", "0"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("viper capture: error:")] == [
        "viper capture: error: the live view (--live) needs foxglove-sdk, which is not installed: "
        "pip install 'viper-appliance[live]'"]


def test_a_tiled_build_without_dask_names_the_cluster_extra_and_leaves_no_folder(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "distributed", None)
    out = tmp_path / "tiles"
    assert main(["precompute", "jacksboro", "--tiles", "--out", str(out)]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "viper precompute: error: a tiled build (--tiles) needs dask.distributed, which is not installed: "
        "pip install 'viper-appliance[cluster]'"]
    assert not out.exists()


def test_require_returns_the_module_and_leaves_other_missing_modules_alone(monkeypatch):
    import json

    assert require("json", "reading JSON") is json  # not an optional module, but imported all the same
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(MissingExtraError, match=r"viper-appliance\[cluster\]") as info:
        require("distributed", "--workers")
    assert isinstance(info.value, ImportError) and info.value.extra == "cluster" and info.value.exit_code == 1
    # a module of the base install that is missing is a broken install: no extra to name
    assert missing_extra(ModuleNotFoundError("No module named 'rasterio'", name="rasterio")) is None
    assert missing_extra(ModuleNotFoundError("No module named 'cv2.gapi'", name="cv2.gapi")) is not None
