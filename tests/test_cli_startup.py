"""The command line starts at once: only the command being run is imported."""

from __future__ import annotations

import argparse
import json
import pkgutil
import subprocess
import sys

import numpy as np

import appliance.cli as cli_pkg
from appliance.cli.main import COMMANDS, build_parser, command_of


def test_the_command_table_lists_every_command_module_with_its_own_help():
    modules = {m.name for m in pkgutil.iter_modules(cli_pkg.__path__)
               if m.name != "main" and not m.name.startswith("_")}
    assert {module for module, _ in COMMANDS.values()} == modules
    full = build_parser("*")
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    listed = {c.dest: c.help for c in sub._choices_actions}
    assert listed == {name: help_text for name, (_, help_text) in COMMANDS.items()}


def _modules_after(argv: list[str]) -> set[str]:
    code = (f"import json, sys\nfrom appliance.cli.main import main\ntry:\n    main({argv!r})\n"
            "except SystemExit:\n    pass\nprint(json.dumps(sorted(sys.modules)), file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(json.loads(out.stderr.strip().splitlines()[-1]))


def test_help_loads_no_numerical_library():
    for argv in (["--help"], ["--log-level", "debug", "--help"]):
        loaded = _modules_after(argv)
        assert not {"numpy", "numba", "scipy", "cv2", "rasterio", "pyproj", "tqdm"} & loaded, argv
        assert not any(m.startswith("appliance.cli.") and m != "appliance.cli.main" for m in loaded), argv


def test_a_command_loads_its_own_module_only():
    loaded = _modules_after(["skyline", "--help"])
    assert "appliance.cli.skyline" in loaded
    assert not {"appliance.cli.estimate", "appliance.cli.precompute", "appliance.estimator.estimate"} & loaded


def test_the_command_is_found_after_global_options():
    assert command_of(["--version"]) is None
    assert command_of(["estimate", "db", "demo.csv"]) == "estimate"


def test_detecting_a_skyline_loads_no_compiler(tmp_path):
    """`viper skyline` is a one-shot command: it detects with numpy and OpenCV, and loading numba's
    kernels would cost it more than the detection itself."""
    import numpy as np

    from appliance.vision.panorama import save_panorama
    from appliance.vision.synth import analytic_skyline_fn, render_panorama

    synth = render_panorama(analytic_skyline_fn(seed=3), np.random.default_rng(3), px_per_rad=150.0, height_px=120)
    image = tmp_path / "pano.png"
    save_panorama(synth.panorama, image)
    out = tmp_path / "sky.csv"
    loaded = _modules_after(["skyline", str(image), "--out", str(out)])
    assert out.is_file() and len(out.read_text().splitlines()) > 300  # a header and 360 azimuths
    assert not {"numba", "scipy", "appliance.estimator.estimate"} & loaded


def _estimate_in_fresh_process(argv: list[str], first: str = "") -> tuple[dict, set[str]]:
    code = (f"{first}\nimport json, sys\nfrom appliance.cli.main import main\nrc = main({argv!r})\n"
            "print(json.dumps(sorted(sys.modules)), file=sys.stderr)\nsys.exit(rc)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    record = json.loads(out.stdout.strip().splitlines()[-1])
    record.pop("elapsed_ms")
    return record, set(json.loads(out.stderr.strip().splitlines()[-1]))


def test_an_estimate_loads_scipys_lapack_without_scipy_linalg(window_db, dem, tmp_path):
    """The estimator's kernels call LAPACK (np.linalg.solve) through scipy.linalg.cython_lapack: it is
    loaded on its own, not with the whole of scipy.linalg, and the record is the same bit for bit as
    in a process that imported scipy.linalg first."""
    from appliance.skyline import Skyline, write_skyline_csv
    from appliance.terrain.horizon import render_skyline

    az = np.arange(360.0)
    sky = tmp_path / "sky.csv"
    write_skyline_csv(Skyline(az, render_skyline(dem, 36.585, -84.26, azimuths_deg=az).elevation_deg), sky)
    for heading in (["--heading-tolerance", "4"], ["--unknown-heading"]):
        argv = ["estimate", window_db.path, str(sky), "--json", *heading]
        lean, loaded = _estimate_in_fresh_process(argv)
        assert {"scipy.linalg.cython_blas", "scipy.linalg.cython_lapack"} <= loaded
        assert "scipy.linalg" not in loaded and "numpy.f2py" not in loaded
        whole, loaded_whole = _estimate_in_fresh_process(argv, first="import scipy.linalg")
        assert "scipy.linalg" in loaded_whole
        assert lean == whole
        assert lean["status"] in ("ok", "ambiguous") and abs(lean["lat"] - 36.585) < 0.01
