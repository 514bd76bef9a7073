"""The calibration scripts' CSV inputs: UTF-8 text, a fixed header, then rows."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from appliance.errors import InputError


def read_rows(data: bytes, source: str, header: tuple[str, ...]) -> list[list[str]]:
    """The rows after ``header`` (blank lines dropped); a wrong encoding or header is an InputError."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{source}: not UTF-8 text: {exc}") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{source}: empty file, expected the header {','.join(header)}")
    found = tuple(c.strip() for c in rows[0])
    if found != header:
        raise InputError(f"{source}: header is {','.join(found)!r}, expected {','.join(header)!r}")
    return rows[1:]


def read_input(path: str | Path) -> bytes:
    """A calibration input file's bytes; a missing or unreadable file is an InputError."""
    p = Path(path)
    try:
        return p.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{p}: file not found") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc.strerror or exc}") from None
