"""A catalogue of bad inputs across the commands: damaged DEMs of every format, bad skyline CSVs,
bad configurations, damaged databases and bad arguments.

Each case runs ``viper`` in-process as a user would (``main`` with the argument list) and must end
with a non-zero exit status, exactly one line on stderr, no traceback, and the work folder as it
was (no new file, no file changed).  The matrix of bad output paths (missing folder, a file in the
way, read-only and full disks) is in tests/test_hardening_cli.py.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from appliance.cli.main import main
from appliance.skyline import write_skyline_csv
from appliance.terrain.dem import load_dem
from appliance.terrain.horizon import render_skyline

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
WINDOW = "--search-bounds=-84.30,36.55,-84.28,36.56"

# One DEM of every format in ../shared/data; a PDS image travels with its label.
DEMS = {
    "tif": "dem_geotiff/gmted2010_clips/matterhorn.tiff",
    "webmerc": "dem_geotiff/msh00_MountStHelens_2000_webmerc.tif",
    "hgt": "dem_srtm_hgt/N44W072.hgt",
    "usgs": "dem_usgs_ascii/SainteHelens.dem",
    "pds": "dem_planetary/LDEM_4.IMG",
    "npz": "dem_other/jacksboro_fault_dem.npz",
    "e00": "dem_other/msh00_83_MountStHelens_2000.e00",
}
# How each DEM is damaged: (name, function of the original bytes).
DEM_DAMAGE = {
    "empty": lambda b: b"",
    "first-100-bytes": lambda b: b[:100],
    "first-tenth": lambda b: b[: len(b) // 10],
    "header-bits-flipped": lambda b: bytes(x ^ 0xA5 for x in b[:64]) + b[64:],
}
# The damage that still loads by design (the bytes that survive are a readable map): a PDS image's
# label carries the georeferencing, so its image is damaged only by truncation; flipping the first
# bytes of an SRTM tile changes heights only (no header to break); the first 64 bytes of a USGS
# ASCII DEM and of an .e00 export are free text (the map's name, the export's path).
DEM_LOADS_ANYWAY = {("hgt", "header-bits-flipped"), ("pds", "header-bits-flipped"), ("usgs", "header-bits-flipped"),
                    ("e00", "header-bits-flipped")}

BAD_SKYLINES = {
    "empty": "",
    "header-only": "azimuth_deg,elevation_deg\n",
    "wrong-header": "az,el\n0,1\n",
    "text-elevation": "azimuth_deg,elevation_deg\n0,high\n",
    "text-azimuth": "azimuth_deg,elevation_deg\nnorth,1\n",
    "elevation-100": "azimuth_deg,elevation_deg\n0,100\n",
    "elevation-inf": "azimuth_deg,elevation_deg\n0,inf\n",
    "azimuth-nan": "azimuth_deg,elevation_deg\nnan,1\n",
    "azimuth-inf": "azimuth_deg,elevation_deg\ninf,1\n",
    "three-fields-in-two": "azimuth_deg,elevation_deg\n0,1,2\n",
    "one-field": "azimuth_deg,elevation_deg\n0\n",
    "conflicting-duplicate": "azimuth_deg,elevation_deg\n0,1.5\n1,1.6\n1,3.0\n",
    "conflict-across-north": "azimuth_deg,elevation_deg\n0,1.5\n360,2.5\n",
    "confidence-2": "azimuth_deg,elevation_deg,confidence\n0,1,2\n",
    "confidence-text": "azimuth_deg,elevation_deg,confidence\n0,1,sure\n",
    "nul-byte": "azimuth_deg,elevation_deg\n0,1\x00\n",
    "binary": "\x89PNG\r\n\x1a\n\x00\x00",
    "all-missing": "azimuth_deg,elevation_deg\n" + "".join(f"{a},\n" for a in range(360)),
}
SKYLINE_BYTES = {"latin-1": "azimuth_deg,elevation_deg\n0,1\u00b0\n".encode("latin-1"),
                 "utf-16": "azimuth_deg,elevation_deg\n0,1\n".encode("utf-16")}

BAD_CONFIGS = {
    "not-toml": "[estimator\nsigma_deg = 1\n",
    "unknown-table": "[estimatr]\nsigma_deg = [0.2, 0.4]\n",
    "unknown-key": "[estimator]\nsigmadeg = [0.2, 0.4]\n",
    "wrong-type": "[session]\nsettle_s = \"long\"\n",
    "sigma-reversed": "[estimator]\nsigma_deg = [0.8, 0.3]\n",
    "sigma-zero": "[estimator]\nsigma_deg = [0.0, 0.3]\n",
    "min-valid-negative": "[estimator]\nmin_valid_fraction = -1\n",
    "removed-terrain-table": "[terrain]\ncamera_height_m = 1.5\n",
    "occlusion-one": "[estimator]\nocclusion_weight = 1.0\n",
    "time-rate-zero": "[sim]\ntime_rate = 0\n",
    "gps-rate-zero": "[sim]\ngps_rate_hz = 0\n",
    "lat-beyond-pole": "[sim]\nlat_deg = 95.0\n",
    "interval-negative": "[session]\ninterval_s = -1\n",
    "truth-duration-negative": "[session]\ntruth_duration_s = -30\n",
    "compass-steps-two": "[session]\ncompass_steps = 2\n",
    "overlap-one": "[session]\ncapture_overlap = 1.0\n",
    "mask-one-angle": "[session]\nbody_mask_deg = [[1.0]]\n",
    "fsync-zero": "[logbook]\nfsync_interval_s = 0\n",
    "compression-unknown": "[logbook]\ncompression = \"bz2\"\n",
    "encoding-unknown": "[logbook]\nencoding = \"ros3\"\n",
    "platform-unknown": "[platform]\nkind = \"rover9000\"\n",
    "baud-zero": "[devices.gps]\nbaudrate = 0\n",
    "i2c-address-big": "[devices.compass]\ni2c_address = 300\n",
    "camera-width-zero": "[devices.camera]\nwidth = 0\n",
    "garbage-rate-two": "[sim.faults]\ngps_garbage_rate = 2.0\n",
}
CONFIG_COMMANDS = {
    "capture": ["capture", "--config", "CFG", "--log-dir", "logs"],
    "daemon": ["daemon", "session", "--config", "CFG", "--log-dir", "logs"],
    "devices": ["devices", "--config", "CFG"],
    "estimate": ["estimate", "map.viperdb", "sky.csv", "--config", "CFG"],
}

# Damaged databases: (name, function of the good database's bytes).
BAD_DATABASES = {
    "empty": lambda b: b"",
    "magic-only": lambda b: b[:8],
    "header-cut": lambda b: b[:40],
    "arrays-cut": lambda b: b[: len(b) // 2],
    "checksums-cut": lambda b: b[:-3],
    "bit-in-arrays": lambda b: _flip(b, len(b) - 200),
    "bit-in-header": lambda b: _flip(b, b.index(b'"height_m": 1.5') + 13),
    "header-length-huge": lambda b: b[:8] + b"\xff\xff\xff\x7f" + b[12:],
    "json-broken": lambda b: b[:12] + b"[" + b[13:],
    "version-1": lambda b: b.replace(b'"format_version": 3', b'"format_version": 1', 1),
    "png-instead": lambda b: b"\x89PNG\r\n\x1a\n" + b[8:64],
}
DB_COMMANDS = {
    "estimate": ["estimate", "DB", "sky.csv"],
    "estimate-json": ["estimate", "DB", "sky.csv", "--json"],
}

BAD_ARGUMENTS = {
    "no-command-args": ["precompute"],
    "render-lat-text": ["render", "jacksboro", "--lat", "north", "--lon", "-84.285"],
    "render-lat-91": ["render", "jacksboro", "--lat", "91", "--lon", "-84.285"],
    "render-max-range-0": ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--max-range", "0"],
    "render-height-nan": ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--height", "nan"],
    "render-azimuths-0": ["render", "jacksboro", "--lat", "36.56", "--lon", "-84.285", "--azimuths", "0"],
    "precompute-spacing-tiny": ["precompute", "jacksboro", "--spacing", "0.001", "--out", "new.viperdb"],
    "precompute-spacing-negative": ["precompute", "jacksboro", "--spacing", "-5", "--out", "new.viperdb"],
    "precompute-bounds-reversed": ["precompute", "jacksboro", "--search-bounds", "-84.27,36.57,-84.30,36.55",
                                   "--out", "new.viperdb"],
    "precompute-bounds-elsewhere": ["precompute", "jacksboro", "--search-bounds", "7,46,7.1,46.1",
                                    "--out", "new.viperdb"],
    "precompute-bounds-three": ["precompute", "jacksboro", "--search-bounds", "1,2,3", "--out", "new.viperdb"],
    "precompute-azimuths-4": ["precompute", "jacksboro", WINDOW, "--azimuths", "4", "--out", "new.viperdb"],
    "skyline-mask-400": ["skyline", "pano.png", "--mask", "10-400", "--out", "new.csv"],
    "skyline-mask-text": ["skyline", "pano.png", "--mask", "east-west", "--out", "new.csv"],
    "skyline-missing-image": ["skyline", "nothere.png", "--out", "new.csv"],
    "estimate-sigma-reversed": ["estimate", "map.viperdb", "sky.csv", "--sigma", "0.8,0.3"],
    "estimate-missing-csv": ["estimate", "map.viperdb", "nothere.csv"],
    "estimate-missing-db": ["estimate", "nothere.viperdb", "sky.csv"],
    "gps-count-negative": ["gps", "nothere.log", "--count", "-1"],
    "demo-time-rate-0": ["demo", "--time-rate", "0", "--out", "new-demo"],
    "dem-info-missing": ["dem", "info", "nothere.tif"],
    "dem-info-folder": ["dem", "info", "a_folder"],
    "calibrate-theodolite-missing": ["calibrate", "theodolite", "nothere.csv"],
    "calibrate-theodolite-map-share": ["calibrate", "theodolite", "survey.csv", "--map-share", "0.8,0.3"],
    "calibrate-theodolite-confidence": ["calibrate", "theodolite", "survey.csv", "--confidence", "1.5"],
    "log-info-missing": ["log", "info", "nothere.mcap"],
    "precompute-azimuths-90": ["precompute", "jacksboro", WINDOW, "--azimuths", "90", "--out", "new.viperdb"],
    "unknown-command": ["teleport"],
}


def _flip(b: bytes, i: int) -> bytes:
    out = bytearray(b)
    out[i] ^= 0x04
    return bytes(out)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    w = tmp_path_factory.mktemp("catalogue")
    (w / "a_folder").mkdir()
    (w / "logs").mkdir()
    dem = load_dem("jacksboro")
    write_skyline_csv(render_skyline(dem, 36.555, -84.29, 1.5, np.arange(360.0), 15_000.0), w / "sky.csv")
    assert main(["precompute", "jacksboro", WINDOW, "--azimuths", "120", "--out", str(w / "map.viperdb")]) == 0
    good = (w / "map.viperdb").read_bytes()
    for name, damage in BAD_DATABASES.items():
        (w / f"db-{name}.viperdb").write_bytes(damage(good))
    (w / "db-folder.viperdb").mkdir()
    pano = np.full((360, 720, 3), 200, np.uint8)
    pano[200:] = (40, 90, 60)
    import cv2

    cv2.imwrite(str(w / "pano.png"), pano)
    shutil.copy(Path(__file__).resolve().parents[1] / "calibration" / "examples" / "theodolite_points.csv",
                w / "survey.csv")
    for key, rel in DEMS.items():
        src = SHARED / rel
        if not src.exists():
            continue
        for damage, fn in DEM_DAMAGE.items():
            folder = w / f"dem-{key}-{damage}"
            folder.mkdir()
            (folder / src.name).write_bytes(fn(src.read_bytes()))
            if src.suffix == ".IMG":
                shutil.copy(src.with_suffix(".LBL"), folder / src.with_suffix(".LBL").name)
    for name, text in BAD_SKYLINES.items():
        (w / f"sky-{name}.csv").write_text(text, encoding="utf-8")
    for name, raw in SKYLINE_BYTES.items():
        (w / f"sky-{name}.csv").write_bytes(raw)
    for name, text in BAD_CONFIGS.items():
        (w / f"cfg-{name}.toml").write_text(text)
    return w


def listing(folder: Path) -> dict[str, tuple[int, int] | None]:
    """Every path under ``folder`` with its size and modification time (None for folders)."""
    out: dict[str, tuple[int, int] | None] = {}
    for p in sorted(folder.rglob("*")):
        st = p.stat()
        out[str(p.relative_to(folder))] = None if p.is_dir() else (st.st_size, st.st_mtime_ns)
    return out


def run_bad(w: Path, argv: list[str], capsys) -> str:
    """Run ``viper argv`` in ``w``'s terms; assert the catalogue's four rules; return the error line."""
    args = [str(w / a) if (w / a).exists() or a.startswith(("new", "nothere")) else a for a in argv]
    capsys.readouterr()
    before = listing(w)
    try:
        rc = main(args)
    except SystemExit as exc:  # argparse: bad argument syntax
        rc = exc.code if isinstance(exc.code, int) else 2
    out, err = capsys.readouterr()
    assert rc != 0, out
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("viper") and ": error: " in lines[0], err
    assert listing(w) == before
    return lines[0]


DEM_CASES = [(k, d, c) for k in DEMS for d in DEM_DAMAGE for c in ("dem info", "render", "precompute")
             if (k, d) not in DEM_LOADS_ANYWAY]


@pytest.mark.parametrize("key, damage, command", DEM_CASES, ids=[f"{k}-{d}-{c}" for k, d, c in DEM_CASES])
def test_damaged_dem(work, key, damage, command, capsys):
    src = SHARED / DEMS[key]
    if not src.exists():
        pytest.skip(f"real data file {src} is absent")
    dem = str(work / f"dem-{key}-{damage}" / src.name)
    argv = {"dem info": ["dem", "info", dem],
            "render": ["render", dem, "--lat", "0", "--lon", "0", "--out", "new.csv"],
            "precompute": ["precompute", dem, "--out", f"new-{key}-{damage}.viperdb"]}[command]
    line = run_bad(work, argv, capsys)
    assert src.name in line


SKY_CASES = sorted(BAD_SKYLINES) + sorted(SKYLINE_BYTES)


@pytest.mark.parametrize("name", SKY_CASES)
def test_bad_skyline_csv(work, name, capsys):
    line = run_bad(work, ["estimate", "map.viperdb", f"sky-{name}.csv"], capsys)
    if name == "all-missing":
        assert "0 valid azimuths" in line
    else:
        assert f"sky-{name}.csv" in line


def test_conflicting_duplicate_names_both_lines(work, capsys):
    line = run_bad(work, ["estimate", "map.viperdb", "sky-conflicting-duplicate.csv"], capsys)
    assert line.endswith("line 4: azimuth 1 deg already on line 3 with another value (elevation 1.6 vs 3, "
                         "confidence 1 vs 1)")


CONFIG_CASES = [(c, n) for c in CONFIG_COMMANDS for n in BAD_CONFIGS]


@pytest.mark.parametrize("command, name", CONFIG_CASES, ids=[f"{c}-{n}" for c, n in CONFIG_CASES])
def test_bad_config(work, command, name, capsys):
    argv = [f"cfg-{name}.toml" if a == "CFG" else a for a in CONFIG_COMMANDS[command]]
    line = run_bad(work, argv, capsys)
    assert f"cfg-{name}.toml" in line


DB_CASES = [(c, n) for c in DB_COMMANDS for n in [*BAD_DATABASES, "folder"]]


@pytest.mark.parametrize("command, name", DB_CASES, ids=[f"{c}-{n}" for c, n in DB_CASES])
def test_damaged_database(work, command, name, capsys):
    argv = [f"db-{name}.viperdb" if a == "DB" else a for a in DB_COMMANDS[command]]
    line = run_bad(work, argv, capsys)
    assert f"db-{name}.viperdb" in line


def test_a_flipped_bit_in_a_database_names_its_block(work, capsys):
    line = run_bad(work, ["estimate", "db-bit-in-arrays.viperdb", "sky.csv"], capsys)
    assert "block 0 of 1" in line and "fails its CRC32 check" in line


@pytest.mark.parametrize("name", sorted(BAD_ARGUMENTS))
def test_bad_argument(work, name, capsys):
    run_bad(work, BAD_ARGUMENTS[name], capsys)


def test_the_catalogue_holds_at_least_150_cases():
    n = len(DEM_CASES) + len(SKY_CASES) + len(CONFIG_CASES) + len(DB_CASES) + len(BAD_ARGUMENTS)
    assert n >= 150, n
