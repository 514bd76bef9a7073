"""Bounded input at the edge: every file the appliance reads from a user passes through here.

A path must name a regular file (a FIFO, a device such as ``/dev/zero``, a socket or a folder is
refused before it is opened for reading, so nothing waits on a writer that never comes or reads
without end); streams that are meant to be streams (an NMEA serial port, a recorded NMEA log the
drivers replay) do not come through here.  What is read is capped for each kind: bytes of a
configuration, a sidecar or a CSV, the nesting of JSON and TOML (checked on the text before a
recursive parser sees it), and the pixels of an image (read from its header before it is decoded).
Each refusal is one :class:`~appliance.errors.ViperError` line naming the file.
"""

from __future__ import annotations

import io
import json
import os
import re
import stat
import struct
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from appliance.errors import InputError, ViperError

#: A configuration or calibration TOML (the shipped ones are a few KiB).
MAX_CONFIG_BYTES = 1 << 20
#: A JSON sidecar of a photo or panorama, or a stitch shot's pose.
MAX_SIDECAR_BYTES = 1 << 20
#: A tiled database's index.json (a few hundred bytes per tile: some 100,000 tiles).
MAX_INDEX_BYTES = 64 << 20
#: A skyline CSV: one row per azimuth, at most a thousandth of a degree apart.
MAX_SKYLINE_ROWS = 360_000
MAX_SKYLINE_BYTES = 32 << 20
#: Nesting of the JSON and TOML the appliance reads (its own formats nest 4 levels at most).
MAX_NESTING = 64
#: Pixels of an image decoded whole (a photo of 50 megapixels, a panorama of 16000 x 3000).
MAX_IMAGE_PIXELS = 50_000_000
#: Bytes of an image file.
MAX_IMAGE_BYTES = 256 << 20

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder"))


def file_kind(mode: int) -> str:
    """What a file of ``mode`` is, in words ("a FIFO", "a character device"...)."""
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str | Path, what: str = "file", error: type[ViperError] = InputError) -> None:
    """Refuse ``path`` unless it is a regular file (links followed); a missing file raises the
    ``OSError`` of ``stat`` for the caller's own message.  For readers that open by name (GDAL)."""
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise error(f"{path}: the {what} is {file_kind(mode)}, not a regular file")


def open_regular(path: str | Path, what: str = "file", error: type[ViperError] = InputError) -> io.BufferedReader:
    """Open ``path`` for reading if it is a regular file, else raise ``error`` in one line.

    The file is opened without blocking (a FIFO opens at once, with no writer) and checked on the
    open descriptor, so what is checked is what is read.  A missing or unreadable file raises the
    ``OSError`` of ``open`` for the caller's own message."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise error(f"{path}: the {what} is {file_kind(mode)}, not a regular file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bounded(path: str | Path, limit: int, what: str = "file", error: type[ViperError] = InputError) -> bytes:
    """The bytes of the regular file ``path``, refused in one line when longer than ``limit``."""
    with open_regular(path, what, error) as fh:
        size = os.fstat(fh.fileno()).st_size
        data = b"" if size > limit else fh.read(limit + 1)
    if size > limit or len(data) > limit:
        raise error(f"{path}: the {what} is larger than {_size(limit)} ({_size(max(size, len(data)))}"
                    f"{'' if size > limit else ' or more'})")
    return data


def read_text_bounded(path: str | Path, limit: int, what: str = "file", error: type[ViperError] = InputError,
                      encoding: str = "utf-8") -> str:
    """:func:`read_bounded` decoded (``UnicodeDecodeError`` for the caller's message)."""
    return read_bounded(path, limit, what, error).decode(encoding)


def _size(n: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift:
            return f"{n / (1 << shift):.3g} {unit}"
    return f"{n} bytes"


# strings (JSON's and TOML's four kinds) and TOML comments, whose brackets do not nest
_NOT_NESTING = re.compile(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*')
_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_OPEN[[ord("]"), ord("}")]] = -1


def nesting_depth(text: str | bytes) -> int:
    """The deepest nesting of arrays and tables/objects in JSON or TOML text (brackets in strings and
    comments left out), counted without recursion."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    bare = _NOT_NESTING.sub("", text).encode("utf-8", errors="replace")
    if not bare:
        return 0
    steps = _OPEN[np.frombuffer(bare, np.uint8)].astype(np.int32)
    return int(np.cumsum(steps).max(initial=0))


class NestingError(ValueError):
    """Text nested deeper than a parser is let to recurse (a ``ValueError`` like the parser's own
    errors, which the caller words with the file's name)."""


def check_nesting(text: str | bytes, limit: int = MAX_NESTING) -> None:
    """Raise :class:`NestingError` when ``text`` nests deeper than ``limit``, before a recursive
    parser would exhaust the stack on it."""
    depth = nesting_depth(text)
    if depth > limit:
        raise NestingError(f"nested {depth} levels deep, more than {limit}")


def read_json_bounded(path: str | Path, what: str, limit: int = MAX_SIDECAR_BYTES,
                      error: type[ViperError] = InputError) -> Any:
    """The JSON value of the regular file ``path`` of at most ``limit`` bytes, nested at most
    :data:`MAX_NESTING` levels; every refusal is one ``error`` line naming the file and ``what`` it
    is.  A missing or unreadable file raises the ``OSError`` of ``open`` for the caller's message."""
    data = read_bounded(path, limit, what, error)
    try:
        check_nesting(data)
        return json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise error(f"{path}: the {what} is not valid JSON: {exc}") from None


_PNG = b"\x89PNG\r\n\x1a\n"


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) declared by an image's header, without decoding the pixels: a PNG's IHDR read
    here, any other format's header read by Pillow (a dependency of matplotlib); None for a format
    Pillow does not know or a header it cannot read (the decoder then says what it finds)."""
    if data[:8] == _PNG and data[12:16] == b"IHDR" and len(data) >= 24:
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    # deferred: Pillow is needed only for images
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's own bomb warning: the cap is checked by the caller
            with Image.open(io.BytesIO(data)) as im:
                w, h = im.size
    except Image.DecompressionBombError:
        return None if Image.MAX_IMAGE_PIXELS is None else (2 * Image.MAX_IMAGE_PIXELS + 1, 1)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError, IndexError, TypeError):
        return None
    return int(w), int(h)


def check_image_pixels(data: bytes, name: str | Path, limit: int = MAX_IMAGE_PIXELS) -> None:
    """Refuse an image whose header declares more than ``limit`` pixels, before it is decoded."""
    size = image_size(data)
    if size is None or size[0] * size[1] <= limit:
        return
    shape = f"a {size[0]} x {size[1]} image has" if size[1] > 1 else "the image has over"
    raise InputError(f"{name}: {shape} {size[0] * size[1]:,} pixels, more than {limit:,}")


def bounded_png(data: bytes) -> bytes:
    """``data`` as an image decoder may take it: a PNG cut before its first chunk that runs past the end of the
    data (OpenCV's PNG reader allocates the length a chunk declares before it reads the chunk: 161 bytes
    declaring a 2.5 GiB chunk took 2.5 GiB); any other format as it is."""
    if data[:8] != _PNG:
        return data
    pos = 8
    while pos < len(data):
        end = pos + 12 + int.from_bytes(data[pos:pos + 4], "big")  # length, type, data, CRC
        if pos + 12 > len(data) or end > len(data):
            return data[:pos]
        pos = end
    return data


def read_image_bytes(path: str | Path) -> bytes:
    """The bytes of an image file (regular, capped), its pixel count checked from its header."""
    data = read_bounded(path, MAX_IMAGE_BYTES, "image")
    check_image_pixels(data, path)
    return data


def read_image_buffer(path: str | Path) -> bytes:
    """:func:`read_image_bytes`, a missing or unreadable file refused in one :class:`InputError` line:
    the buffer a decoder (``cv2.imdecode``) takes."""
    try:
        return bounded_png(read_image_bytes(path))
    except FileNotFoundError:
        raise InputError(f"{path}: image file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the image: {exc.strerror or exc}") from None

