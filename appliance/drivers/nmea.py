"""NMEA 0183 sentence parsing (checksums enforced) and strict field converters.

:func:`parse_sentence` wraps pynmea2 with the checksum required; the converters turn a field's
text into a value or ``None`` when the field is empty, and raise :class:`ProtocolError` on text that
is neither (never a silent 0 or NaN): numbers are plain decimals (no ``nan``, ``inf``, exponents or
underscores), of at most :data:`MAX_DIGITS` digits.  :func:`guarded` turns any other exception a
decoder raises into a :class:`ProtocolError`, so no sentence can raise anything else.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Callable
from typing import Any, TypeVar

import pynmea2

from appliance.errors import ProtocolError

_ADDRESS = re.compile(r"^[$!]([A-Z0-9]{2}[A-Z]{3}|P[A-Z0-9]{3,}),")
#: Longest number a field may hold (NMEA 0183 fields are at most a few tens of characters).
MAX_DIGITS = 20
_DECIMAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)")
_INTEGER = re.compile(r"[+-]?\d+")
_T = TypeVar("_T")

#: Exceptions a decoder may raise on hostile field text; :func:`guarded` maps them to ProtocolError.
FOREIGN_ERRORS = (ArithmeticError, ValueError, IndexError, KeyError, TypeError, AttributeError)


def guarded(what: str, decode: Callable[..., _T], *args: Any) -> _T:
    """``decode(*args)``; a foreign exception (a decoder's bug, an unforeseen field) as ProtocolError."""
    try:
        return decode(*args)
    except ProtocolError:
        raise
    except FOREIGN_ERRORS as exc:
        raise ProtocolError(f"{what}: undecodable ({type(exc).__name__}: {exc})") from None


def parse_sentence(text: str) -> pynmea2.NMEASentence:
    """Parse one sentence (``$...*HH``); a missing or wrong checksum raises :class:`ProtocolError`."""
    if not _ADDRESS.match(text):
        raise ProtocolError(f"not an NMEA sentence address: {text[:20]!r}")
    try:
        return pynmea2.parse(text, check=True)
    except pynmea2.ChecksumError as exc:
        detail = exc.args[0][0] if exc.args and isinstance(exc.args[0], tuple) else "does not match"
        raise ProtocolError(f"checksum: {detail}: {text[:40]!r}") from None
    except pynmea2.SentenceTypeError:
        raise ProtocolError(f"unknown sentence type: {text[:12]!r}") from None
    except pynmea2.ParseError:
        raise ProtocolError(f"malformed sentence: {text[:40]!r}") from None
    except FOREIGN_ERRORS as exc:
        raise ProtocolError(f"malformed sentence ({type(exc).__name__}): {text[:40]!r}") from None


def sentence_type(msg: pynmea2.NMEASentence) -> str:
    """The three-letter type (``GGA``) of a talker sentence, or ``P`` + maker (``PTNT``)."""
    st = getattr(msg, "sentence_type", None)
    if st:
        return str(st)
    return "P" + str(getattr(msg, "manufacturer", ""))


def talker(msg: pynmea2.NMEASentence) -> str:
    return str(getattr(msg, "talker", ""))


def field(msg: pynmea2.NMEASentence, name: str) -> str:
    """Raw text of the named field ('' when absent)."""
    i = type(msg).name_to_idx[name]
    return str(msg.data[i]).strip() if i < len(msg.data) else ""


def raw(msg: pynmea2.NMEASentence, index: int) -> str:
    return str(msg.data[index]).strip() if index < len(msg.data) else ""


def opt_float(text: str, what: str) -> float | None:
    """A plain decimal number (``-12.5``, ``.5``, ``7.``); ``None`` for an empty field."""
    if text == "":
        return None
    if len(text) > MAX_DIGITS + 2 or not _DECIMAL.fullmatch(text):
        raise ProtocolError(f"{what}: not a number: {text[:30]!r}")
    return float(text)


def opt_int(text: str, what: str) -> int | None:
    """A decimal integer of at most :data:`MAX_DIGITS` digits; ``None`` for an empty field."""
    if text == "":
        return None
    if len(text) > MAX_DIGITS + 1 or not _INTEGER.fullmatch(text):
        raise ProtocolError(f"{what}: not an integer: {text[:30]!r}")
    return int(text)


def opt_time(text: str) -> dt.time | None:
    """``hhmmss[.sss]`` UTC time of day (microsecond resolution)."""
    if text == "":
        return None
    m = re.fullmatch(r"(\d\d)(\d\d)(\d\d)(\.\d+)?", text)
    if not m:
        raise ProtocolError(f"time of day: malformed {text!r}")
    h, mi, s = int(m.group(1)), int(m.group(2)), int(m.group(3))
    us = round(float(m.group(4)[:8]) * 1e6) if m.group(4) else 0
    if h > 23 or mi > 59 or s > 60 or us >= 1_000_000:
        raise ProtocolError(f"time of day: out of range {text!r}")
    return dt.time(h, mi, min(s, 59), us, tzinfo=dt.timezone.utc)


def opt_date_ddmmyy(text: str) -> dt.date | None:
    """RMC date ``ddmmyy``; years 80-99 are 19xx, 00-79 are 20xx (as receivers and gpsd read them)."""
    if text == "":
        return None
    m = re.fullmatch(r"(\d\d)(\d\d)(\d\d)", text)
    if not m:
        raise ProtocolError(f"date: malformed {text!r}")
    yy = int(m.group(3))
    year = 1900 + yy if yy >= 80 else 2000 + yy
    try:
        return dt.date(year, int(m.group(2)), int(m.group(1)))
    except ValueError:
        raise ProtocolError(f"date: out of range {text!r}") from None


def opt_latlon(value: str, hemisphere: str, what: str) -> float | None:
    """``(d)ddmm.mmmm`` + ``N/S/E/W`` to signed decimal degrees; both empty gives ``None``."""
    if value == "" and hemisphere == "":
        return None
    m = re.fullmatch(r"(\d{1,3})(\d\d(?:\.\d*)?)", value)
    if not m or hemisphere not in ("N", "S", "E", "W"):
        raise ProtocolError(f"{what}: malformed {value!r},{hemisphere!r}")
    deg = int(m.group(1)) + float(m.group(2)) / 60.0
    limit = 90.0 if what == "latitude" else 180.0
    if float(m.group(2)) >= 60.0 or deg > limit:
        raise ProtocolError(f"{what}: out of range {value!r}")
    return -deg if hemisphere in ("S", "W") else deg


_SENTENCE = re.compile(
    r"^[$!](?P<address>[A-Z0-9]{2}[A-Z]{3}|P[A-Z0-9]{3,})(?P<data>(,[^*]*)?)\*(?P<cs>[0-9A-Fa-f]{2})$"
)


def split_checked(text: str) -> tuple[str, list[str]]:
    """Address (``HCHDG``, ``PTNTHTM``) and fields of one sentence, its checksum enforced.

    For sentence types pynmea2 does not know (``THS``, TNT's ``HTM``): the generic half of a
    decoder whose per-type grammar is a data table.
    """
    m = _SENTENCE.match(text)
    if not m:
        if "*" not in text:
            raise ProtocolError(f"checksum: missing: {text[:40]!r}")
        raise ProtocolError(f"malformed sentence: {text[:40]!r}")
    body = text[1 : text.index("*")]
    expected = pynmea2.NMEASentence.checksum(body)
    got = int(m.group("cs"), 16)
    if got != expected:
        raise ProtocolError(f"checksum: {got:02X} != {expected:02X}: {text[:40]!r}")
    data = m.group("data")
    return m.group("address"), [f.strip() for f in data[1:].split(",")] if data else []
