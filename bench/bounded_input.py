"""The catalogue of inputs that never end, blow up memory or have another shape (issue 35), run as a
user would: ``viper`` in a child process with a 60 s timeout and a 2 GiB address-space limit, its
peak memory read from the kernel's accounting of the child (``wait4``).

Each case builds its inputs in a folder of its own and names what must happen: one stderr line
matching a pattern and a non-zero exit, or a correct result (exit status and output).  The test
``tests/test_bounded_input.py`` runs the same catalogue and asserts each case; this script prints the
table of outcomes and peak memory and appends it, dated, to ``bench/results/bounded_input.md``.

    python -m bench.bounded_input [--out bench/results/bounded_input.md] [--only NAME]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
TIMEOUT_S = 60.0
MEMORY_BYTES = 2 << 30
DEEP = 100_000  # nesting of the deeply nested JSON and TOML


@dataclass(frozen=True)
class Run:
    """One ``viper`` run: exit status (None: killed at the timeout), output and peak memory."""

    returncode: int | None
    stdout: str
    stderr: str
    peak_bytes: int
    seconds: float

    @property
    def stderr_lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_BYTES, MEMORY_BYTES))


def run_viper(args: list[str], cwd: Path, timeout: float = TIMEOUT_S) -> Run:
    """Run ``viper ARGS`` in ``cwd`` under the timeout and the memory limit."""
    env = dict(os.environ, PYTHONPATH=str(REPO), VIPER_SOCKET="", VIPER_CACHE_DIR=str(cwd / ".cache"),
               PYTHONWARNINGS="ignore")
    out, err = cwd / ".stdout", cwd / ".stderr"
    t0 = time.monotonic()
    with out.open("wb") as fo, err.open("wb") as fe:
        proc = subprocess.Popen([sys.executable, "-m", "appliance.cli.main", *args], cwd=cwd, env=env,
                                stdin=subprocess.DEVNULL, stdout=fo, stderr=fe, preexec_fn=_limit_memory)
    status, usage, killed = None, None, False
    while status is None:
        pid, st, ru = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            status, usage = st, ru
        elif time.monotonic() - t0 > timeout and not killed:
            os.kill(proc.pid, signal.SIGKILL)
            killed = True
        else:
            time.sleep(0.05)
    proc.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.monotonic() - t0
    text = out.read_text(errors="replace"), err.read_text(errors="replace")
    out.unlink()
    err.unlink()
    assert usage is not None
    return Run(None if killed else proc.returncode, text[0], text[1], usage.ru_maxrss * 1024, seconds)


# --- inputs ----------------------------------------------------------------------------------------

def png_bytes(width: int, height: int, rows: int | None = None) -> bytes:
    """A PNG declaring ``width`` x ``height`` grey pixels whose data holds ``rows`` rows of zeros (all of
    them by default; fewer make a bomb's header without its gigabytes)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    n = height if rows is None else rows
    raw = zlib.compress(b"\0" * ((width + 1) * n), 9)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", raw) + chunk(b"IEND", b""))


def skyline_csv(folder: Path, name: str = "sky.csv") -> str:
    rows = "".join(f"{a},{1.0 + 0.5 * ((a // 30) % 2)}\n" for a in range(360))
    (folder / name).write_text("azimuth_deg,elevation_deg\n" + rows)
    return name


def deep_json() -> str:
    return "[" * DEEP + "]" * DEEP


def fifo(folder: Path, name: str) -> str:
    os.mkfifo(folder / name)
    return name


def mcap_with(folder: Path, name: str, messages: list[tuple[str, str, bytes]]) -> str:
    """A complete MCAP log whose JSON channels (topic, schema name) carry the raw ``messages``."""
    from mcap.writer import Writer

    with (folder / name).open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="bench")
        channels: dict[str, int] = {}
        for i, (topic, schema, data) in enumerate(messages):
            if topic not in channels:
                sid = w.register_schema(name=schema, encoding="jsonschema", data=b"{}")
                channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            t = 1_780_000_000_000_000_000 + i * 1_000_000
            w.add_message(channel_id=channels[topic], log_time=t, data=data, publish_time=t)
        w.finish()
    return name


MCAP_MAGIC = b"\x89MCAP0\r\n"
GIB3 = 3 << 30  # what the compression bombs inflate to


def _record(opcode: int, body: bytes, length: int | None = None) -> bytes:
    """An MCAP record: its opcode, its length (``body``'s unless forged) and ``body``."""
    return bytes([opcode]) + struct.pack("<Q", len(body) if length is None else length) + body


def _chunk(compression: str, data: bytes, uncompressed_size: int) -> bytes:
    """A chunk record's body: no time span, no CRC, ``data`` declared as ``uncompressed_size`` bytes."""
    return (struct.pack("<QQQI", 0, 0, uncompressed_size, 0) + struct.pack("<I", len(compression))
            + compression.encode() + struct.pack("<Q", len(data)) + data)


def _zeros_compressed(compression: str, size: int) -> bytes:
    """``size`` zero bytes as one zstd frame (declaring its size) or one lz4 frame, compressed piece by piece."""
    import io

    import lz4.frame
    import zstandard

    piece = bytes(16 << 20)
    if compression == "zstd":
        buf = io.BytesIO()
        with zstandard.ZstdCompressor(level=3).stream_writer(buf, size=size, closefd=False) as w:
            for _ in range(size // len(piece)):
                w.write(piece)
        return buf.getvalue()
    with lz4.frame.LZ4FrameCompressor() as c:
        return c.begin() + b"".join(c.compress(piece) for _ in range(size // len(piece))) + c.flush()


def hostile_mcap(d: Path, name: str, record: bytes) -> str:
    """A log of the magic, a header record and ``record`` (forged by hand, lengths included)."""
    header = _record(0x01, struct.pack("<I", 5) + b"viper" + struct.pack("<I", 5) + b"bench")
    (d / name).write_bytes(MCAP_MAGIC + header + record)
    return name


# each: the record after the header (at byte 35), and what `viper log info` says of it
HOSTILE_MCAP: dict[str, tuple[Callable[[], bytes], str]] = {
    "mcap-chunk-length-2e62": (lambda: _record(0x06, bytes(64), 2**62),
                               r"unreadable record at byte 35: CHUNK record has length 4611686018427387904 that "
                               r"exceeds limit 108"),
    "mcap-attachment-length-2e62": (lambda: _record(0x09, bytes(64), 2**62),
                                    r"unreadable record at byte 35: ATTACHMENT record has length 4611686018427387904"),
    "mcap-attachment-data-2e62": (lambda: _record(0x09, struct.pack("<QQ", 0, 0) + struct.pack("<I", 1) + b"a"
                                                  + struct.pack("<I", 1) + b"b" + struct.pack("<Q", 2**62)
                                                  + bytes(16)),
                                  r"unreadable record at byte 35: a length of 4611686018427387904 bytes, more than the "
                                  r"file's \d+"),
    "mcap-chunk-data-2e64": (lambda: _record(0x06, struct.pack("<QQQI", 0, 0, 10, 0) + struct.pack("<I", 0)
                                             + struct.pack("<Q", 2**64 - 1) + bytes(10)),
                             r"unreadable record at byte 35: a length of 18446744073709551615 bytes, more than the "
                             r"file's \d+"),
    "mcap-string-beyond-file": (lambda: _record(0x03, struct.pack("<HI", 1, 2**31) + b"abc"),
                                r"unreadable record at byte 35: a length of 2147483648 bytes, more than the "
                                r"file's \d+"),
    "mcap-chunk-declaring-2e62": (lambda: _record(0x06, _chunk("zstd", b"", 2**62)),
                                  r"unreadable record at byte 35: a chunk declaring 4611686018427387904 bytes "
                                  r"uncompressed, more than the 256 MiB a chunk may hold"),
    "mcap-zstd-bomb-3-gib": (lambda: _record(0x06, _chunk("zstd", _zeros_compressed("zstd", GIB3), 1000)),
                             r"unreadable record at byte 35: a chunk declaring 1000 bytes uncompressed holds more "
                             r"than 1000"),
    "mcap-lz4-bomb-3-gib": (lambda: _record(0x06, _chunk("lz4", _zeros_compressed("lz4", GIB3), 1000)),
                            r"unreadable record at byte 35: a chunk declaring 1000 bytes uncompressed holds more "
                            r"than 1000"),
}


def _hostile_info(case: str) -> Callable[[Path, dict[str, Path]], list[str]]:
    def make(d: Path, shared: dict[str, Path]) -> list[str]:
        return ["log", "info", hostile_mcap(d, "hostile.mcap", HOSTILE_MCAP[case][0]())]
    return make


def _hostile_replay(case: str) -> Callable[[Path, dict[str, Path]], list[str]]:
    def make(d: Path, shared: dict[str, Path]) -> list[str]:
        return ["replay", hostile_mcap(d, "hostile.mcap", HOSTILE_MCAP[case][0]()), "--db", str(shared["db"]),
                "--out", "rep"]
    return make


SHAPES = [
    ("/estimate/record", "viper.EstimateRecord", b"[1, 2]"),
    ("/estimate/record", "viper.EstimateRecord", b'{"lat": "north", "lon": [], "region": 5}'),
    ("/estimate/record", "viper.EstimateRecord", b'{"lat": 36.5, "lon": -84.2, "ambiguous": true, "region": "big",'
                                                 b' "error_m": "far"}'),
    ("/gps/truth", "viper.Fix", b'{"latitude": 36.5}'),
    ("/estimate/fix", "viper.Fix", b'"a string"'),
    ("/camera/capture", "viper.Capture", b"[1]"),
    ("/camera/capture", "viper.Capture", b'{"index": "first", "stage_deg": null}'),
    ("/camera/image", "viper.Image", b'{"data": 5}'),
    ("/camera/calibration", "viper.Calibration", b'{"K": 1}'),
    ("/session/procedure", "viper.Procedure", b'{"procedure": "truth", "used": [1], "sigma_m": {}}'),
    ("/session/info", "viper.Session", b'{"session_id": {"a": 1}}'),
    ("/skyline/detected", "viper.Skyline", b'{"elevation_deg": 5}'),
    ("/skyline/detected", "viper.Skyline", b'{"elevation_deg": ["high", 1e999]}'),
]


@dataclass(frozen=True)
class Case:
    """A case: ``make`` builds its inputs in a folder and returns viper's arguments; ``expect`` is the
    pattern of the one stderr line (after ``viper CMD: error: ``), or None for a correct result
    (exit status ``ok_status`` and ``stdout`` matching ``expect_stdout``)."""

    name: str
    make: Callable[[Path, dict[str, Path]], list[str]]
    expect: str | None
    ok_status: int = 0
    expect_stdout: str = ""
    needs: tuple[str, ...] = ()  # shared inputs: "db" (a small skyline database), "srtm" (../shared/data)


def _estimate_config(text: str) -> Callable[[Path, dict[str, Path]], list[str]]:
    def make(d: Path, shared: dict[str, Path]) -> list[str]:
        (d / "c.toml").write_text(text)
        return ["estimate", "map.viperdb", skyline_csv(d), "--config", "c.toml"]
    return make


def _ten_million_rows(d: Path, shared: dict[str, Path]) -> list[str]:
    block = ("".join(f"{i * 3.6e-5:.6f},1.5\n" for i in range(1_000_000))).encode()
    with (d / "big.csv").open("wb") as fh:
        fh.write(b"azimuth_deg,elevation_deg\n")
        for _ in range(10):
            fh.write(block)
    return ["estimate", "map.viperdb", "big.csv"]


def _npz_bomb(d: Path, rows: int, cols: int) -> str:
    """A compressed .npz DEM of a few MB whose rows x cols float64 heights (all zero) inflate to
    8 rows cols bytes."""
    import io
    import zipfile

    import numpy as np

    with zipfile.ZipFile(d / "bomb.npz", "w", compression=zipfile.ZIP_DEFLATED) as zf:
        with zf.open("elevation.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (rows, cols)})
            row = bytes(8 * cols)
            for _ in range(rows):
                fh.write(row)
        for key in ("dx", "dy", "xmin", "xmax", "ymin", "ymax"):
            one = io.BytesIO()
            np.save(one, np.float64(1.0))
            zf.writestr(f"{key}.npy", one.getvalue())
    return "bomb.npz"


def _e00_declaring(d: Path, rows: int, cols: int) -> str:
    """An ArcInfo .e00 grid whose GRD header declares rows x cols cells and holds one line of them."""
    (d / "huge.e00").write_text(
        "EXP  0 /huge.e00\nGRD  2\n"
        f"{cols:10d}{rows:10d}         2-0.21474836470000000E+10\n"
        " 0.10000000000000000E+01 0.10000000000000000E+01\n"
        " 0.00000000000000000E+00 0.00000000000000000E+00\n"
        f" {float(cols):.17E} {float(rows):.17E}\n"
        " 0.1000000E+01 0.1000000E+01 0.1000000E+01 0.1000000E+01 0.1000000E+01\nEOG\n")
    return "huge.e00"


def _theodolite_config_zero(d: Path, shared: dict[str, Path]) -> list[str]:
    (d / "points.csv").write_text("point,camera_elevation_deg,theodolite_elevation_deg\n"
                                  + "".join(f"p{i},{i * 0.5:.2f},{i * 0.5 + 0.1 * (i % 3 - 1):.2f}\n"
                                            for i in range(12)))
    return ["calibrate", "theodolite", "points.csv", "--config", "/dev/zero"]


def _png(d: Path, name: str, width: int, height: int, rows: int | None = None) -> str:
    (d / name).write_bytes(png_bytes(width, height, rows))
    return name


def _pano_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    _png(d, "pano.png", 360, 90)
    (d / "pano.png.json").write_text(deep_json())
    return ["skyline", "pano.png", "--out", "s.csv"]


def _stitch_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    _png(d, "shot.png", 64, 48)
    (d / "shot.png.json").write_text(deep_json())
    return ["stitch", "shot.png", "--out", "p.png", "--hfov-deg", "60"]


def _photo_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    _png(d, "photo.png", 64, 48)
    (d / "cam.toml").write_text("[camera]\nwidth = 64\nheight = 48\nfx = 50.0\nfy = 50.0\ncx = 31.5\ncy = 23.5\n")
    (d / "o.json").write_text(deep_json())
    return ["skyline", "photo.png", "--camera", "cam.toml", "--orientation", "o.json", "--out", "s.csv"]


def _tiled_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    (d / "tiled").mkdir()
    (d / "tiled" / "index.json").write_text(deep_json())
    return ["estimate", "tiled", skyline_csv(d)]


def _db_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    head = deep_json().encode()
    (d / "deep.viperdb").write_bytes(b"VIPERDB\0" + struct.pack("<I", len(head)) + head)
    return ["estimate", "deep.viperdb", skyline_csv(d)]


def _log_nested(d: Path, shared: dict[str, Path]) -> list[str]:
    return ["log", "info", mcap_with(d, "deep.mcap", [("/estimate/record", "viper.EstimateRecord",
                                                        deep_json().encode())])]


def _replay(name: str, messages: list[tuple[str, str, bytes]]) -> Callable[[Path, dict[str, Path]], list[str]]:
    def make(d: Path, shared: dict[str, Path]) -> list[str]:
        return ["replay", mcap_with(d, name, messages), "--db", str(shared["db"]), "--out", "rep"]
    return make


def _ansi_name(d: Path, shared: dict[str, Path]) -> list[str]:
    return ["estimate", "map.viperdb", "\x1b[31mred\x1b[0m.csv"]


def _long_name(d: Path, shared: dict[str, Path]) -> list[str]:
    return ["render", "jacksboro", "--lat", "36.555", "--lon=-84.29", "--out", "s" * 246 + ".csv"]


def _two_far_tiles(d: Path, shared: dict[str, Path]) -> list[str]:
    srtm = shared["srtm"]
    return ["precompute", str(srtm / "N43E006.hgt"), str(srtm / "N44W072.hgt"), "--out", "big.viperdb"]


CATALOGUE: list[Case] = [
    # inputs that never end
    Case("fifo-skyline", lambda d, s: ["estimate", "map.viperdb", fifo(d, "sky.csv")], r"sky\.csv: the skyline "
         r"file is a FIFO, not a regular file"),
    Case("fifo-database", lambda d, s: ["estimate", fifo(d, "map.viperdb"), skyline_csv(d)],
         r"map\.viperdb: the database is a FIFO, not a regular file"),
    Case("fifo-dem", lambda d, s: ["dem", "info", fifo(d, "map.tif")], r"map\.tif: the DEM is a FIFO, not a "
         r"regular file"),
    Case("fifo-config", lambda d, s: ["estimate", "map.viperdb", skyline_csv(d), "--config", fifo(d, "c.toml")],
         r"c\.toml: the configuration file is a FIFO, not a regular file"),
    Case("fifo-log-info", lambda d, s: ["log", "info", fifo(d, "s.mcap")], r"s\.mcap: the log is a FIFO, not a "
         r"regular file"),
    Case("dev-zero-skyline", lambda d, s: ["estimate", "map.viperdb", "/dev/zero"],
         r"/dev/zero: the skyline file is a character device, not a regular file"),
    Case("dev-zero-config", lambda d, s: ["estimate", "map.viperdb", skyline_csv(d), "--config", "/dev/zero"],
         r"/dev/zero: the configuration file is a character device, not a regular file"),
    # memory
    Case("csv-10-million-rows", _ten_million_rows, r"big\.csv: the skyline file is larger than 32 MiB"),
    Case("png-bomb-skyline", lambda d, s: ["skyline", _png(d, "bomb.png", 30000, 30000, 1), "--out", "s.csv"],
         r"bomb\.png: a 30000 x 30000 image has 900,000,000 pixels, more than 50,000,000"),
    Case("png-bomb-stitch", lambda d, s: ["stitch", _png(d, "bomb.png", 30000, 30000, 1), "--out", "p.png",
                                          "--hfov-deg", "60", "--stage-angles", "0"],
         r"bomb\.png: a 30000 x 30000 image has 900,000,000 pixels, more than 50,000,000"),
    Case("precompute-two-far-tiles", _two_far_tiles, r"too large for one metric grid", needs=("srtm",)),
    # deeply nested JSON and TOML, in each place the appliance parses them
    Case("nested-config", _estimate_config("[estimator]\nx = " + deep_json() + "\n"),
         r"c\.toml: not valid TOML: nested 100000 levels deep, more than 64"),
    Case("nested-pano-sidecar", _pano_nested, r"pano\.png\.json: the (panorama|JSON) sidecar is not valid JSON: "
         r"nested 100000 levels deep"),
    Case("nested-photo-orientation", _photo_nested, r"o\.json: the JSON sidecar is not valid JSON: nested 100000"),
    Case("nested-stitch-sidecar", _stitch_nested, r"shot\.png\.json: the pose sidecar is not valid JSON: nested "
         r"100000"),
    Case("nested-tiled-index", _tiled_nested, r"index\.json: the index\.json is not valid JSON: nested 100000"),
    Case("nested-database-header", _db_nested, r"deep\.viperdb: unreadable database header \(nested 100000 levels"),
    Case("nested-mcap-log-info", _log_nested, None, expect_stdout=r"1 messages, complete"),
    Case("nested-mcap-replay", _replay("deep.mcap", [("/camera/capture", "viper.Capture", deep_json().encode())]),
         None, ok_status=1, expect_stdout=r"no estimate: no tagged frames", needs=("db",)),
    # JSON of another shape on the viper channels
    Case("shapes-mcap-log-info", lambda d, s: ["log", "info", mcap_with(d, "shapes.mcap", SHAPES)], None,
         expect_stdout=r"estimate:  lat 36\.500000 lon -84\.200000  ambiguous \(\? cells"),
    Case("shapes-mcap-replay", _replay("shapes.mcap", SHAPES), None, ok_status=1,
         expect_stdout=r"no estimate: no tagged frames", needs=("db",)),
    # options
    Case("sigma-1e-300", lambda d, s: ["estimate", "map.viperdb", skyline_csv(d), "--sigma", "1e-300,1e-299"],
         r"--sigma: estimator\.sigma_deg: expected \[lo, hi\] in degrees with 0\.001 <= lo"),
    Case("replay-sigma-1e-300", lambda d, s: ["replay", "x.mcap", "--sigma", "1e-300,1e-299", "--out", "rep"],
         r"--sigma: estimator\.sigma_deg: expected \[lo, hi\] in degrees with 0\.001 <= lo"),
    Case("truth-nan", lambda d, s: ["estimate", "map.viperdb", skyline_csv(d), "--truth", "nan,nan"],
         r"--truth 'nan,nan': expected 2 comma-separated finite numbers"),
    Case("fuse-move-nan", lambda d, s: ["estimate", "map.viperdb", skyline_csv(d), skyline_csv(d, "b.csv"),
                                        "--fuse", "--move", "nan,0,1"],
         r"--move 'nan,0,1': expected 3 comma-separated finite numbers"),
    Case("render-max-range-1e-300", lambda d, s: ["render", "jacksboro", "--lat", "36.555", "--lon=-84.29",
                                                  "--max-range", "1e-300"],
         r"a reach of 1e-300 m holds no sample of the map"),
    # names and keys
    Case("ansi-file-name", _ansi_name, r"\\x1b\[31mred\\x1b\[0m\.csv: skyline file not found"),
    Case("ansi-toml-key", _estimate_config('"\\u001b[2J" = 1\n'), r"unknown key \\x1b\[2J"),
    Case("long-output-name", _long_name, None),
    # configuration limits
    Case("camera-100000", _estimate_config("[devices.camera]\nwidth = 100000\nheight = 100000\n"),
         r"devices\.camera\.width: expected an integer in \[1, 20000\], got 100000"),
    Case("compass-steps-1e6", _estimate_config("[session]\ncompass_steps = 1000000\n"),
         r"session\.compass_steps: expected an integer in \[3, 360\], got 1000000"),
    Case("reserve-bytes-1e12", _estimate_config("[logbook]\nreserve_bytes = 1000000000000\n"),
         r"logbook\.reserve_bytes: expected an integer in \[0, 1073741824\] \(1 GiB\), got 1000000000000"),
    # readers and options of the last round
    Case("npz-bomb-144-mp", lambda d, s: ["dem", "info", _npz_bomb(d, 12000, 12000)],
         r"bomb\.npz: 12000 x 12000 pixels, more than the 100,000,000 a map read whole may have"),
    Case("e00-declaring-10-gp", lambda d, s: ["dem", "info", _e00_declaring(d, 100000, 100000)],
         r"huge\.e00: 100000 x 100000 pixels, more than the 100,000,000 a map read whole may have"),
    Case("render-height-1e300", lambda d, s: ["render", "jacksboro", "--lat", "36.555", "--lon=-84.29",
                                              "--height", "1e300"],
         r"--height 1e\+300 m: more than 100000 m above the ground"),
    Case("calibrate-config-dev-zero", _theodolite_config_zero, r"/dev/zero: the configuration is a character "
         r"device, not a regular file"),
    # MCAP records with forged lengths: `log info` reports the log INCOMPLETE (exit 1) with the reason on
    # stdout; `replay` notes it and finds no frame to estimate from
    *(Case(name, _hostile_info(name), None, ok_status=1,
           expect_stdout=r"hostile\.mcap: \d+ bytes, 0 messages, INCOMPLETE: " + said)
      for name, (_, said) in HOSTILE_MCAP.items()),
    *(Case(name.replace("mcap-", "mcap-replay-"), _hostile_replay(name), None, ok_status=1,
           expect_stdout=r"log incomplete \(" + said + r".*\n.*no estimate: no tagged frames", needs=("db",))
      for name, (_, said) in HOSTILE_MCAP.items() if name in ("mcap-chunk-length-2e62", "mcap-zstd-bomb-3-gib",
                                                                "mcap-lz4-bomb-3-gib")),
]


def build_shared(folder: Path) -> dict[str, Path]:
    """The shared inputs: a skyline database of a few nodes of the jacksboro map (built here, in a few
    seconds) and the SRTM tiles of ../shared/data when present."""
    sys.path.insert(0, str(REPO))
    from appliance.terrain.database import build_database
    from appliance.terrain.dem import load_dem

    db = folder / "tiny.viperdb"
    if not db.exists():
        build_database(load_dem("jacksboro"), db, search_bounds=(-84.29, 36.555, -84.288, 36.556),
                       max_range_m=3000.0, progress=None)
    shared = {"db": db}
    if (SHARED / "dem_srtm_hgt" / "N44W072.hgt").exists():
        shared["srtm"] = SHARED / "dem_srtm_hgt"
    return shared


def listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if ".cache" not in p.parts}


def run_case(case: Case, folder: Path, shared: dict[str, Path]) -> tuple[Run, set[str], set[str]]:
    """Run ``case`` in the empty folder ``folder``: (the run, the files before, the files after)."""
    args = case.make(folder, shared)
    before = listing(folder)
    return run_viper(args, folder), before, listing(folder)


def verdict(case: Case, run: Run, before: set[str], after: set[str]) -> str:
    """'ok' when the case ended as it must, else what went wrong."""
    if run.returncode is None:
        return f"hung past {TIMEOUT_S:.0f} s"
    if "Traceback" in run.stderr:
        return "traceback"
    if run.peak_bytes >= MEMORY_BYTES:
        return "over 2 GiB"
    if case.expect is None:
        if run.returncode != case.ok_status:
            return f"exit {run.returncode}: {run.stderr.strip()[-200:]}"
        if case.expect_stdout and not re.search(case.expect_stdout, run.stdout):
            return f"stdout {run.stdout.strip()[-200:]!r}"
        return "ok"
    lines = run.stderr_lines
    if run.returncode == 0 or len(lines) != 1:
        return f"exit {run.returncode}, {len(lines)} stderr lines: {run.stderr.strip()[-300:]!r}"
    if not re.match(r"viper [a-z]+: error: ", lines[0]) or not re.search(case.expect, lines[0]):
        return f"line {lines[0]!r}"
    if after != before:
        return f"left behind: {sorted(after - before)}"
    return "ok"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "bounded_input.md")
    ap.add_argument("--only", help="run only the cases whose name contains this")
    args = ap.parse_args(argv)
    rows = []
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        shared = build_shared(root)
        for i, case in enumerate(CATALOGUE):
            if args.only and args.only not in case.name:
                continue
            if any(n not in shared for n in case.needs):
                rows.append((case.name, "skipped (no ../shared/data)", "", "", ""))
                continue
            folder = root / f"case{i:02d}"
            folder.mkdir()
            run, before, after = run_case(case, folder, shared)
            v = verdict(case, run, before, after)
            failed += v != "ok"
            line = run.stderr_lines[0] if run.stderr_lines else run.stdout.strip().splitlines()[-1:]
            shown = json.dumps(line if isinstance(line, str) else " ".join(line), ensure_ascii=True)[1:-1]
            rows.append((case.name, v, str(run.returncode), f"{run.peak_bytes / 2**20:.0f}",
                         f"{run.seconds:.1f}"))
            print(f"{case.name:28s} {v:6s} exit {run.returncode}  {run.peak_bytes / 2**20:6.0f} MiB  "
                  f"{run.seconds:5.1f} s  {shown[:110]}", flush=True)
    table = ["| case | outcome | exit | peak RSS (MiB) | time (s) |", "|---|---|---|---|---|"]
    table += [f"| {' | '.join(r)} |" for r in rows]
    header = ("# Bounded input: the catalogue of issue 35\n\n"
              "`python -m bench.bounded_input`: each case runs `viper` in a child process with a 60 s timeout and "
              "a 2 GiB address-space limit (RLIMIT_AS); peak RSS is the child's `ru_maxrss` from `wait4`. "
              "'ok' means one stderr line of the expected shape, a non-zero exit and nothing left behind, or the "
              "correct result.\n")
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    text = (f"\n## {stamp}\n\nPython {sys.version.split()[0]}, {os.cpu_count()} CPUs, load average "
            f"{os.getloadavg()[0]:.1f} at the end; {len(rows)} cases, {failed} not ok.\n\n" + "\n".join(table) + "\n")
    if not args.only:
        sys.path.insert(0, str(REPO))
        from bench.results_file import append_result

        append_result(args.out, header, text)
        print(f"appended to {args.out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
