"""GPS receiver: NMEA 0183 GGA, RMC, GSA and GST decoded into typed records and grouped into fixes.

Pure protocol layer: :class:`GpsDecoder` is fed framed sentences (:class:`RawSentence`, text and
receive time) and returns :class:`GpsFix` records; it reads no clock and no port.

A fix is one completed *epoch*: the sentences a receiver sends for one measurement time (GGA, RMC
and GST carry the same UTC time of day; GSA, which has none, belongs to the epoch it follows).  An
epoch is complete when the sentence type that ended the previous epoch arrives again (the receiver's
cycle ender, learned as gpsd does), or when a sentence with another time of day starts the next
epoch, or at the end of the stream.  The date comes from RMC (or ZDA) of the same epoch, else the last
date seen, rolled over at midnight; without any date the fix has no ``utc`` (never an invented one).

Position covariance is built the ROS ``NavSatFix`` way, in the local East-North-Up frame (m^2):
from GST's 1-sigma latitude/longitude/altitude errors where the epoch has a GST ("diagonal known"),
else ``(hdop * error_m[quality])^2`` horizontally and ``(2 * hdop * error_m[quality])^2`` vertically
("approximated").  ``sigma_m`` is the horizontal radial RMS error, sqrt(var_east + var_north).
Altitudes: ``alt_msl_m`` is GGA's altitude above mean sea level (the receiver's geoid),
``alt_ellipsoid_m`` = ``alt_msl_m`` + geoid separation (height above the WGS84 ellipsoid).
"""

from __future__ import annotations

import datetime as dt
import enum
import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import pynmea2

from appliance.drivers import nmea
from appliance.drivers.nmea_framer import RawSentence
from appliance.drivers.policy import ErrorCounter, ErrorPolicy
from appliance.errors import ProtocolError

log = logging.getLogger(__name__)


class FixQuality(enum.IntEnum):
    """GGA fix quality indicator (NMEA 0183 field 6)."""

    INVALID = 0
    GPS = 1
    DGPS = 2
    PPS = 3
    RTK = 4
    FLOAT_RTK = 5
    ESTIMATED = 6
    MANUAL = 7
    SIMULATION = 8


class CovarianceType(enum.IntEnum):
    """As ``sensor_msgs/NavSatFix.position_covariance_type``."""

    UNKNOWN = 0
    APPROXIMATED = 1
    DIAGONAL_KNOWN = 2


#: RMC/GNS mode indicator (NMEA 2.3+) to fix quality, for epochs without GGA.
_RMC_MODE = {
    "A": FixQuality.GPS,
    "D": FixQuality.DGPS,
    "P": FixQuality.PPS,
    "R": FixQuality.RTK,
    "F": FixQuality.FLOAT_RTK,
    "E": FixQuality.ESTIMATED,
    "M": FixQuality.MANUAL,
    "S": FixQuality.SIMULATION,
}

#: Qualities whose position is not a measurement (a receiver in simulator mode invents it).
_NOT_A_FIX = frozenset({FixQuality.INVALID, FixQuality.SIMULATION})

#: Default 1-sigma horizontal error per unit HDOP, by fix quality (m); as nmea_navsat_driver.
DEFAULT_ERROR_BY_QUALITY_M: Mapping[FixQuality, float] = {
    FixQuality.GPS: 4.0,
    FixQuality.DGPS: 0.1,
    FixQuality.PPS: 4.0,
    FixQuality.RTK: 0.02,
    FixQuality.FLOAT_RTK: 4.0,
    FixQuality.ESTIMATED: 40.0,
    FixQuality.MANUAL: 4.0,
}


@dataclass(frozen=True)
class Gga:
    time: dt.time | None
    lat_deg: float | None
    lon_deg: float | None
    quality: FixQuality
    satellites: int | None
    hdop: float | None
    alt_msl_m: float | None
    geoid_separation_m: float | None


@dataclass(frozen=True)
class Rmc:
    time: dt.time | None
    valid: bool
    lat_deg: float | None
    lon_deg: float | None
    date: dt.date | None
    mode: str


@dataclass(frozen=True)
class Gsa:
    fix_dim: int | None
    pdop: float | None
    hdop: float | None
    vdop: float | None


@dataclass(frozen=True)
class Gst:
    time: dt.time | None
    rms_m: float | None
    sigma_lat_m: float | None
    sigma_lon_m: float | None
    sigma_alt_m: float | None


@dataclass(frozen=True)
class Zda:
    time: dt.time | None
    date: dt.date | None


GpsRecord = Gga | Rmc | Gsa | Gst | Zda


@dataclass(frozen=True)
class GpsFix:
    """One receiver epoch with a position.  Angles in degrees (WGS84), lengths in metres."""

    utc: dt.datetime | None
    time_of_day: dt.time
    lat_deg: float
    lon_deg: float
    alt_msl_m: float | None
    alt_ellipsoid_m: float | None
    quality: FixQuality
    satellites: int | None
    hdop: float | None
    covariance_enu_m2: tuple[float, ...] | None  # 3x3 row-major, East-North-Up
    covariance_type: CovarianceType
    receive_time_ns: int

    @property
    def sigma_m(self) -> float | None:
        """Horizontal radial RMS error sqrt(var_e + var_n) in metres, or ``None`` if unknown."""
        if self.covariance_enu_m2 is None:
            return None
        return float((self.covariance_enu_m2[0] + self.covariance_enu_m2[4]) ** 0.5)

    def to_json_dict(self) -> dict[str, object]:
        """The ``viper gps --json`` record."""
        return {
            "time": _iso(self.utc) if self.utc is not None else None,
            "lat": self.lat_deg,
            "lon": self.lon_deg,
            "alt_msl_m": self.alt_msl_m,
            "alt_ellipsoid_m": self.alt_ellipsoid_m,
            "quality": self.quality.name.lower(),
            "satellites": self.satellites,
            "hdop": self.hdop,
            "sigma_m": None if self.sigma_m is None else round(self.sigma_m, 4),
        }


def _iso(t: dt.datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


# --- sentence decoders (pynmea2 object -> typed record) -------------------------------------------


def _decode_gga(m: pynmea2.NMEASentence) -> Gga:
    q = nmea.opt_int(nmea.field(m, "gps_qual"), "GGA fix quality")
    if q is None:
        raise ProtocolError("GGA: empty fix quality")
    try:
        quality = FixQuality(q)
    except ValueError:
        raise ProtocolError(f"GGA: unknown fix quality {q}") from None
    return Gga(
        time=nmea.opt_time(nmea.field(m, "timestamp")),
        lat_deg=nmea.opt_latlon(nmea.field(m, "lat"), nmea.field(m, "lat_dir"), "latitude"),
        lon_deg=nmea.opt_latlon(nmea.field(m, "lon"), nmea.field(m, "lon_dir"), "longitude"),
        quality=quality,
        satellites=nmea.opt_int(nmea.field(m, "num_sats"), "GGA satellites"),
        hdop=nmea.opt_float(nmea.field(m, "horizontal_dil"), "GGA HDOP"),
        alt_msl_m=nmea.opt_float(nmea.field(m, "altitude"), "GGA altitude"),
        geoid_separation_m=nmea.opt_float(nmea.field(m, "geo_sep"), "GGA geoid separation"),
    )


def _decode_rmc(m: pynmea2.NMEASentence) -> Rmc:
    status = nmea.field(m, "status")
    if status not in ("A", "V"):
        raise ProtocolError(f"RMC: status {status!r} is neither A nor V")
    mode = nmea.raw(m, 11) if len(m.data) > 11 else ""
    return Rmc(
        time=nmea.opt_time(nmea.field(m, "timestamp")),
        valid=status == "A" and mode != "N",
        lat_deg=nmea.opt_latlon(nmea.field(m, "lat"), nmea.field(m, "lat_dir"), "latitude"),
        lon_deg=nmea.opt_latlon(nmea.field(m, "lon"), nmea.field(m, "lon_dir"), "longitude"),
        date=_lenient_date(nmea.field(m, "datestamp")),
        mode=mode,
    )


def _lenient_date(text: str) -> dt.date | None:
    """RMC date, or ``None`` for a malformed one (receivers after a week rollover send ``2208-1``)."""
    try:
        return nmea.opt_date_ddmmyy(text)
    except ProtocolError as exc:
        log.warning("RMC date dropped: %s", exc)
        return None


def _decode_gsa(m: pynmea2.NMEASentence) -> Gsa:
    return Gsa(
        fix_dim=nmea.opt_int(nmea.field(m, "mode_fix_type"), "GSA fix type"),
        pdop=nmea.opt_float(nmea.field(m, "pdop"), "GSA PDOP"),
        hdop=nmea.opt_float(nmea.field(m, "hdop"), "GSA HDOP"),
        vdop=nmea.opt_float(nmea.field(m, "vdop"), "GSA VDOP"),
    )


def _decode_gst(m: pynmea2.NMEASentence) -> Gst:
    return Gst(
        time=nmea.opt_time(nmea.field(m, "timestamp")),
        rms_m=nmea.opt_float(nmea.field(m, "rms"), "GST rms"),
        sigma_lat_m=nmea.opt_float(nmea.field(m, "std_dev_latitude"), "GST latitude sigma"),
        sigma_lon_m=nmea.opt_float(nmea.field(m, "std_dev_longitude"), "GST longitude sigma"),
        sigma_alt_m=nmea.opt_float(nmea.field(m, "std_dev_altitude"), "GST altitude sigma"),
    )


def _decode_zda(m: pynmea2.NMEASentence) -> Zda:
    t = nmea.opt_time(nmea.field(m, "timestamp"))
    d, mo, y = (nmea.opt_int(nmea.field(m, k), "ZDA date") for k in ("day", "month", "year"))
    date = None
    if d is not None and mo is not None and y is not None:
        try:
            date = dt.date(y, mo, d)
        except (ValueError, OverflowError):
            raise ProtocolError(f"ZDA: date out of range {y}-{mo}-{d}") from None
    return Zda(time=t, date=date)


_DECODERS: dict[str, Callable[[pynmea2.NMEASentence], GpsRecord]] = {
    "GGA": _decode_gga,
    "RMC": _decode_rmc,
    "GSA": _decode_gsa,
    "GST": _decode_gst,
    "ZDA": _decode_zda,
}


def decode_gps_sentence(msg: pynmea2.NMEASentence) -> GpsRecord | None:
    """Typed record of a GGA/RMC/GSA/GST/ZDA sentence from any talker; ``None`` for other types."""
    stype = nmea.sentence_type(msg)
    decoder = _DECODERS.get(stype)
    return nmea.guarded(stype, decoder, msg) if decoder is not None else None


# --- epoch assembly ----------------------------------------------------------------------------------


@dataclass
class _Epoch:
    time: dt.time
    receive_time_ns: int
    gga: Gga | None = None
    rmc: Rmc | None = None
    gsa: Gsa | None = None
    gst: Gst | None = None
    date: dt.date | None = None
    types: list[str] = field(default_factory=list)


@dataclass
class GpsStats:
    sentences: int = 0
    epochs: int = 0
    fixes: int = 0
    epochs_without_fix: int = 0


class GpsDecoder:
    """Framed sentences in, :class:`GpsFix` records out (see the module docstring for epochs)."""

    def __init__(
        self,
        policy: ErrorPolicy = ErrorPolicy.LOG,
        error_by_quality_m: Mapping[FixQuality, float] = DEFAULT_ERROR_BY_QUALITY_M,
    ) -> None:
        self.errors = ErrorCounter(policy, log)
        self.stats = GpsStats()
        self._error_by_quality_m = dict(error_by_quality_m)
        self._epoch: _Epoch | None = None
        self._emitted_time: dt.time | None = None
        self._cycle_ender: str | None = None
        self._last_date: dt.date | None = None
        self._last_time: dt.time | None = None

    def feed(self, sentences: Iterable[RawSentence]) -> list[GpsFix]:
        out: list[GpsFix] = []
        for s in sentences:
            out.extend(self.feed_one(s))
        return out

    def feed_one(self, raw: RawSentence) -> list[GpsFix]:
        try:
            msg = nmea.parse_sentence(raw.text)
        except ProtocolError as exc:
            reason = "bad checksum" if str(exc).startswith("checksum") else "unparsable sentence"
            if "unknown sentence type" in str(exc):
                self.errors.count("other sentence")
                return []
            self.errors.reject(reason, exc)
            return []
        try:
            rec = decode_gps_sentence(msg)
        except ProtocolError as exc:
            self.errors.reject("malformed field", exc)
            return []
        if rec is None:
            self.errors.count("other sentence")
            return []
        self.stats.sentences += 1
        try:
            return nmea.guarded("epoch", self._add, rec, nmea.sentence_type(msg), raw.receive_time_ns)
        except ProtocolError as exc:
            self.errors.reject("malformed field", exc)
            return []

    def flush(self) -> list[GpsFix]:
        """Emit the epoch in progress (end of stream)."""
        return self._close()

    def _add(self, rec: GpsRecord, stype: str, receive_time_ns: int) -> list[GpsFix]:
        out: list[GpsFix] = []
        t = None if isinstance(rec, Gsa) else rec.time
        if isinstance(rec, Zda):
            if rec.date is not None and t is not None:
                self._last_date, self._last_time = rec.date, t
            if self._epoch is not None and t == self._epoch.time:
                self._epoch.date = rec.date
            return out
        if t is None and not isinstance(rec, Gsa):
            return out  # a no-fix sentence without time (e.g. an empty RMC) opens no epoch
        if t is not None and (self._epoch is None or t != self._epoch.time):
            out.extend(self._close())
            if t == self._emitted_time:
                return out  # a late sentence of an epoch already emitted
            self._epoch = _Epoch(time=t, receive_time_ns=receive_time_ns)
        ep = self._epoch
        if ep is None:
            return out
        if isinstance(rec, Gga):
            ep.gga = rec
        elif isinstance(rec, Rmc):
            ep.rmc = rec
            if rec.date is not None:
                ep.date = rec.date
        elif isinstance(rec, Gsa):
            ep.gsa = rec
        elif isinstance(rec, Gst):
            ep.gst = rec
        ep.types.append(stype)
        if self._cycle_ender is not None and stype == self._cycle_ender:
            out.extend(self._close())
        return out

    def _close(self) -> list[GpsFix]:
        ep = self._epoch
        if ep is None:
            return []
        self._epoch = None
        self._emitted_time = ep.time
        self.stats.epochs += 1
        if ep.types:
            self._cycle_ender = ep.types[-1]
        date = self._epoch_date(ep)
        fix = self._make_fix(ep, date)
        if fix is None:
            self.stats.epochs_without_fix += 1
            return []
        self.stats.fixes += 1
        return [fix]

    def _epoch_date(self, ep: _Epoch) -> dt.date | None:
        date = ep.date
        if date is None and self._last_date is not None and self._last_time is not None:
            date = self._last_date
            if ep.time < self._last_time and date < dt.date.max:
                date = date + dt.timedelta(days=1)  # the carried date rolls over at midnight
        if date is not None:
            self._last_date, self._last_time = date, ep.time
        return date

    def _make_fix(self, ep: _Epoch, date: dt.date | None) -> GpsFix | None:
        gga, rmc = ep.gga, ep.rmc
        if (gga is not None and gga.quality in _NOT_A_FIX) or (rmc is not None and rmc.mode == "S"):
            return None
        if gga is not None and gga.lat_deg is not None:
            lat, lon, quality = gga.lat_deg, gga.lon_deg, gga.quality
        elif rmc is not None and rmc.valid and rmc.lat_deg is not None:
            lat, lon = rmc.lat_deg, rmc.lon_deg
            quality = _RMC_MODE.get(rmc.mode, FixQuality.GPS)
        else:
            return None
        if lon is None:
            return None
        satellites = gga.satellites if gga is not None else None
        hdop = gga.hdop if gga is not None and gga.hdop is not None else None
        if hdop is None and ep.gsa is not None:
            hdop = ep.gsa.hdop
        alt_msl = gga.alt_msl_m if gga is not None and gga.quality is not FixQuality.INVALID else None
        sep = gga.geoid_separation_m if gga is not None else None
        alt_ell = alt_msl + sep if alt_msl is not None and sep is not None else None
        cov, cov_type = self._covariance(ep.gst, hdop, quality)
        utc = dt.datetime.combine(date, ep.time) if date is not None else None
        return GpsFix(
            utc=utc,
            time_of_day=ep.time,
            lat_deg=lat,
            lon_deg=lon,
            alt_msl_m=alt_msl,
            alt_ellipsoid_m=alt_ell,
            quality=quality,
            satellites=satellites,
            hdop=hdop,
            covariance_enu_m2=cov,
            covariance_type=cov_type,
            receive_time_ns=ep.receive_time_ns,
        )

    def _covariance(
        self, gst: Gst | None, hdop: float | None, quality: FixQuality
    ) -> tuple[tuple[float, ...] | None, CovarianceType]:
        approx_h = approx_v = None
        if hdop is not None and quality in self._error_by_quality_m:
            approx_h = (hdop * self._error_by_quality_m[quality]) ** 2
            approx_v = (2.0 * hdop * self._error_by_quality_m[quality]) ** 2
        if gst is not None and gst.sigma_lat_m is not None and gst.sigma_lon_m is not None:
            up = gst.sigma_alt_m**2 if gst.sigma_alt_m is not None else approx_v
            if up is not None:
                return _diag(gst.sigma_lon_m**2, gst.sigma_lat_m**2, up), CovarianceType.DIAGONAL_KNOWN
        if approx_h is not None and approx_v is not None:
            return _diag(approx_h, approx_h, approx_v), CovarianceType.APPROXIMATED
        return None, CovarianceType.UNKNOWN


def _diag(e: float, n: float, u: float) -> tuple[float, ...]:
    return (e, 0.0, 0.0, 0.0, n, 0.0, 0.0, 0.0, u)
