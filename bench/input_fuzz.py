"""Input-file fuzzing: mutated skyline CSVs, configurations, DEMs of every format and skyline databases.

Run: .venv/bin/python bench/input_fuzz.py [--count 20000] [--dem-count 12] [--seed 1] [--kinds fast]
     (appends to bench/results/input_fuzz.md)

Readers and their seeds:

- skyline CSV (``parse_skyline_csv``): a rendered skyline with and without the confidence column,
  with a byte order mark and CRLF; ``--count`` inputs.
- configuration (``load_config`` on a file): examples/tripod.toml, examples/sim-forest.toml and a
  file setting every section; ``--count`` inputs.
- DEM readers (``viper dem info``, in process, which loads the map with ``load_dem``): one file of
  every format in ../shared/data (GeoTIFF, SRTM .hgt, USGS ASCII .dem, PDS .IMG with its label, .npz,
  .e00), copied to a scratch folder and truncated or bit-flipped; ``--dem-count`` inputs per file
  (each load reads a whole map).
- skyline database (``load_database``): a small jacksboro database; ``--count`` inputs.
- tiled database index (``open_tiled``, then ``open_surface`` and a search with ``locate_tiled``): the
  ``index.json`` of a small 2 x 2 tiled jacksboro database, with a ``surface`` record naming the
  jacksboro map, and the whole-body Moon index of ``bench/moon_whole_body.py`` where its cache exists
  (opened and its surface record checked, not searched: one search takes seconds); ``--index-count``
  inputs, half of them byte mutations, half structural ones (a value replaced by a hostile one of
  another type or sign, a key deleted).
- images through ``viper skyline`` (``main`` in-process, as a user runs it): a small synthetic
  panorama as PNG and as JPEG with its geometry sidecar, and a small photo with its camera
  calibration TOML and an orientation sidecar; ``--image-count`` inputs, each mutating the image, the
  sidecar (bytes or structure) or the calibration.

- session logs (MCAP) through ``viper log info``, ``viper log recover`` and ``viper replay``: the log of
  ``viper demo --seed 11`` (made once into bench/cache/, with its jacksboro database), mutated;
  ``--log-count`` inputs for info and recover, ``--replay-count`` for replay (each replay stitches,
  detects and estimates: seconds; run as a child process, since the estimator keeps a pool of threads).
  Both report each log on stdout: ``log info`` exits 1 on a log it reads as incomplete, ``replay`` on one
  it cannot estimate from, with nothing on stderr; that counts as a project error.

The fast kinds (``--kinds fast``, or by name), about a millisecond per input, for counts of 100,000:

- ``sidecars``: the JSON sidecars through ``load_panorama``, ``read_orientation_file`` and ``shot_pose``.
- ``dem-headers``: ``load_dem`` on 16 x 32 maps whose header is most of the file (GeoTIFF, PDS label and
  image, .npz, .e00).
- ``image-headers``: ``read_image`` (the header's pixel count checked, then OpenCV) on small PNGs and JPEGs.
- ``mcap-records``: small logs (zstd, lz4, uncompressed), mutated or with one length forged, through
  ``viper log info``'s reader and every message's decoder; an incomplete log is its project error.
``--subprocess-every N`` runs every Nth DEM header and MCAP input again as ``viper dem info`` or ``viper log
info`` in a child process.  A project error whose message has more than one line counts as foreign.

The commands (``viper dem info``, ``viper skyline``, ``viper log``, ``viper replay``) are judged by
what a user sees on stderr, the compiled libraries' own lines included: a project error is a non-zero
exit with exactly one line; an exception out of ``main``, more lines, or an exit of 0 with more than
one line or without its output, is foreign.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import copy
import datetime
import functools
import hashlib
import io
import json
import logging
import os
import random
import resource
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from appliance.config import load_config
from appliance.errors import ViperError
from appliance.locating.tile_cache import SearchParams
from appliance.locating.tiled_index import open_surface, open_tiled
from appliance.locating.tiled_search import locate_tiled
from appliance.native import native_messages
from appliance.skyline import Skyline, format_skyline_csv, parse_skyline_csv
from appliance.terrain.database import build_database, load_database
from appliance.terrain.dem import load_dem

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "bench" / "results" / "input_fuzz.md"
sys.path.insert(0, str(ROOT))
from bench.results_file import append_result  # noqa: E402
from tests.tiled_build import build_tiled  # noqa: E402

HOSTILE = [b"nan", b"-inf", b"1e999", b"99999999999999999999", b"-", b"", b"\x00", b"\"", b"[", b"]]", b"=",
           b"\xef\xbb\xbf", b"\r\n", b",", b"-0", b"0", b"true", b"{}", b"\xff\xfe"]
DEMS = ["dem_geotiff/gmted2010_clips/matterhorn.tiff", "dem_geotiff/msh00_MountStHelens_2000_webmerc.tif",
        "dem_srtm_hgt/N44W072.hgt", "dem_usgs_ascii/SainteHelens.dem", "dem_planetary/LDEM_4.IMG",
        "dem_other/jacksboro_fault_dem.npz", "dem_other/topobathy.npz", "dem_other/msh00_83_MountStHelens_2000.e00"]
FULL_CONFIG = b"""[estimator]
sigma_deg = [0.3, 0.8]
heading_tolerance_deg = 4.0
min_valid_fraction = 0.2
[platform]
kind = "sim"
[logbook]
fsync_interval_s = 2.0
compression = "zstd"
[session]
interval_s = 3600.0
body_mask_deg = [[170.0, 190.0]]
[devices.gps]
source = "/dev/ttyUSB0"
baudrate = 9600
[devices.compass]
kind = "nmea"
soft_iron_matrix = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
[sim]
time_rate = 10.0
gps_rate_hz = 1.0
[sim.faults]
gps_garbage_rate = 0.1
camera_black_frames = [2, 5]
"""


def mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 3)):
        kind = rng.choice(("cut", "flip", "flip", "random", "hostile", "insert", "delete", "dupline"))
        i = rng.randrange(len(b) + 1) if b else 0
        if kind == "cut":
            del b[i:]
        elif kind == "flip" and b:
            for _ in range(rng.randint(1, 8)):
                j = rng.randrange(len(b))
                b[j] ^= 1 << rng.randrange(8)
        elif kind == "random":
            n = rng.randint(1, 16)
            b[i : i + n] = bytes(rng.randrange(256) for _ in range(n))
        elif kind == "hostile":
            n = rng.randint(0, 6)
            b[i : i + n] = rng.choice(HOSTILE)
        elif kind == "insert":
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        elif kind == "delete":
            del b[i : i + rng.randint(1, 16)]
        elif kind == "dupline":
            lines = bytes(b).split(b"\n")
            k = rng.randrange(len(lines))
            lines.insert(k, lines[k])
            b = bytearray(b"\n".join(lines))
    return bytes(b)


class Tally:
    def __init__(self) -> None:
        self.inputs = 0
        self.loaded = 0
        self.errors: collections.Counter[str] = collections.Counter()
        self.foreign: list[str] = []

    def run(self, call: Callable[[], object]) -> None:
        self.inputs += 1
        try:
            call()
        except ViperError as exc:
            if "\n" in str(exc).strip():  # the commands print it as their one line of error
                self.foreign.append(f"{type(exc).__name__} of {len(str(exc).splitlines())} lines: "
                                    f"{str(exc).splitlines()[0]}")
            else:
                self.errors[type(exc).__name__] += 1
        except Exception as exc:  # noqa: BLE001 - the foreign exceptions are what this benchmark counts
            self.foreign.append(f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
        else:
            self.loaded += 1


def skyline_seeds() -> list[bytes]:
    az = np.arange(0.0, 360.0, 1.0)
    el = 2.0 + np.sin(np.radians(3 * az))
    el[40:60] = np.nan
    plain = format_skyline_csv(Skyline(az, el)).encode()
    conf = format_skyline_csv(Skyline(az, el, np.clip(0.5 + 0.4 * np.cos(np.radians(az)), 0, 1))).encode()
    return [plain, conf, b"\xef\xbb\xbf" + plain.replace(b"\n", b"\r\n")]


def fuzz_skyline(count: int, rng: random.Random) -> Tally:
    t = Tally()
    seeds = skyline_seeds()
    for _ in range(count):
        data = mutate(rng.choice(seeds), rng)
        t.run(functools.partial(parse_skyline_csv, data.decode("utf-8", "replace"), "fuzz.csv"))
    return t


def fuzz_config(count: int, rng: random.Random, work: Path) -> Tally:
    t = Tally()
    seeds = [(ROOT / "examples" / n).read_bytes() for n in ("tripod.toml", "sim-forest.toml")] + [FULL_CONFIG]
    path = work / "fuzz.toml"
    for _ in range(count):
        path.write_bytes(mutate(rng.choice(seeds), rng))
        t.run(functools.partial(load_config, path))
    return t


def fuzz_dems(count: int, rng: random.Random, work: Path) -> dict[str, Tally]:
    out = {}
    for rel in DEMS:
        src = DATA / rel
        if not src.exists():
            continue
        t = Tally()
        data = src.read_bytes()
        folder = work / "dem"
        for _ in range(count):
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            target = folder / src.name
            if src.suffix.upper() == ".IMG":
                label = src.with_suffix(".LBL")
                (folder / label.name).write_bytes(label.read_bytes())
            target.write_bytes(mutate(data, rng) if rng.random() < 0.5 else data[: rng.randrange(len(data))])
            t.run(functools.partial(_command, ["dem", "info", str(target)]))
        out[rel] = t
    return out


def fuzz_database(count: int, rng: random.Random, work: Path) -> Tally:
    db = work / "seed.viperdb"
    build_database(load_dem("jacksboro"), db, (-84.30, 36.55, -84.28, 36.56), None, 1.5, 36, progress=None)
    data = db.read_bytes()
    path = work / "fuzz.viperdb"
    t = Tally()
    for _ in range(count):
        path.write_bytes(mutate(data, rng))
        t.run(functools.partial(load_database, path))
    return t


JSON_HOSTILE: list[object] = [None, -1, 0, -0.5, 1e308, float("nan"), float("inf"), 2**70, True, "x", "", [], {},
                               [1, 2], "../index.json", "/etc/passwd", "EPSG:4326", "moon"]


def _leaves(node: object, path: tuple = ()) -> list[tuple]:
    """Every path (keys and indices) inside a parsed JSON document, containers included."""
    out = [path]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _leaves(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _leaves(v, path + (i,))
    return out


def mutate_json(doc: dict, rng: random.Random) -> bytes:
    """``doc`` with one to three values replaced by hostile ones or their keys deleted."""
    doc = json.loads(json.dumps(doc))
    for _ in range(rng.randint(1, 3)):
        paths = [p for p in _leaves(doc) if p]
        path = rng.choice(paths)
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        if isinstance(parent, dict) and rng.random() < 0.25:
            del parent[path[-1]]
        else:
            parent[path[-1]] = copy.deepcopy(rng.choice(JSON_HOSTILE))
    return json.dumps(doc).encode()


def _open_and_search(folder: Path, sky: Skyline, params: SearchParams, search: bool) -> None:
    index = open_tiled(folder)
    open_surface(index)
    if search:
        locate_tiled(index, sky, params)


def fuzz_tiled_index(count: int, rng: random.Random, work: Path) -> dict[str, Tally]:
    dem = load_dem("jacksboro")
    small = build_tiled(dem, work / "tiled-seed", (-84.30, 36.55, -84.28, 36.56), (2, 2), 3_000.0, n_azimuths=36)
    index = json.loads((small / "index.json").read_text())
    map_path = DATA / "dem_other" / "jacksboro_fault_dem.npz"
    if map_path.exists():
        index["surface"] = {"path": str(map_path), "crs": None,
                            "sha256": hashlib.sha256(map_path.read_bytes()).hexdigest()}
    seeds = {"tiled index (jacksboro 2 x 2)": (small, index, True)}
    moon = ROOT / "bench" / "cache" / "moon_whole_body_3790m_150km"
    if (moon / "index.json").is_file():
        seeds["tiled index (Moon whole body)"] = (moon, json.loads((moon / "index.json").read_text()), False)
    az = np.arange(0.0, 360.0, 10.0)
    sky = Skyline(az, 1.0 + np.sin(np.radians(2.0 * az)))
    params = SearchParams((0.3, 1.2), 4.0)
    out = {}
    for name, (source, doc, search) in seeds.items():
        folder = work / "tiled-fuzz"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        for tile in source.iterdir():
            if tile.name != "index.json":
                (folder / tile.name).symlink_to(tile.resolve())
        raw = json.dumps(doc).encode()
        t = Tally()

        for _ in range(count):
            data = mutate(raw, rng) if rng.random() < 0.5 else mutate_json(doc, rng)
            (folder / "index.json").write_bytes(data)
            t.run(functools.partial(_open_and_search, folder, sky, params, search))
        out[name] = t
    return out


def _image_seeds(work: Path) -> dict[str, dict[str, bytes]]:
    """Each seed's files by name: the image first, then the files beside it."""
    import cv2

    from appliance.vision.intrinsics import CameraIntrinsics, save_intrinsics
    from appliance.vision.panorama import save_panorama
    from appliance.vision.synth import analytic_skyline_fn, render_panorama

    seeds: dict[str, dict[str, bytes]] = {}
    pano = render_panorama(analytic_skyline_fn(3), np.random.default_rng(3), px_per_rad=120.0, height_px=120).panorama
    for suffix in (".png", ".jpg"):
        folder = work / f"seed{suffix}"
        folder.mkdir()
        side = save_panorama(pano, folder / f"pano{suffix}")
        seeds[f"panorama{suffix}"] = {f"pano{suffix}": (folder / f"pano{suffix}").read_bytes(),
                                      side.name: side.read_bytes()}
    folder = work / "seed-photo"
    folder.mkdir()
    img = np.empty((135, 240, 3), np.uint8)
    img[:] = (205, 200, 198)
    rows = np.arange(135)[:, None] > 70 + 8 * np.sin(np.arange(240) / 20.0)[None, :]
    img[rows] = (60, 110, 80)
    ok, buf = cv2.imencode(".png", img)
    save_intrinsics(CameraIntrinsics(240, 135, 180.0, 180.0, 120.0, 67.5), folder / "camera.toml")
    seeds["photo.png"] = {"photo.png": buf.tobytes(),
                          "photo.png.json": json.dumps({"yaw_deg": 30.0, "pitch_deg": 0.0, "roll_deg": 0.0,
                                                        "camera": "camera.toml"}).encode(),
                          "camera.toml": (folder / "camera.toml").read_bytes()}
    return seeds


def fuzz_images(count: int, rng: random.Random, work: Path) -> dict[str, Tally]:
    out = {}
    for name, files in _image_seeds(work).items():
        t = Tally()
        folder = work / "image-fuzz"
        image = next(iter(files))
        for _ in range(count):
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            victim = rng.choice(list(files))
            for fname, data in files.items():
                if fname == victim:
                    if fname.endswith(".json") and rng.random() < 0.5:
                        data = mutate_json(json.loads(data), rng)
                    else:
                        data = mutate(data, rng)
                (folder / fname).write_bytes(data)
            t.run(functools.partial(_command, ["skyline", str(folder / image), "--out", str(folder / "sky.csv")],
                                    folder / "sky.csv"))
        out[f"viper skyline, {name}"] = t
    return out


def _alone() -> None:
    """A command is judged by all it prints only while this process has one thread (see
    ``appliance.native``)."""
    if threading.active_count() > 1:
        raise SystemExit(f"input_fuzz: {threading.active_count()} threads alive; stderr cannot be judged")


class _ForeignExitError(Exception):
    pass


def _command(args: list[str], expect: Path | None = None) -> None:
    """Run ``viper ARGS`` in process as a user would; what the process prints on stderr (Python's
    and compiled libraries') is its terminal.  A non-zero exit with one line there is a project
    error; more lines, an escaping exception, or an exit of 0 with more than one line (a warning) or
    without ``expect`` written, is foreign."""
    from appliance.cli.main import main as viper_main

    _alone()
    err = io.StringIO()
    with native_messages() as native, contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = viper_main(args)
    lines = native + err.getvalue().strip().splitlines()
    if code == 0:
        if expect is not None and not expect.is_file():
            raise _ForeignExitError(f"exit 0 without {expect.name}")
        if len(lines) > 1:
            raise _ForeignExitError(f"exit 0 with {len(lines)} lines on stderr: {lines[:2]}")
        return
    if len(lines) != 1:
        raise _ForeignExitError(f"exit {code} with {len(lines)} lines on stderr: {lines[:2]}")
    raise ViperError(lines[0])


def _demo_seed() -> tuple[Path, Path]:
    """The demo's session log and database (``viper demo --seed 11``), made once into bench/cache/."""
    import subprocess

    folder = ROOT / "bench" / "cache" / "fuzz-demo-seed-11"
    logs = sorted(folder.glob("viper-*.mcap"))
    if not logs or not (folder / "jacksboro.viperdb").is_file():
        subprocess.run([sys.executable, "-m", "appliance.cli.main", "demo", "--seed", "11", "--out", str(folder)],
                       check=True, capture_output=True)
        logs = sorted(folder.glob("viper-*.mcap"))
    return logs[0], folder / "jacksboro.viperdb"


def _batch(args: list[str], verdict: str) -> None:
    """``viper log info`` and ``viper replay``, which report each log on stdout: an exit of 1 with
    nothing on stderr and ``verdict`` on stdout is their own finding about a damaged log."""
    from appliance.cli.main import main as viper_main

    _alone()
    err = io.StringIO()
    out = io.StringIO()
    with native_messages() as native, contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = viper_main(args)
    lines = native + err.getvalue().strip().splitlines()
    if code == 1 and not lines and verdict in out.getvalue():
        raise ViperError(verdict)
    if code == 0 and not lines:
        return
    if code != 0 and len(lines) == 1:
        raise ViperError(lines[0])
    raise _ForeignExitError(f"exit {code} with {len(lines)} lines on stderr: {lines[:2]}")


def fuzz_logs(count: int, replay_count: int, rng: random.Random, work: Path) -> dict[str, Tally]:
    seed, db = _demo_seed()
    data = seed.read_bytes()
    log = work / "fuzz.mcap"
    fixed = work / "fixed.mcap"
    info, recover, replay = Tally(), Tally(), Tally()
    for k in range(count):
        log.write_bytes(mutate(data, rng) if rng.random() < 0.7 else data[: rng.randrange(len(data))])
        info.run(functools.partial(_batch, ["log", "info", str(log)], "INCOMPLETE"))
        recover.run(functools.partial(_command, ["log", "recover", str(log), "--out", str(fixed), "--force"],
                                      fixed))
        if k < replay_count:  # in a child process: the estimator keeps a pool of threads once it has run
            out = work / "replay"
            shutil.rmtree(out, ignore_errors=True)
            replay.run(functools.partial(_in_child, ["replay", str(log), "--db", str(db), "--out", str(out)],
                                         ": no estimate: "))
    return {"viper log info": info, "viper log recover": recover, "viper replay": replay}


# --- the fast kinds: each reader called in process on small seeds, about a millisecond per input -------

SUBPROCESS_EVERY = 0  # set by --subprocess-every


def _in_child(args: list[str], verdict: str = "") -> None:
    """``viper ARGS`` in a child process, judged by what a user sees: exit 0 and nothing on stderr; a
    non-zero exit with one stderr line (a project error); or, where ``verdict`` is given, exit 1 with
    nothing on stderr and ``verdict`` on stdout (log info's report of a damaged log)."""
    import subprocess

    r = subprocess.run([sys.executable, "-m", "appliance.cli.main", *args], capture_output=True, text=True,
                       timeout=120, check=False, env=dict(os.environ, PYTHONPATH=str(ROOT), VIPER_SOCKET=""))
    lines = r.stderr.strip().splitlines()
    if r.returncode == 0 and not lines:
        return
    if r.returncode == 1 and not lines and verdict and verdict in r.stdout:
        raise ViperError(verdict)
    if r.returncode not in (0, -9) and len(lines) == 1 and "Traceback" not in r.stderr:
        raise ViperError(lines[0])
    raise _ForeignExitError(f"child exit {r.returncode} with {len(lines)} lines on stderr: {lines[-2:]}")


def _sample(tally: Tally, k: int, args: list[str], verdict: str = "") -> None:
    """Every SUBPROCESS_EVERY-th input again in a child process, counted in ``tally``."""
    if SUBPROCESS_EVERY and k % SUBPROCESS_EVERY == 0:
        tally.run(functools.partial(_in_child, args, verdict))


def fuzz_sidecars(count: int, rng: random.Random, work: Path) -> Tally:
    """The JSON sidecars: a panorama's geometry (``load_panorama``), a photo's orientation
    (``read_orientation_file``) and a stitched shot's pose (``shot_pose``), mutated byte-wise or
    structurally."""
    import cv2

    from appliance.cli.stitch import shot_pose
    from appliance.vision.panorama import load_panorama
    from appliance.vision.photo import read_orientation_file

    folder = work / "sidecars"
    folder.mkdir()
    ok, buf = cv2.imencode(".png", np.full((8, 36, 3), 128, np.uint8))
    (folder / "pano.png").write_bytes(buf.tobytes())
    (folder / "shot.png").write_bytes(buf.tobytes())
    seeds: list[tuple[Path, dict, Callable[[], object]]] = [
        (folder / "pano.png.json", {"projection": "cylindrical", "px_per_rad": 5.73, "azimuth0_deg": 10.0,
                                    "horizon_row": 4.0, "full_circle": True, "width": 36, "height": 8},
         functools.partial(load_panorama, folder / "pano.png")),
        (folder / "o.json", {"yaw_deg": 30.0, "pitch_deg": -1.5, "roll_deg": 0.5, "camera": "camera.toml"},
         functools.partial(read_orientation_file, folder / "o.json")),
        (folder / "shot.png.json", {"stage_angle_deg": 45.0, "pitch_deg": 0.5, "roll_deg": -0.2},
         functools.partial(shot_pose, folder / "shot.png", None)),
    ]
    t = Tally()
    for _ in range(count):
        side, doc, call = rng.choice(seeds)
        side.write_bytes(mutate(json.dumps(doc).encode(), rng) if rng.random() < 0.5 else mutate_json(doc, rng))
        t.run(call)
    return t


PDS_LABEL = """PDS_VERSION_ID = PDS3
RECORD_TYPE = FIXED_LENGTH
FILE_RECORDS = 16
RECORD_BYTES = 64
^IMAGE = "SMALL.IMG"
OBJECT = IMAGE
  LINES = 16
  LINE_SAMPLES = 32
  SAMPLE_TYPE = LSB_INTEGER
  SAMPLE_BITS = 16
  UNIT = METER
  SCALING_FACTOR = 0.5
  OFFSET = 1737400.
END_OBJECT = IMAGE
OBJECT = IMAGE_MAP_PROJECTION
  ^DATA_SET_MAP_PROJECTION = "DSMAP.CAT"
  MAP_PROJECTION_TYPE = "SIMPLE CYLINDRICAL"
  A_AXIS_RADIUS = 1737.4 <KM>
  B_AXIS_RADIUS = 1737.4 <KM>
  C_AXIS_RADIUS = 1737.4 <KM>
  FIRST_STANDARD_PARALLEL = 'N/A'
  SECOND_STANDARD_PARALLEL = 'N/A'
  POSITIVE_LONGITUDE_DIRECTION = "EAST"
  CENTER_LATITUDE = 0 <DEG>
  CENTER_LONGITUDE = 180 <DEG>
  LINE_FIRST_PIXEL = 1
  LINE_LAST_PIXEL = 16
  SAMPLE_FIRST_PIXEL = 1
  SAMPLE_LAST_PIXEL = 32
  MAP_PROJECTION_ROTATION = 0.0 <DEG>
  MAP_RESOLUTION = 4 <PIX/DEG>
  MAP_SCALE = 7.5806 <KM/PIXEL>
  MAXIMUM_LATITUDE = 2 <DEG>
  MINIMUM_LATITUDE = -2 <DEG>
  LINE_PROJECTION_OFFSET = 7.5 <PIXEL>
  SAMPLE_PROJECTION_OFFSET = -704.5 <PIXEL>
  EASTERNMOST_LONGITUDE = 184 <DEG>
  WESTERNMOST_LONGITUDE = 176 <DEG>
END_OBJECT = IMAGE_MAP_PROJECTION
END
"""


def _small_dems(folder: Path) -> dict[str, dict[str, bytes]]:
    """A small map (16 x 32 cells) in each format with a header: GeoTIFF, PDS (label and image), .npz, .e00.
    Each seed's files by name, the one given to the reader first."""
    import io as _io

    import rasterio
    from rasterio.transform import from_origin

    rows, cols = 16, 32
    elev = (100.0 + 10.0 * np.add.outer(np.sin(np.arange(rows) / 3.0), np.cos(np.arange(cols) / 5.0)))
    seeds: dict[str, dict[str, bytes]] = {}
    tif = folder / "small.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=cols, height=rows, count=1, dtype="float32",
                       crs="EPSG:4326", transform=from_origin(7.0, 46.0, 0.001, 0.001), nodata=-9999.0) as ds:
        ds.write(elev.astype(np.float32), 1)
    seeds["GeoTIFF"] = {"small.tif": tif.read_bytes()}
    seeds["PDS"] = {"SMALL.LBL": PDS_LABEL.encode(), "SMALL.IMG": (elev * 2).astype("<i2").tobytes()}
    one = _io.BytesIO()
    np.savez(one, elevation=elev, dx=np.float64(0.001), dy=np.float64(0.001), xmin=np.float64(7.0),
             xmax=np.float64(7.0 + 0.001 * cols), ymin=np.float64(46.0), ymax=np.float64(46.0 + 0.001 * rows))
    seeds["npz"] = {"small.npz": one.getvalue()}
    cells = "\n".join("".join(f" {v:.7E}" for v in row[k:k + 5]) for row in elev for k in range(0, cols, 5))
    seeds["e00"] = {"small.e00": (
        "EXP  0 /small.e00\nGRD  2\n"
        f"{cols:10d}{rows:10d}         2-0.21474836470000000E+10\n"
        " 0.10000000000000000E-02 0.10000000000000000E-02\n"
        " 0.70000000000000000E+01 0.46000000000000000E+02\n"
        f" {7.0 + 0.001 * cols:.17E} {46.0 + 0.001 * rows:.17E}\n" + cells
        + "\nEOG\nPRJ  2\nProjection    GEOGRAPHIC\n~\nDatum         WGS84\n~\nEOP\nEOS\n").encode()}
    return seeds


def fuzz_dem_headers(count: int, rng: random.Random, work: Path) -> dict[str, Tally]:
    """``load_dem`` on small maps whose header is most of the file (a PDS input mutates its label or its
    image); ``count`` inputs over the formats."""
    folder = work / "dem-headers"
    folder.mkdir()
    seeds = _small_dems(folder)
    out = {name: Tally() for name in seeds}
    child = Tally()
    for files in seeds.values():  # every seed loads as it is
        for fname, data in files.items():
            (folder / fname).write_bytes(data)
        load_dem(folder / next(iter(files)))
    for k in range(count):
        name = rng.choice(list(seeds))
        files = seeds[name]
        victim = rng.choice(list(files)) if name != "PDS" or rng.random() < 0.5 else "SMALL.LBL"
        for fname, data in files.items():
            data = (mutate(data, rng) if rng.random() < 0.7 else data[: rng.randrange(len(data) + 1)]) \
                if fname == victim else data
            (folder / fname).write_bytes(data)
        out[name].run(functools.partial(load_dem, folder / next(iter(files))))
        _sample(child, k, ["dem", "info", str(folder / next(iter(files)))])
    tallies = {f"DEM header, small {k}": v for k, v in out.items()}
    if child.inputs:
        tallies["DEM header, sample in a child process (viper dem info)"] = child
    return tallies


def fuzz_image_headers(count: int, rng: random.Random, work: Path) -> Tally:
    """``read_image`` (the pixel count checked in the header, then decoded) on small PNGs and JPEGs."""
    import cv2

    from appliance.vision.panorama import read_image

    img = np.zeros((24, 48, 3), np.uint8)
    img[12:] = (60, 110, 80)
    img[:12] = (205, 200, 198)
    seeds = {suffix: cv2.imencode(suffix, img)[1].tobytes() for suffix in (".png", ".jpg")}
    t = Tally()
    for _ in range(count):
        suffix = rng.choice(list(seeds))
        path = work / f"header{suffix}"
        path.write_bytes(mutate(seeds[suffix], rng))
        t.run(functools.partial(_quiet, read_image, path))
    return t


def _quiet(call: Callable[..., object], *args: object) -> object:
    """``call`` with the libraries' messages gathered (as the commands do): a warning is not a failure."""
    with native_messages():
        return call(*args)


def _small_log(path: Path, compression: str) -> None:
    """A small session log: metadata, protobuf fixes, JSON records (an estimate among them), an image."""
    from appliance.config import Compression
    from appliance.logbook import Logbook
    from appliance.logbook import messages as m
    from appliance.logbook import topics as tp

    t0 = 1_780_000_000_000_000_000
    with Logbook.create(path, reserve_bytes=0, compression=Compression(compression)) as lb:
        lb.write_metadata("viper.software", {"name": "viper", "version": "fuzz"})
        for i in range(6):
            lb.write_proto(tp.GPS_FIX, m.location_fix(t0 + i, 36.55 + i * 1e-6, -84.29), t0 + i)
            lb.write_json(tp.TILT_RAW, "viper.TiltRaw", {"roll_deg": 0.1 * i}, t0 + i)
            if i % 2:
                lb.write_proto(tp.IMAGE, m.compressed_image(t0 + i, bytes(range(64))), t0 + i)
                lb.flush()
        lb.write_json(tp.ESTIMATE_RECORD, "viper.Estimate",
                      {"lat": 36.55, "lon": -84.29, "ambiguous": False, "error_m": 12.0}, t0 + 9)


def _read_log(path: Path) -> None:
    """What ``viper log info`` does (the summary and its lines), then every message decoded."""
    from appliance.errors import LogError
    from appliance.logbook.reader import LogReader
    from appliance.logbook.summary import summarize_log

    summary = summarize_log(path)
    summary.lines()
    for msg in LogReader(path).messages():
        msg.decode()
    if not summary.complete:  # log info reports it and exits 1
        raise LogError(f"{path}: INCOMPLETE: {summary.problem}")


def _forge_length(data: bytes, rng: random.Random) -> bytes:
    """``data`` with the length of one of its records (or of a field inside one) set to a hostile value."""
    b = bytearray(data)
    i = rng.randrange(8, max(9, len(b) - 8))
    b[i:i + 8] = rng.choice((2**62, 2**63 - 1, 2**64 - 1, 2**32, 2**31, len(b), len(b) + 1, 0)).to_bytes(8, "little")
    if rng.random() < 0.5:  # a uint32 field's worth
        b[i + 4:i + 8] = data[i + 4:i + 8]
    return bytes(b)


def fuzz_mcap_records(count: int, rng: random.Random, work: Path) -> tuple[Tally, Tally]:
    """Small logs (zstd, lz4, uncompressed) with mutated bytes or a forged length, through the reader of
    ``viper log info`` and every message's decoder."""
    seeds = []
    for compression in ("zstd", "lz4", "none"):
        _small_log(work / f"seed-{compression}.mcap", compression)
        seeds.append((work / f"seed-{compression}.mcap").read_bytes())
    path = work / "records.mcap"
    t, child = Tally(), Tally()
    for k in range(count):
        data = rng.choice(seeds)
        path.write_bytes(_forge_length(data, rng) if rng.random() < 0.3 else mutate(data, rng))
        t.run(functools.partial(_read_log, path))
        _sample(child, k, ["log", "info", str(path)], "INCOMPLETE")
    return t, child


def _mcap_tallies(in_process: Tally, child: Tally) -> dict[str, Tally]:
    out = {"MCAP records (log info's reader, every message decoded)": in_process}
    if child.inputs:
        out["MCAP records, sample in a child process (viper log info)"] = child
    return out


OLD_KINDS = ("csv", "config", "dem", "database", "images", "logs", "tiled")
FAST_KINDS = ("csv", "config", "sidecars", "dem-headers", "image-headers", "mcap-records")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=20_000,
                    help="inputs per reader (CSV, config, database, and each of the fast kinds)")
    ap.add_argument("--dem-count", type=int, default=12, help="inputs per DEM file")
    ap.add_argument("--index-count", type=int, default=2_000, help="inputs per tiled database index")
    ap.add_argument("--image-count", type=int, default=1_000, help="inputs per image seed of viper skyline")
    ap.add_argument("--log-count", type=int, default=1_000, help="mutated session logs for log info and recover")
    ap.add_argument("--replay-count", type=int, default=40, help="of those, how many go through viper replay")
    ap.add_argument("--kinds", default=",".join(OLD_KINDS),
                    help=f"comma-separated, of {', '.join(dict.fromkeys(OLD_KINDS + FAST_KINDS))}; 'fast' for "
                         f"{','.join(FAST_KINDS)}")
    ap.add_argument("--subprocess-every", type=int, default=0,
                    help="also run every Nth DEM header and MCAP input as a viper command in a child process")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-record", action="store_true", help="do not append to the results file")
    args = ap.parse_args()
    kinds = FAST_KINDS if args.kinds == "fast" else tuple(args.kinds.split(","))
    unknown = set(kinds) - set(OLD_KINDS + FAST_KINDS)
    if unknown:
        ap.error(f"unknown kinds: {', '.join(sorted(unknown))}")
    global SUBPROCESS_EVERY
    SUBPROCESS_EVERY = args.subprocess_every
    logging.disable(logging.CRITICAL)
    rng = random.Random(args.seed)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    tallies: dict[str, Tally] = {}
    with tempfile.TemporaryDirectory(prefix="viper-input-fuzz-") as tmp:
        work = Path(tmp)
        steps: dict[str, Callable[[], dict[str, Tally]]] = {
            "csv": lambda: {"skyline CSV": fuzz_skyline(args.count, rng)},
            "config": lambda: {"config": fuzz_config(args.count, rng, work)},
            "sidecars": lambda: {"JSON sidecars (panorama, orientation, pose)": fuzz_sidecars(args.count, rng,
                                                                                               work)},
            "dem-headers": lambda: fuzz_dem_headers(args.count, rng, work),
            "image-headers": lambda: {"image headers (read_image, PNG and JPEG)": fuzz_image_headers(args.count,
                                                                                                      rng, work)},
            "mcap-records": lambda: _mcap_tallies(*fuzz_mcap_records(args.count, rng, work)),
            "dem": lambda: {f"DEM {Path(k).name}": v for k, v in fuzz_dems(args.dem_count, rng, work).items()},
            "database": lambda: {"database": fuzz_database(args.count, rng, work)},
            "images": lambda: fuzz_images(args.image_count, rng, work),
            "logs": lambda: fuzz_logs(args.log_count, args.replay_count, rng, work),
            # last: a tiled search leaves its pool's threads, and with other threads alive the readers
            # leave the libraries' stderr alone, so the commands above could not be judged after it
            "tiled": lambda: fuzz_tiled_index(args.index_count, rng, work),
        }
        for kind in sorted(kinds, key=list(steps).index):
            c0 = time.process_time()
            got = steps[kind]()
            cpu = time.process_time() - c0
            n = sum(t.inputs for t in got.values())
            print(f"[{kind}: {n} inputs, {cpu:.0f} CPU s, {1e3 * cpu / max(n, 1):.2f} CPU ms per input]", flush=True)
            tallies.update(got)
    cpu_s = time.process_time() - cpu0
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    elapsed = time.perf_counter() - t0
    foreign = sum(len(t.foreign) for t in tallies.values())
    result = "pass" if not foreign else f"FAIL: {foreign} foreign exceptions"
    rows = []
    for name, t in tallies.items():
        said = ", ".join(f"{k} {v}" for k, v in t.errors.most_common()) or "none"
        print(f"{name}: {t.inputs} inputs, {t.loaded} loaded, project errors: {said}; foreign: {len(t.foreign)}")
        for line in sorted(set(t.foreign))[:10]:
            print("  " + line)
        rows.append(f"| {datetime.date.today().isoformat()} | {args.seed} | {name} | {t.inputs} | {t.loaded} | "
                     f"{sum(t.errors.values())} | {len(t.foreign)} |")
    print(f"{sum(t.inputs for t in tallies.values())} inputs in {elapsed:.0f} s ({cpu_s:.0f} CPU s, peak RSS "
          f"{peak_mib:.0f} MiB) -> {result}")
    if not args.no_record:
        append_result(OUT,
                      "# Input-file fuzzing\n\n`bench/input_fuzz.py`: truncated, bit-flipped and otherwise "
                      "mutated skyline CSVs, configurations, DEMs of every format in ../shared/data and skyline "
                      "databases through their readers.\nTarget: every input loads or raises the project's own "
                      "error (ViperError); no foreign exception.\n\n"
                      "| date | seed | reader | inputs | loaded | project errors | foreign exceptions |\n"
                      "|---|---|---|---|---|---|---|\n",
                      "\n".join(rows) + "\n"
                      + f"\nRun of {datetime.date.today().isoformat()} (--kinds {','.join(kinds)} --count "
                      f"{args.count} --dem-count {args.dem_count} --index-count {args.index_count} "
                      f"--image-count {args.image_count} --log-count {args.log_count} "
                      f"--replay-count {args.replay_count} --subprocess-every {args.subprocess_every} "
                      f"--seed {args.seed}): {result}; "
                      f"{elapsed:.0f} s, {cpu_s:.0f} CPU s, peak RSS {peak_mib:.0f} MiB, load average "
                      f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs.\n\n")
    return 0 if not foreign else 1


if __name__ == "__main__":
    sys.exit(main())
