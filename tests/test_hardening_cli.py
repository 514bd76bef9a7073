"""Every command that writes, over a matrix of bad output paths, on real disks.

Each case runs ``viper`` as a user would (``main`` with the argument list) and must end with a
non-zero exit status, exactly one line on stderr, no traceback, and the work folder exactly as it
was: no temporary file left, no new file, pre-existing files byte for byte the same.  The full
disk is a filled 64 KiB tmpfs and the read-only folder a read-only tmpfs (skipped with the reason
where mounting is not permitted).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.cli.main import main
from appliance.logbook.writer import Logbook
from appliance.skyline import write_skyline_csv
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline
from tests.test_hardening_atomic import fill, snapshot

WINDOW = "--search-bounds=-84.30,36.55,-84.27,36.57"


def _mount(where: Path, opts: str) -> bool:
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True)
    return done.returncode == 0


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """Inputs, decoys and the two small disks; unmounted at the end."""
    w = tmp_path_factory.mktemp("hardening")
    (w / "a_file").write_text("a file, not a folder\n")
    (w / "a_folder").mkdir()
    (w / "m.tif").write_bytes(b"stands for a DEM")
    dem = load_dem("jacksboro")
    sky = render_skyline(dem, 36.56, -84.285, 1.5, np.arange(360.0), 15_000.0)
    write_skyline_csv(sky, w / "sky.csv")
    assert main(["precompute", "jacksboro", WINDOW, "--out", str(w / "map.viperdb")]) == 0
    pano = np.full((180, 720, 3), 200, np.uint8)
    rows = (90 - 12 * np.sin(np.radians(np.arange(720)))).astype(int)
    for c, r in enumerate(rows):
        pano[r:, c] = (40, 90, 60)
    cv2.imwrite(str(w / "pano.png"), pano)
    with Logbook.create(w / "session.mcap") as log:
        log.write_json("/viper/test", "viper.Skyline", {"azimuth_deg": [0.0], "elevation_deg": [1.0]}, 1)
    (w / "viper.toml").write_text("# site config\n[estimator]\nheading_tolerance_deg = 4.0\n")
    shutil.copy(Path(__file__).resolve().parents[1] / "calibration" / "examples" / "theodolite_points.csv",
                w / "survey.csv")
    mounts = []
    if _mount(w / "ro", "size=64k,ro"):
        mounts.append(w / "ro")
    if _mount(w / "full", "size=64k"):
        mounts.append(w / "full")
        (w / "full" / "viper.toml").write_text((w / "viper.toml").read_text())
        fill(w / "full")
    yield w
    for m in mounts:
        subprocess.run(["umount", str(m)], check=False)


# Commands writing one file: argument list with OUT for the output path; the input it must not replace.
FILE_COMMANDS = {
    "render": (["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--out", "OUT"], "sky.csv"),
    "precompute": (["precompute", "m.tif", WINDOW, "--out", "OUT"], "m.tif"),
    "skyline --out": (["skyline", "pano.png", "--out", "OUT"], "pano.png"),
    "skyline --overlay": (["skyline", "pano.png", "--out", "new.csv", "--overlay", "OUT"], "pano.png"),
    "stitch": (["stitch", "shot_stage000.png", "shot_stage090.png", "--hfov-deg", "100", "--out", "OUT"],
               "shot_stage000.png"),
    "log recover": (["log", "recover", "session.mcap", "--out", "OUT"], "session.mcap"),
    "calibrate theodolite": (["calibrate", "theodolite", "survey.csv", "--config", "OUT"], "survey.csv"),
}
# What each bad place is, for a file output; "input" is the command's own input.
FILE_PLACES = ["missing/out.csv", "a_file/out.csv", "a_folder", "existing", "input", "ro/out.csv", "full/out.csv"]
# Commands writing into a folder.
FOLDER_COMMANDS = {
    "estimate --report": ["estimate", "map.viperdb", "sky.csv", "--report", "OUT"],
    "replay": ["replay", "session.mcap", "--db", "map.viperdb", "--out", "OUT"],
    "demo": ["demo", "--skyline-only", "--out", "OUT"],
}
FOLDER_PLACES = ["a_file", "a_file/report", "ro/report", "input"]

CASES = [(name, place) for name in FILE_COMMANDS for place in FILE_PLACES]
CASES += [(name, place) for name in FOLDER_COMMANDS for place in FOLDER_PLACES]
CASES += [("estimate --report", "full/report"), ("estimate --report", "report exists")]
# Not meaningful: theodolite edits an existing config in place (no "existing" refusal, a missing
# one is its own error), and the stitch inputs exist only as names (checked before reading).
SKIP = {("calibrate theodolite", "existing"), ("calibrate theodolite", "ro/out.csv")}


def _argv(name: str, place: str, w: Path) -> list[str]:
    if name in FILE_COMMANDS:
        args, own_input = FILE_COMMANDS[name]
        if place == "existing":
            target = w / f"existing-{name.replace(' ', '_')}.out"
            target.write_bytes(b"an earlier result\n")
        elif place == "input":
            target = w / own_input
        elif name == "calibrate theodolite" and place == "full/out.csv":
            target = w / "full" / "viper.toml"
        else:
            target = w / place
    else:
        args = FOLDER_COMMANDS[name]
        if place == "input":
            target = w / ("sky.csv" if name != "demo" else "a_file")
        elif place == "report exists":
            target = w / "old_report"
            target.mkdir(exist_ok=True)
            (target / "01-sky.png").write_bytes(b"an earlier picture")
        else:
            target = w / place
    return [str(target) if a == "OUT" else (str(w / a) if (w / a).exists() or a.endswith((".png", ".csv")) else a)
            for a in args]


@pytest.mark.parametrize("name, place", CASES, ids=[f"{n} -> {p}" for n, p in CASES])
def test_a_bad_output_path_is_one_line_and_changes_nothing(work, name, place, capsys):
    if (name, place) in SKIP:
        pytest.skip("not a bad path for this command")
    if place.startswith(("ro/", "full/")) and not (work / place.split("/")[0]).is_mount():
        pytest.skip("cannot mount a tmpfs here: needs root in a sandbox")
    argv = _argv(name, place, work)
    capsys.readouterr()
    before = snapshot(work)
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc != 0, out
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("viper ") and "error" in err
    assert snapshot(work) == before


def test_force_replaces_an_existing_output_and_leaves_no_temporary(work, capsys):
    out = work / "forced" / "sky.csv"
    out.parent.mkdir()
    out.write_text("old\n")
    argv = ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--out", str(out), "--force"]
    assert main(argv) == 0
    assert out.read_text().startswith("azimuth_deg,elevation_deg\n")
    assert [p.name for p in out.parent.iterdir()] == ["sky.csv"]


def test_a_report_leaves_only_its_own_files(work, capsys):
    report = work / "report_ok"
    assert main(["estimate", str(work / "map.viperdb"), str(work / "sky.csv"), "--report", str(report)]) == 0
    assert sorted(p.name for p in report.iterdir()) == ["01-sky-points.geojson", "01-sky-points.qml",
                                                        "01-sky-posterior.qml", "01-sky-posterior.tif",
                                                        "01-sky-region.geojson", "01-sky-region.qml",
                                                        "01-sky.png", "report.html"]


def test_negative_values_are_taken_as_users_type_them(work, capsys):
    argv = ["estimate", str(work / "map.viperdb"), str(work / "sky.csv"), "--json", "--truth", "36.56,-84.285"]
    assert main(argv) == 0
    argv = ["estimate", str(work / "map.viperdb"), str(work / "sky.csv"), "--json", "--truth", "-36.56,84.285"]
    assert main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and '"truth"' in out[1]


BAD_ARGUMENTS = [
    ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--max-range", "0"],
    ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--height", "nan"],
    ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--refraction", "nan"],
    ["render", "jacksboro", "--lat", "91", "--lon", "-84.285"],
    ["gps", "session.mcap", "--count", "-1"],
    ["demo", "--time-rate", "0", "--out", "OUT"],
    ["precompute", "jacksboro", "--out", "OUT", "--search-bounds", "-84.30,36.55,-84.27,36.57", "--spacing", "-5"],
]


@pytest.mark.parametrize("argv", BAD_ARGUMENTS, ids=[" ".join(a[:1] + a[-2:]) for a in BAD_ARGUMENTS])
def test_a_bad_argument_is_one_line_and_writes_nothing(work, argv, capsys):
    argv = [str(work / "new_out") if a == "OUT" else (str(work / a) if a == "session.mcap" else a) for a in argv]
    capsys.readouterr()
    before = snapshot(work)
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc != 0 and out == ""
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert snapshot(work) == before


def test_a_gps_truth_off_the_database_is_recognised(work):
    from appliance.cli.replay import truth_on_map
    from appliance.terrain.database import load_database

    db = load_database(work / "map.viperdb")
    assert truth_on_map(db, (36.56, -84.285))
    assert not truth_on_map(db, (36.70, -84.285))  # 15 km north of the window
    assert not truth_on_map(db, (46.0, 7.0))
