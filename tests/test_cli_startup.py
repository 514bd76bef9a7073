"""The command line starts at once: only the command being run is imported."""

from __future__ import annotations

import argparse
import json
import pkgutil
import subprocess
import sys

import numpy as np
import pytest

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
        # the command line's own module, and the client of `viper serve` (the standard library only)
        first = {"appliance.cli.main", "appliance.cli._forward"}
        assert not any(m.startswith("appliance.cli.") and m not in first for m in loaded), argv


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


#: run first in a process: numba's compiler registries and the whole of scipy.linalg, as numba loads them
WHOLE_NUMBA = "import scipy.linalg\nfrom numba.core.registry import cpu_target\ncpu_target.target_context.refresh()"


@pytest.fixture(scope="module")
def window_skyline(dem, tmp_path_factory):
    from appliance.skyline import Skyline, write_skyline_csv
    from appliance.terrain.horizon import render_skyline

    az = np.arange(360.0)
    sky = tmp_path_factory.mktemp("sky") / "sky.csv"
    write_skyline_csv(Skyline(az, render_skyline(dem, 36.585, -84.26, azimuths_deg=az).elevation_deg), sky)
    return sky


def test_an_estimate_loads_neither_scipy_linalg_nor_numbas_compiler(window_db, window_skyline):
    """The estimator's kernels call LAPACK (np.linalg.solve) through scipy.linalg.cython_lapack: it is
    loaded on its own, not with the whole of scipy.linalg; the kernels come from numba's cache without
    its compiler's registries.  The records are the same bit for bit as in a process that loaded
    both first."""
    import numba

    from appliance.numerics import CACHE_LOAD_TESTED

    for heading in (["--heading-tolerance", "4"], ["--unknown-heading"]):
        argv = ["estimate", window_db.path, str(window_skyline), "--json", *heading]
        _estimate_in_fresh_process(argv)  # the kernels into numba's cache, if they are not there yet
        lean, loaded = _estimate_in_fresh_process(argv)
        assert {"scipy.linalg.cython_blas", "scipy.linalg.cython_lapack"} <= loaded
        assert "scipy.linalg" not in loaded and "numpy.f2py" not in loaded
        if tuple(int(v) for v in numba.__version__.split(".")[:2]) in CACHE_LOAD_TESTED:
            assert not {"numba.np.arraymath", "numba.np.npyimpl", "numba.typed.typeddict"} & loaded
        whole, loaded_whole = _estimate_in_fresh_process(argv, first=WHOLE_NUMBA)
        assert {"scipy.linalg", "numba.np.arraymath"} <= loaded_whole
        assert lean == whole
        assert lean["status"] in ("ok", "ambiguous") and abs(lean["lat"] - 36.585) < 0.01


def test_numba_compiles_as_before_after_loading_cached_kernels(window_db, window_skyline):
    """A kernel that is not in the cache, compiled after the estimator's came from it: numba's compiler
    loads what it needs then (here np.dot on BLAS, a typed list, an array reduction); scipy.linalg
    imported after is the whole package, with the Cython modules the estimate loaded as its own."""
    code = f"""
import numba, numpy as np
from appliance.cli.main import main
assert main(["estimate", {window_db.path!r}, {str(window_skyline)!r}, "--json"]) == 0

@numba.njit
def fresh(a, b):
    out = numba.typed.List()
    out.append(np.dot(a, b))
    out.append(np.sum(np.sqrt(a)) + np.linalg.solve(np.diag(b), a)[1])
    return out

print(list(fresh(np.array([1.0, 4.0, 9.0]), np.array([2.0, 4.0, 8.0]))))
import sys
import scipy.linalg, scipy.optimize
assert scipy.linalg.cython_lapack is sys.modules["scipy.linalg.cython_lapack"]
assert scipy.linalg.cython_blas is sys.modules["scipy.linalg.cython_blas"]
print(float(scipy.linalg.solve(np.diag([2.0, 4.0]), np.array([1.0, 2.0]))[1]),
      round(float(scipy.optimize.minimize_scalar(lambda x: (x - 3.0) ** 2).x), 6))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-2:] == ["[90.0, 7.0]", "0.5 3.0"]
