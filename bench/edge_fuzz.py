"""Fuzzing the readers at the edge: every input either reads or raises the project's own error.

Run: .venv/bin/python bench/edge_fuzz.py [--count 100000] [--kinds csv,config,...] [--seed 1]
     (writes bench/results/edge_fuzz.md)

Kinds, each mutated from valid seeds and read in process by the reader the CLI uses:

- ``csv``: skyline CSVs (``read_skyline_csv``), with and without the confidence column, with a BOM
  and CRLF.
- ``config``: configuration TOML (``load_config``): examples/tripod.toml, examples/sim-forest.toml.
- ``pano-sidecar``: a small PNG panorama's geometry sidecar (``load_panorama``).
- ``photo-sidecar``: a photo's orientation sidecar and its camera TOML (``load_photo``).
- ``dem-asc``, ``dem-usgs``: small ESRI ASCII and USGS ASCII DEMs (``load_dem``), headers included.
- ``dem-hgt``: SRTM ``.hgt`` files (``load_dem``) of the sizes a tile may have (3", 1", and a few
  bytes either side), with their contents mutated.
- ``png``, ``jpeg``: small images (``read_image``), their header fields (IHDR, SOF) set to hostile
  sizes with valid checksums as well as raw byte mutations.
- ``mcap``: small session logs written by the appliance's Logbook, uncompressed and zstd
  (``summarize_log`` of ``viper log info``, ``read_session`` of ``viper replay`` and ``recover_log``
  of ``viper log recover``, all three on each input), records' lengths and opcodes mutated too.

Mutations: bit flips, truncation, random bytes, hostile tokens, huge numbers written over numbers,
deep nesting ([[[..., {"a":{"a":..., a.a.a...= in TOML), a slice repeated up to a few MB; binary
fields (4- and 8-byte lengths, image sizes) set to 0, 2^31-1, 2^32-1, 2^63.  Input i of a kind is a
function of (seed, kind, i), so ``--show KIND I`` writes it again.

Each kind runs in a worker subprocess under RLIMIT_AS (--limit-gb, default 4 GB) so that a
blow-up fails there rather than on the machine.  After each input the worker reads its peak RSS
(``resource.getrusage``); a run past 2 GB is counted and the worker restarted (peak RSS only
grows), as is an input that kills the worker (a signal, an abort).  Per input, anything but a
``ViperError`` escaping the reader is a foreign exception, counted by type with one example.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import random
import resource
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "edge_fuzz.md"
sys.path.insert(0, str(ROOT))

KINDS = ("csv", "config", "pano-sidecar", "photo-sidecar", "dem-asc", "dem-usgs", "dem-hgt", "png", "jpeg", "mcap")
OVER_BYTES = 2 << 30  # a run over 2 GB of RSS counts against the target
OVER_EXIT = 3  # the worker's exit code after a run over 2 GB (so that its peak starts afresh)

HOSTILE = [b"nan", b"-inf", b"1e999", b"99999999999999999999", b"-", b"", b"\x00", b"\"", b"[", b"]]", b"=",
           b"\xef\xbb\xbf", b"\r\n", b",", b"-0", b"0", b"true", b"{}", b"\xff\xfe", b"\x1b[31m", b"\n\n\n"]
HUGE = [b"1e308", b"-1e308", b"1e-320", b"9" * 400, b"2147483648", b"-2147483649", b"4294967296",
        b"18446744073709551616", b"100000000", b"1000000", b"65536", b"0", b"-1", b"nan", b"inf"]
FIELDS = [0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000, 1 << 40, (1 << 63) - 1, (1 << 64) - 1, 65535, 30000]


# ----------------------------------------------------------------------------- mutations


def _numbers(b: bytes) -> list[tuple[int, int]]:
    """(start, end) of the runs of digits in ``b``."""
    out, i = [], 0
    while i < len(b):
        if 48 <= b[i] <= 57:
            j = i
            while j < len(b) and (48 <= b[j] <= 57 or b[j] in b".eE+-"):
                j += 1
            out.append((i, j))
            i = j
        else:
            i += 1
    return out


def _nest(rng: random.Random, text_kind: str) -> bytes:
    n = rng.choice((10, 100, 1000, 10_000, 100_000))
    if text_kind == "toml":
        return rng.choice((b"x = " + b"[" * n + b"]" * n + b"\n", b"x = " + b"[" * n + b"\n",
                           b"x = " + b"{a = " * n + b"1" + b"}" * n + b"\n", b"[" + b"a." * n + b"a]\n"))
    return rng.choice((b"[" * n + b"]" * n, b"[" * n, b"{\"a\":" * n + b"1" + b"}" * n, b"{\"a\":" * n))


def mutate_bytes(data: bytes, rng: random.Random, text_kind: str = "") -> tuple[bytes, list[str]]:
    """One to three mutations of ``data``, and their names."""
    b = bytearray(data)
    ops = []
    for _ in range(rng.randint(1, 3)):
        op = rng.choice(("cut", "flip", "flip", "random", "hostile", "insert", "delete", "huge", "huge", "nest",
                         "repeat", "field"))
        i = rng.randrange(len(b) + 1) if b else 0
        if op == "cut":
            del b[i:]
        elif op == "flip" and b:
            for _ in range(rng.randint(1, 8)):
                j = rng.randrange(len(b))
                b[j] ^= 1 << rng.randrange(8)
        elif op == "random":
            n = rng.randint(1, 16)
            b[i : i + n] = bytes(rng.randrange(256) for _ in range(n))
        elif op == "hostile":
            b[i : i + rng.randint(0, 6)] = rng.choice(HOSTILE)
        elif op == "insert":
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        elif op == "delete":
            del b[i : i + rng.randint(1, 16)]
        elif op == "huge":
            spans = _numbers(bytes(b))
            if spans:
                s, e = rng.choice(spans)
                b[s:e] = rng.choice(HUGE)
        elif op == "nest":
            b[i:i] = _nest(rng, text_kind)
        elif op == "repeat" and b:
            s = rng.randrange(len(b))
            piece = bytes(b[s : s + rng.randint(1, 200)])
            times = rng.choice((2, 10, 100, 1000, 10_000, 100_000))
            b[s:s] = piece * max(2, min(times, (4 << 20) // len(piece)))
        elif op == "field" and len(b) >= 8:
            j = rng.randrange(len(b) - 7)
            fmt = rng.choice(("<I", ">I", "<Q", ">Q", ">H", "<H"))
            size = struct.calcsize(fmt)
            b[j : j + size] = struct.pack(fmt, rng.choice(FIELDS) & ((1 << (8 * size)) - 1))
        ops.append(op)
    return bytes(b), ops


def png_dims(data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    """The PNG with IHDR's width and height set to hostile values and a correct CRC."""
    w, h = rng.choice(FIELDS), rng.choice(FIELDS)
    w, h = w & 0xFFFFFFFF, h & 0xFFFFFFFF
    ihdr = bytearray(data[12:29])  # b"IHDR" + 13 bytes of fields
    ihdr[4:12] = struct.pack(">II", w, h)
    if rng.random() < 0.3:
        ihdr[12] = rng.choice((1, 2, 4, 8, 16, 3, 0, 255))  # bit depth
    crc = struct.pack(">I", zlib.crc32(bytes(ihdr)) & 0xFFFFFFFF)
    return data[:12] + bytes(ihdr) + crc + data[33:], [f"ihdr {w}x{h}"]


def jpeg_dims(data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    """The JPEG with its SOF's height and width set to hostile values."""
    b = bytearray(data)
    for i in range(2, len(b) - 9):
        if b[i] == 0xFF and b[i + 1] in (0xC0, 0xC1, 0xC2):
            h, w = rng.choice(FIELDS) & 0xFFFF, rng.choice(FIELDS) & 0xFFFF
            b[i + 5 : i + 9] = struct.pack(">HH", h, w)
            return bytes(b), [f"sof {w}x{h}"]
    return data, ["no sof"]


def mcap_records(data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    """The MCAP with one record's length or opcode changed (records: opcode u8, length u64 LE)."""
    starts, i = [], 8
    while i + 9 <= len(data):
        starts.append(i)
        (length,) = struct.unpack_from("<Q", data, i + 1)
        i += 9 + length
    b = bytearray(data)
    s = rng.choice(starts)
    if rng.random() < 0.7:
        value = rng.choice(FIELDS + [0, 1, 8, rng.randrange(1 << 16)])
        b[s + 1 : s + 9] = struct.pack("<Q", value & ((1 << 64) - 1))
        return bytes(b), [f"record@{s} length {value}"]
    b[s] = rng.randrange(256)
    return bytes(b), [f"record@{s} opcode {b[s]}"]


# ----------------------------------------------------------------------------- seeds and readers


def _skyline_seeds() -> list[bytes]:
    import numpy as np

    from appliance.skyline import Skyline, format_skyline_csv

    az = np.arange(0.0, 360.0, 1.0)
    el = 2.0 + np.sin(np.radians(3 * az))
    el[40:60] = np.nan
    plain = format_skyline_csv(Skyline(az, el)).encode()
    conf = format_skyline_csv(Skyline(az, el, np.clip(0.5 + 0.4 * np.cos(np.radians(az)), 0, 1))).encode()
    return [plain, conf, b"\xef\xbb\xbf" + plain.replace(b"\n", b"\r\n")]


def _small_image(fmt: str) -> bytes:
    import cv2
    import numpy as np

    img = np.empty((48, 96, 3), np.uint8)
    img[:] = (205, 200, 198)
    rows = np.arange(48)[:, None] > 24 + 6 * np.sin(np.arange(96) / 10.0)[None, :]
    img[rows] = (60, 110, 80)
    ok, buf = cv2.imencode(fmt, img)
    assert ok
    return bytes(buf.tobytes())


def _dem_seeds(work: Path) -> dict[str, list[dict[str, bytes]]]:
    """ESRI ASCII and USGS ASCII grids of a small hill, written by GDAL."""
    import numpy as np
    import rasterio
    from rasterio import shutil as rio_shutil
    from rasterio.transform import from_origin

    z = (300.0 + 50.0 * np.hypot(*np.meshgrid(np.linspace(-1, 1, 12), np.linspace(-1, 1, 10)))).astype("float32")
    out: dict[str, list[dict[str, bytes]]] = {"dem-asc": [], "dem-usgs": []}
    for kind, driver, name, crs, transform in (
        ("dem-asc", "AAIGrid", "seed.asc", "EPSG:4326", from_origin(-84.3, 36.6, 0.001, 0.001)),
        ("dem-usgs", "USGSDEM", "seed.dem", "EPSG:4326", from_origin(-84.3, 36.6, 1 / 1200, 1 / 1200)),
    ):
        tif = work / f"{kind}.tif"
        with rasterio.open(tif, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                           dtype="float32" if kind == "dem-asc" else "int16", crs=crs, transform=transform) as ds:
            ds.write(z if kind == "dem-asc" else z.astype("int16"), 1)
        with rasterio.open(tif) as src:
            opts: dict[str, str] = {}
            rio_shutil.copy(src, work / name, driver=driver, **opts)
        prj = (work / name).with_suffix(".prj")
        out[kind].append({f"d{Path(name).suffix}": (work / name).read_bytes(),
                          **({"d.prj": prj.read_bytes()} if prj.exists() else {})})
    return out


def _mcap_seeds(work: Path) -> list[bytes]:
    """Two small session logs written by the Logbook (uncompressed and zstd)."""
    from appliance.config import Compression
    from appliance.logbook import Logbook
    from appliance.logbook import messages as m
    from appliance.logbook import topics as t
    from appliance.vision.intrinsics import CameraIntrinsics

    t0 = 1_700_000_000_000_000_000
    jpeg = _small_image(".jpg")
    seeds = []
    for comp in (Compression.NONE, Compression.ZSTD):
        path = work / f"seed-{comp.value}.mcap"
        with Logbook.create(path, compression=comp, reserve_bytes=0, chunk_size_bytes=4096) as lb:
            lb.write_json(t.SESSION, "viper.Session", {"session_id": "fuzz"}, t0)
            lb.write_proto(t.CALIBRATION, m.camera_calibration(t0, CameraIntrinsics.from_fov(96, 48, 60.0)), t0)
            for i in range(3):
                ns = t0 + i * 1_000_000
                lb.write_proto(t.IMAGE, m.compressed_image(ns, jpeg), ns)
                lb.write_json(t.CAPTURE, "viper.Capture", {"index": i, "stage_deg": 60.0 * i, "heading_deg": 10.0,
                                                            "roll_deg": 0.1, "pitch_deg": -0.2, "yaw_deg": 10.0}, ns)
                lb.write_json(t.TILT_RAW, "viper.TiltRaw", {"roll_deg": 0.1, "pitch_deg": -0.2}, ns)
                lb.write_proto(t.GPS_FIX, m.location_fix(ns, 36.6, -84.25, 300.0, 2.5), ns)
            lb.write_proto(t.GPS_TRUTH, m.location_fix(t0, 36.6, -84.25, sigma_m=1.0), t0)
            lb.write_json(t.ESTIMATE_RECORD, "viper.Estimate", {"lat": 36.6, "lon": -84.25, "error_m": 12.0}, t0)
        seeds.append(path.read_bytes())
    return seeds


class Kind:
    """A kind's seeds (each a dict of file name -> bytes, the first file being the one mutated
    unless ``victims`` says otherwise), its mutators and its reader."""

    def __init__(self, name: str, work: Path) -> None:
        self.name, self.work = name, work
        self.folder = work / "in"
        self.seeds, self.read, self.text_kind = self._setup(name)

    def _setup(self, name: str) -> tuple[list[dict[str, bytes]], Callable[[Path], object], str]:
        if name == "csv":
            from appliance.skyline import read_skyline_csv

            return [{"sky.csv": s} for s in _skyline_seeds()], read_skyline_csv, "csv"
        if name == "config":
            from appliance.config import load_config

            seeds = [{"c.toml": (ROOT / "examples" / n).read_bytes()} for n in ("tripod.toml", "sim-forest.toml")]
            return seeds, load_config, "toml"
        if name == "pano-sidecar":
            from appliance.vision.panorama import load_panorama

            side = {"projection": "cylindrical", "px_per_rad": 15.28, "azimuth0_deg": 0.0, "horizon_row": 24.0,
                    "full_circle": True, "width": 96, "height": 48}
            return [{"p.png.json": json.dumps(side).encode(), "p.png": _small_image(".png")}], \
                lambda p: load_panorama(p.with_name("p.png")), "json"
        if name == "photo-sidecar":
            from appliance.vision.intrinsics import CameraIntrinsics, save_intrinsics
            from appliance.vision.photo import load_photo

            save_intrinsics(CameraIntrinsics(96, 48, 80.0, 80.0, 48.0, 24.0), self.work / "camera.toml")
            cam = (self.work / "camera.toml").read_bytes()
            pose = json.dumps({"yaw_deg": 30.0, "pitch_deg": 0.0, "roll_deg": 0.0, "camera": "camera.toml"}).encode()
            return [{"ph.png.json": pose, "ph.png": _small_image(".png"), "camera.toml": cam}], \
                lambda p: load_photo(p.with_name("ph.png")), "json"
        if name in ("dem-asc", "dem-usgs"):
            from appliance.terrain.dem import load_dem

            return _dem_seeds(self.work)[name], load_dem, "text"
        if name == "dem-hgt":
            from appliance.terrain.dem import load_dem

            return [{"N36W085.hgt": b""}], load_dem, ""
        if name in ("png", "jpeg"):
            from appliance.vision.panorama import read_image

            return [{f"i.{name}": _small_image("." + name)}], read_image, ""
        if name == "mcap":
            return [{"s.mcap": s} for s in _mcap_seeds(self.work)], _read_log, ""
        raise SystemExit(f"unknown kind {name}")

    def make(self, seed: int, i: int) -> tuple[Path, list[str]]:
        """Write input ``i`` into the kind's folder; the path of the file to read and the mutations."""
        rng = random.Random(f"{seed}:{self.name}:{i}")
        files = dict(rng.choice(self.seeds))
        victim = next(iter(files))
        if self.name == "photo-sidecar" and rng.random() < 0.3:
            victim = "camera.toml"
        data = files[victim]
        if self.name == "dem-hgt":
            data, ops = _hgt_bytes(rng)
        elif self.name == "png" and rng.random() < 0.3:
            data, ops = png_dims(data, rng)
        elif self.name == "jpeg" and rng.random() < 0.3:
            data, ops = jpeg_dims(data, rng)
        elif self.name == "mcap" and rng.random() < 0.3:
            data, ops = mcap_records(data, rng)
        else:
            data, ops = mutate_bytes(data, rng, "toml" if victim.endswith(".toml") else self.text_kind)
        files[victim] = data
        self.folder.mkdir(exist_ok=True)
        for old in self.folder.iterdir():
            old.unlink()
        for fname, content in files.items():
            (self.folder / fname).write_bytes(content)
        return self.folder / next(iter(files)), [victim] + ops


def _hgt_bytes(rng: random.Random) -> tuple[bytes, list[str]]:
    """An SRTM tile's worth of bytes, give or take a few: zeros, a ramp, or random samples."""
    side = rng.choice((1201, 1201, 1201, 3601))  # a 1" tile is 26 MB a read: fewer of them
    size = side * side * 2 + rng.choice((0, 0, 0, -1, 1, -2, 2, -4096, 4096))
    fill = rng.choice(("ramp", "nodata", "random-rows"))
    if fill == "nodata":
        data = b"\x80\x00" * (size // 2) + b"\x80" * (size % 2)
    else:
        row = struct.pack(f">{side}h", *(min(i, 32767) for i in range(side)))
        data = (row * (size // len(row) + 1))[:size]
        if fill == "random-rows":
            b = bytearray(data)
            for _ in range(8):
                j = rng.randrange(max(len(b) - 64, 1))
                b[j : j + 64] = bytes(rng.randrange(256) for _ in range(64))
            data = bytes(b)
    return data, [f"{side}-side size {size} {fill}"]


def _read_log(path: Path) -> None:
    """What ``viper log info``, ``viper replay`` and ``viper log recover`` read of a log."""
    from appliance.acquisition.replay import read_session
    from appliance.logbook.recover import recover_log
    from appliance.logbook.summary import summarize_log

    summarize_log(path).lines()
    read_session(path)
    recover_log(path, path.with_name("fixed.mcap"), overwrite=True)


# ----------------------------------------------------------------------------- worker


def worker(kind: str, seed: int, start: int, stop: int, fd: int) -> int:
    """Read inputs start..stop-1 of ``kind``; report each on ``fd``: ``s I OPS`` before it, then
    ``e`` (project error), ``k`` (read) or ``f TYPE MESSAGE``; ``o I RSS`` and exit OVER_EXIT after a
    run past 2 GB."""
    import logging
    import warnings

    from appliance.errors import ViperError

    logging.disable(logging.CRITICAL)
    warnings.simplefilter("ignore")
    out = os.fdopen(fd, "w", buffering=1)
    with tempfile.TemporaryDirectory(prefix=f"viper-edge-fuzz-{kind}-") as tmp:
        k = Kind(kind, Path(tmp))
        for i in range(start, stop):
            path, ops = k.make(seed, i)
            out.write(f"s {i} {json.dumps(ops)}\n")
            try:
                k.read(path)
            except ViperError:
                out.write("e\n")
            except BaseException as exc:  # noqa: BLE001 - what escapes the reader is what this counts
                first = str(exc).splitlines()[0][:200] if str(exc) else ""
                out.write(f"f {type(exc).__module__}.{type(exc).__qualname__} {json.dumps(first)}\n")
            else:
                out.write("k\n")
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            if rss > OVER_BYTES:
                out.write(f"o {i} {rss}\n")
                return OVER_EXIT
    out.write("d\n")
    return 0


# ----------------------------------------------------------------------------- parent


class Tally:
    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.inputs = self.read = self.errors = self.over = self.deaths = self.hangs = 0
        self.foreign: dict[str, list] = {}  # type -> [count, example index, message, mutations]
        self.overs: dict[str, list] = {}  # the same for the runs over 2 GB
        self.max_rss = 0
        self.seconds = 0.0

    def add_foreign(self, name: str, index: int, message: str, ops: list[str], over: bool = False) -> None:
        entry = (self.overs if over else self.foreign).setdefault(name, [0, index, message, ops])
        entry[0] += 1

    @property
    def n_foreign(self) -> int:
        return sum(e[0] for e in self.foreign.values())


def _spawn(kind: str, seed: int, start: int, stop: int, limit_gb: float, log: Path) -> tuple[subprocess.Popen, int]:
    r, w = os.pipe()
    limit = int(limit_gb * (1 << 30))

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    with log.open("wb") as err:
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--seed", str(seed),
                                 "--start", str(start), "--stop", str(stop), "--fd", str(w)],
                                pass_fds=(w,), preexec_fn=cap, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=err, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    os.close(w)
    return proc, r


def run_kind(kind: str, count: int, seed: int, limit_gb: float, hang_s: float, work: Path) -> Tally:
    import select

    t = Tally(kind)
    t0 = last_print = time.monotonic()
    start = 0
    log = work / f"{kind}.stderr"
    while start < count:
        proc, r = _spawn(kind, seed, start, count, limit_gb, log)
        current, ops, buf, done, hung = start - 1, [], b"", False, False
        while True:
            ready, _, _ = select.select([r], [], [], hang_s)
            if not ready:
                hung = True
                proc.kill()
                break
            chunk = os.read(r, 1 << 16)
            if not chunk:
                break
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                tag, _, rest = raw.decode().partition(" ")
                if tag == "s":
                    index, _, ops_text = rest.partition(" ")
                    current, ops = int(index), json.loads(ops_text)
                    t.inputs += 1
                elif tag == "e":
                    t.errors += 1
                elif tag == "k":
                    t.read += 1
                elif tag == "f":
                    name, _, msg = rest.partition(" ")
                    t.add_foreign(name, current, json.loads(msg), ops)
                elif tag == "o":
                    t.over += 1
                    t.add_foreign("run over 2 GB of RSS", current, f"peak {int(rest.split()[1]) >> 20} MB", ops,
                                  over=True)
                elif tag == "d":
                    done = True
            now = time.monotonic()
            if now - last_print > 30:
                last_print = now
                print(f"  {kind}: {t.inputs}/{count} in {now - t0:.0f} s ({t.inputs / (now - t0):.0f}/s), "
                      f"foreign {t.n_foreign}, over 2 GB {t.over}", flush=True)
        os.close(r)
        _, status, usage = os.wait4(proc.pid, 0)
        t.max_rss = max(t.max_rss, usage.ru_maxrss * 1024)
        code = os.waitstatus_to_exitcode(status)
        if done:
            break
        if current < start:
            tail = log.read_text("utf-8", "replace").strip().splitlines()
            raise SystemExit(f"{kind}: the worker did not start ({tail[-1] if tail else code})")
        if hung:
            t.hangs += 1
            t.add_foreign(f"no answer within {hang_s:.0f} s", current, "", ops)
        elif code != OVER_EXIT:
            t.deaths += 1
            tail = log.read_bytes()[-300:].decode("utf-8", "replace").strip().splitlines()
            what = f"signal {-code}" if code < 0 else f"exit {code}"
            t.add_foreign(f"worker died ({what})", current, tail[-1] if tail else "", ops)
        start = current + 1
    t.seconds = time.monotonic() - t0
    return t


def _example(ops: list[str]) -> str:
    return ", ".join(ops)[:120].replace("|", "/")


def record(tallies: list[Tally], args: argparse.Namespace) -> None:
    from bench.results_file import append_result

    day = datetime.date.today().isoformat()
    rows = []
    for t in tallies:
        kinds = "; ".join(f"{name} {e[0]}" for name, e in sorted(t.foreign.items())) or "none"
        rows.append(f"| {day} | {t.kind} | {t.inputs} | {t.read} | {t.errors} | {t.n_foreign} ({kinds}) | "
                    f"{t.over} | {t.deaths} | {t.hangs} | {t.max_rss >> 20} | {t.inputs / max(t.seconds, 1e-9):.0f} |")
    examples = []
    for t in tallies:
        for name, (n, index, msg, ops) in sorted(t.foreign.items()) + sorted(t.overs.items()):
            examples.append(f"- {t.kind}, {name} ({n}x): input {index} (`--show {t.kind} {index}`; "
                            f"{_example(ops)}): {msg.replace('|', '/')[:200]}")
    foreign = sum(t.n_foreign for t in tallies)
    over = sum(t.over for t in tallies)
    verdict = "pass" if not foreign and not over else f"FAIL: {foreign} foreign, {over} over 2 GB"
    text = ("\n".join(rows) + f"\n\nRun of {day} (--count {args.count} --seed {args.seed} --limit-gb "
            f"{args.limit_gb}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}): {verdict}.\n\n"
            + ("Foreign exceptions, one example each:\n\n" + "\n".join(examples) + "\n\n" if examples else ""))
    append_result(OUT, "# Fuzzing the readers at the edge\n\n`bench/edge_fuzz.py`: mutated skyline CSVs, "
                  "configurations, JSON sidecars, DEM headers, image headers and MCAP logs through the readers "
                  "the CLI uses, each kind in a worker under RLIMIT_AS.\nTarget: 0 foreign exceptions and 0 runs "
                  "over 2 GB.\n\n| date | kind | inputs | read | project errors | foreign (by type) | over 2 GB | "
                  "worker deaths | hangs | max RSS (MB) | inputs/s |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
                  text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100_000, help="inputs per kind")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated, of {', '.join(KINDS)}")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--limit-gb", type=float, default=4.0, help="RLIMIT_AS of each worker")
    ap.add_argument("--hang", type=float, default=60.0, help="seconds without an answer that count as a hang")
    ap.add_argument("--jobs", type=int, default=2, help="kinds run at once (each in its own worker)")
    ap.add_argument("--no-record", action="store_true", help="do not append to the results file")
    ap.add_argument("--show", nargs=2, metavar=("KIND", "I"), help="write input I of KIND into ./edge-fuzz-input/")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--start", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--stop", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--fd", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(args.worker, args.seed, args.start, args.stop, args.fd)
    if args.show:
        with tempfile.TemporaryDirectory() as tmp:
            k = Kind(args.show[0], Path(tmp))
            path, ops = k.make(args.seed, int(args.show[1]))
            dest = Path("edge-fuzz-input")
            dest.mkdir(exist_ok=True)
            for f in k.folder.iterdir():
                (dest / f.name).write_bytes(f.read_bytes())
            print(f"{dest / path.name}: {', '.join(ops)}")
        return 0
    from concurrent.futures import ThreadPoolExecutor

    def one(kind: str) -> Tally:
        print(f"{kind}: {args.count} inputs", flush=True)
        t = run_kind(kind, args.count, args.seed, args.limit_gb, args.hang, Path(tmp))
        print(f"{kind}: {t.inputs} inputs in {t.seconds:.0f} s, {t.read} read, {t.errors} project errors, "
              f"{t.n_foreign} foreign, {t.over} over 2 GB, max RSS {t.max_rss >> 20} MB", flush=True)
        for name, (n, index, msg, ops) in sorted(t.foreign.items()) + sorted(t.overs.items()):
            print(f"  {kind}: {name} x{n}: input {index} ({_example(ops)}): {msg[:160]}", flush=True)
        return t

    with tempfile.TemporaryDirectory(prefix="viper-edge-fuzz-") as tmp, ThreadPoolExecutor(args.jobs) as pool:
        tallies = list(pool.map(one, args.kinds.split(",")))
    if not args.no_record:
        record(tallies, args)
    return 0 if all(not t.n_foreign and not t.over for t in tallies) else 1


if __name__ == "__main__":
    sys.exit(main())
