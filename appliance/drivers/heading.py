"""Heading and attitude sentences: NMEA HDG, HDT, HDM, THS, XDR, Ashtech PASHR and TNT PTNTHTM.

Pure protocol layer: :func:`decode_heading_sentence` takes one framed sentence (text and receive
time) and returns typed readings; talker IDs are free (``HC``, ``HE``, ``AP``, numeric ``24``...).
Angles in degrees; heading clockwise from north (true or magnetic, as :class:`HeadingReference`
says); pitch positive bow/nose up, roll positive starboard/right side down (NMEA XDR convention).

Grammars (fields after the address):

=========  ====================================================================================
HDG        sensor heading, deviation, E/W, variation, E/W  -> magnetic heading (+ deviation, E+)
HDT        heading, ``T``                                    -> true heading
HDM        heading, ``M``                                    -> magnetic heading
THS        heading, mode (A autonomous, E estimated, M manual, S simulator, V invalid) -> true
XDR        repeated (type, value, unit, name); type ``A`` unit ``D`` with names PITCH/PTCH/TRIM
           (pitch) and ROLL/HEEL (roll)
PASHR      time, heading, ``T``, roll, pitch, ...           -> true heading + attitude
PTNTHTM    heading, status, pitch, status, roll, status, dip, field  (TNT Revolution compass);
           values in device units times ``tnt_angle_scale_deg`` (1.0 for a compass configured to
           send degrees; some send hundredths, scale 0.01).  Status ``N`` is normal; any other
           status letter (alarm) drops the value.
=========  ====================================================================================

Magnetic to true: :func:`magnetic_to_true` applies the World Magnetic Model (pygeomag) declination
at a position and date, and returns the model's name for the log.
"""

from __future__ import annotations

import datetime as dt
import enum
import functools
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from appliance.drivers import nmea
from appliance.drivers.nmea_framer import RawSentence
from appliance.drivers.policy import ErrorCounter, ErrorPolicy
from appliance.errors import InputError, ProtocolError

log = logging.getLogger(__name__)


class HeadingReference(enum.Enum):
    TRUE = "true"
    MAGNETIC = "magnetic"


@dataclass(frozen=True)
class HeadingReading:
    """A heading in degrees [0, 360) clockwise from true or magnetic north."""

    heading_deg: float
    reference: HeadingReference
    variation_deg: float | None  # magnetic variation (declination), east positive, if the device sent it
    source: str  # sentence address, e.g. "HCHDG"
    receive_time_ns: int


@dataclass(frozen=True)
class AttitudeReading:
    """Pitch and roll in degrees (either may be absent from one sentence, never invented)."""

    pitch_deg: float | None
    roll_deg: float | None
    source: str
    receive_time_ns: int


@dataclass(frozen=True)
class TntHtm:
    """TNT Revolution ``$PTNTHTM`` in device units, as sent (gpsd reports these raw values)."""

    heading: float | None
    heading_status: str
    pitch: float | None
    pitch_status: str
    roll: float | None
    roll_status: str
    dip: float | None
    field: float | None


Reading = HeadingReading | AttitudeReading

_PITCH_NAMES = frozenset({"PITCH", "PTCH", "TRIM"})
_ROLL_NAMES = frozenset({"ROLL", "HEEL"})
_THS_VALID = frozenset({"A", "E", "M"})


def _heading(text: str, what: str) -> float | None:
    v = nmea.opt_float(text, what)
    if v is not None and not 0.0 <= v <= 360.0:
        raise ProtocolError(f"{what}: {v} outside 0..360 deg")
    return None if v is None else v % 360.0


def _signed(value: str, direction: str, what: str) -> float | None:
    v = nmea.opt_float(value, what)
    if v is None:
        return None
    if direction not in ("E", "W"):
        raise ProtocolError(f"{what}: direction {direction!r} is neither E nor W")
    return -v if direction == "W" else v


def _angle(text: str, what: str, limit: float = 180.0) -> float | None:
    v = nmea.opt_float(text, what)
    if v is not None and abs(v) > limit:
        raise ProtocolError(f"{what}: {v} outside +-{limit} deg")
    return v


def _field(f: list[str], i: int) -> str:
    return f[i] if i < len(f) else ""


def _hdg(addr: str, f: list[str], t: int) -> list[Reading]:
    sensor = _heading(_field(f, 0), "HDG heading")
    if sensor is None:
        return []
    dev = _signed(_field(f, 1), _field(f, 2), "HDG deviation")
    var = _signed(_field(f, 3), _field(f, 4), "HDG variation")
    mag = (sensor + (dev or 0.0)) % 360.0
    return [HeadingReading(mag, HeadingReference.MAGNETIC, var, addr, t)]


def _hdt_hdm(ref: HeadingReference, letter: str) -> Callable[[str, list[str], int], list[Reading]]:
    def decode(addr: str, f: list[str], t: int) -> list[Reading]:
        h = _heading(_field(f, 0), f"{addr} heading")
        if h is None:
            return []
        if _field(f, 1) not in (letter, ""):
            raise ProtocolError(f"{addr}: reference {_field(f, 1)!r}, expected {letter!r}")
        return [HeadingReading(h, ref, None, addr, t)]

    return decode


def _ths(addr: str, f: list[str], t: int) -> list[Reading]:
    h = _heading(_field(f, 0), "THS heading")
    if h is None or _field(f, 1) not in _THS_VALID:
        return []
    return [HeadingReading(h, HeadingReference.TRUE, None, addr, t)]


def _xdr(addr: str, f: list[str], t: int) -> list[Reading]:
    pitch = roll = None
    for i in range(0, len(f) - 3, 4):
        kind, value, unit, name = f[i : i + 4]
        if kind != "A" or unit != "D":
            continue
        if name.upper() in _PITCH_NAMES:
            pitch = _angle(value, f"XDR {name}", 90.0)
        elif name.upper() in _ROLL_NAMES:
            roll = _angle(value, f"XDR {name}")
    if pitch is None and roll is None:
        return []
    return [AttitudeReading(pitch, roll, addr, t)]


def _pashr(addr: str, f: list[str], t: int) -> list[Reading]:
    out: list[Reading] = []
    h = _heading(_field(f, 1), "PASHR heading")
    if h is not None and _field(f, 2) == "T":
        out.append(HeadingReading(h, HeadingReference.TRUE, None, addr, t))
    roll = _angle(_field(f, 3), "PASHR roll")
    pitch = _angle(_field(f, 4), "PASHR pitch", 90.0)
    if pitch is not None or roll is not None:
        out.append(AttitudeReading(pitch, roll, addr, t))
    return out


def parse_tnt_htm(fields: list[str]) -> TntHtm:
    """Fields of ``$PTNTHTM`` (after the address) in device units."""
    if len(fields) < 8:
        raise ProtocolError(f"PTNTHTM: {len(fields)} fields, expected 8")
    num = [nmea.opt_float(fields[i], f"PTNTHTM field {i + 1}") for i in (0, 2, 4, 6, 7)]
    return TntHtm(num[0], fields[1], num[1], fields[3], num[2], fields[5], num[3], num[4])


def _tnt(scale_deg: float) -> Callable[[str, list[str], int], list[Reading]]:
    def decode(addr: str, f: list[str], t: int) -> list[Reading]:
        r = parse_tnt_htm(f)
        out: list[Reading] = []
        if r.heading is not None and r.heading_status == "N":
            h = r.heading * scale_deg
            if not 0.0 <= h <= 360.0:
                raise ProtocolError(f"PTNTHTM heading {r.heading} x {scale_deg} deg outside 0..360 deg")
            out.append(HeadingReading(h % 360.0, HeadingReference.MAGNETIC, None, addr, t))
        pitch = r.pitch * scale_deg if r.pitch is not None and r.pitch_status == "N" else None
        roll = r.roll * scale_deg if r.roll is not None and r.roll_status == "N" else None
        for v, what, lim in ((pitch, "pitch", 90.0), (roll, "roll", 180.0)):
            if v is not None and abs(v) > lim:
                raise ProtocolError(f"PTNTHTM {what} {v} deg outside +-{lim} deg")
        if pitch is not None or roll is not None:
            out.append(AttitudeReading(pitch, roll, addr, t))
        return out

    return decode


def _grammar(tnt_angle_scale_deg: float) -> dict[str, Callable[[str, list[str], int], list[Reading]]]:
    return {
        "HDG": _hdg,
        "HDT": _hdt_hdm(HeadingReference.TRUE, "T"),
        "HDM": _hdt_hdm(HeadingReference.MAGNETIC, "M"),
        "THS": _ths,
        "XDR": _xdr,
        "PASHR": _pashr,
        "PTNTHTM": _tnt(tnt_angle_scale_deg),
    }


def _type_of(address: str) -> str:
    return address if address.startswith("P") else address[2:]


def decode_heading_sentence(raw: RawSentence, tnt_angle_scale_deg: float = 1.0) -> list[Reading]:
    """Readings in one sentence; ``[]`` for other sentence types or empty fields (``$GPHDT,,T``)."""
    address, fields = nmea.split_checked(raw.text)
    decoder = _grammar(tnt_angle_scale_deg).get(_type_of(address))
    if decoder is None:
        return []
    return nmea.guarded(address, decoder, address, fields, raw.receive_time_ns)


class HeadingDecoder:
    """Framed sentences in, readings out; bad sentences counted and handled per the policy."""

    def __init__(self, policy: ErrorPolicy = ErrorPolicy.LOG, tnt_angle_scale_deg: float = 1.0) -> None:
        self.errors = ErrorCounter(policy, log)
        self._grammar = _grammar(tnt_angle_scale_deg)

    def feed(self, sentences: Iterable[RawSentence]) -> list[Reading]:
        out: list[Reading] = []
        for raw in sentences:
            try:
                address, fields = nmea.split_checked(raw.text)
            except ProtocolError as exc:
                self.errors.reject("bad checksum" if str(exc).startswith("checksum") else "malformed", exc)
                continue
            decoder = self._grammar.get(_type_of(address))
            if decoder is None:
                self.errors.count("other sentence")
                continue
            try:
                out.extend(nmea.guarded(address, decoder, address, fields, raw.receive_time_ns))
            except ProtocolError as exc:
                self.errors.reject("malformed field", exc)
        return out


# --- magnetic to true ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Declination:
    declination_deg: float  # east positive: true = magnetic + declination
    model: str  # e.g. "WMM-2025"


@functools.lru_cache(maxsize=8)
def _geomag(base_year: int):  # type: ignore[no-untyped-def]
    from pygeomag import GeoMag

    return GeoMag(base_year=base_year)


def declination(lat_deg: float, lon_deg: float, alt_m: float, when: dt.datetime) -> Declination:
    """WMM declination at a WGS84 position (altitude above the ellipsoid, m) and UTC time."""
    from pygeomag import decimal_year_from_date

    try:
        gm = _geomag(when.year)
        result = gm.calculate(glat=lat_deg, glon=lon_deg, alt=alt_m / 1000.0, time=decimal_year_from_date(when))
    except (ValueError, FileNotFoundError) as exc:
        raise InputError(f"no World Magnetic Model for {when.date()} at {lat_deg},{lon_deg}: {exc}") from None
    return Declination(float(result.d), str(gm.model))


def magnetic_to_true(
    heading_mag_deg: float, lat_deg: float, lon_deg: float, alt_m: float, when: dt.datetime
) -> tuple[float, Declination]:
    """True heading (deg) from a magnetic one by the WMM at the given position and time."""
    dec = declination(lat_deg, lon_deg, alt_m, when)
    log.info("magnetic to true by %s: declination %.3f deg at %.5f,%.5f", dec.model, dec.declination_deg,
             lat_deg, lon_deg)
    return (heading_mag_deg + dec.declination_deg) % 360.0, dec
