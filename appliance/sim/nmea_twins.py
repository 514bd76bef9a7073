"""Serial NMEA twins: a GPS receiver and an NMEA compass speaking over a :class:`PtyPort`.

The GPS twin sends, once per simulated epoch, GGA + RMC + GSA + GST built from the world's true
position (plus the receiver's noise) and time.  The compass twin sends HDG (magnetic heading with
the WMM variation) and XDR pitch/roll.  Faults from :class:`SimFaultsConfig`: unplug and replug,
binary garbage, bad checksums, a stuck position, a drifting position.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import threading

import numpy as np

from appliance.config import SimConfig, SimFaultsConfig
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimWorld

log = logging.getLogger(__name__)


def checksum(body: str) -> str:
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    return f"{cs:02X}"


def sentence(body: str) -> bytes:
    return f"${body}*{checksum(body)}\r\n".encode("ascii")


def _lat(lat: float) -> tuple[str, str]:
    a = abs(lat)
    d = int(a)
    return f"{d:02d}{(a - d) * 60:010.7f}", "N" if lat >= 0 else "S"


def _lon(lon: float) -> tuple[str, str]:
    a = abs(lon)
    d = int(a)
    return f"{d:03d}{(a - d) * 60:010.7f}", "E" if lon >= 0 else "W"


def gps_epoch_sentences(
    t: dt.datetime, lat: float, lon: float, alt_msl_m: float, geoid_sep_m: float,
    satellites: int, hdop: float, sigma_m: float,
) -> list[bytes]:
    """GGA, RMC, GSA and GST of one epoch (pure)."""
    hms = t.strftime("%H%M%S") + f".{t.microsecond // 10000:02d}"
    la, ns = _lat(lat)
    lo, ew = _lon(lon)
    s = sigma_m / math.sqrt(2.0)
    return [
        sentence(f"GPGGA,{hms},{la},{ns},{lo},{ew},1,{satellites:02d},{hdop:.1f},{alt_msl_m:.2f},M,"
                 f"{geoid_sep_m:.2f},M,,"),
        sentence(f"GPRMC,{hms},A,{la},{ns},{lo},{ew},0.0,0.0,{t.strftime('%d%m%y')},,,A"),
        sentence("GPGSA,A,3,02,05,07,09,13,16,20,26,30,,,," + f"{hdop * 1.6:.1f},{hdop:.1f},{hdop * 1.3:.1f}"),
        sentence(f"GPGST,{hms},{sigma_m:.2f},{s * 1.2:.2f},{s * 0.8:.2f},30.0,{s:.2f},{s:.2f},{2 * s:.2f}"),
    ]


class _TwinThread:
    def __init__(self, name: str) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


class GpsTwin(_TwinThread):
    """A GPS receiver on a pty (``port.path``), sending epochs at ``sim.gps_rate_hz``."""

    def __init__(self, world: SimWorld, port: PtyPort, sim: SimConfig, faults: SimFaultsConfig) -> None:
        super().__init__("gps-twin")
        self.world, self.port, self.sim, self.faults = world, port, sim, faults
        self.rng = np.random.default_rng(sim.seed)
        self.epochs_sent = 0
        self._stuck: tuple[float, float] | None = None
        self.unplugged_at: dt.datetime | None = None

    def true_fix(self, elapsed_s: float) -> tuple[float, float]:
        """The position this epoch reports, faults included (before noise)."""
        north = self.faults.gps_drift_m_per_s * elapsed_s
        return self.world.offset_position(north, 0.0)

    def _run(self) -> None:
        period_real_s = 1.0 / (self.sim.gps_rate_hz * self.world.clock.time_rate)
        start = self.world.clock.now()
        replug_due: dt.datetime | None = None
        while not self._stop.wait(period_real_s):
            now = self.world.clock.now()
            elapsed = (now - start).total_seconds()
            f = self.faults
            if f.gps_unplug_at_s is not None and self.unplugged_at is None and elapsed >= f.gps_unplug_at_s:
                log.info("gps twin: unplugged at %.1f s", elapsed)
                self.port.unplug()
                self.unplugged_at = now
                replug_due = now + dt.timedelta(seconds=f.gps_replug_after_s)
            if replug_due is not None and now >= replug_due:
                log.info("gps twin: replugged at %.1f s", elapsed)
                self.port.replug()
                replug_due = None
            if not self.port.plugged:
                continue
            lat, lon = self.true_fix(elapsed)
            if f.gps_stuck_at_s is not None and elapsed >= f.gps_stuck_at_s:
                if self._stuck is None:
                    self._stuck = (lat, lon)
                lat, lon = self._stuck
            else:
                dn, de = self.rng.normal(0.0, self.sim.gps_sigma_m / math.sqrt(2.0), 2)
                lat, lon = lat + math.degrees(dn / 6_371_008.8), lon + math.degrees(
                    de / (6_371_008.8 * math.cos(math.radians(lat)))
                )
            out = b""
            gps_time = now - dt.timedelta(seconds=f.clock_offset_s)
            for s in gps_epoch_sentences(gps_time, lat, lon, self.world.alt_msl_m, self.world.geoid_separation_m,
                                         self.sim.gps_satellites, self.sim.gps_hdop, self.sim.gps_sigma_m):
                if self.rng.random() < f.gps_garbage_rate:
                    out += bytes(self.rng.integers(0, 256, 24, dtype=np.uint8).tolist()).replace(b"$", b"\x00")
                if self.rng.random() < f.gps_bad_checksum_rate:
                    s = s[:-4] + (b"00" if s[-4:-2] != b"00" else b"11") + b"\r\n"
                out += s
            self.port.write(out)
            self.epochs_sent += 1


class NmeaCompassTwin(_TwinThread):
    """An NMEA compass on a pty: HDG (magnetic, with variation) and XDR pitch/roll at 5 Hz."""

    def __init__(self, world: SimWorld, port: PtyPort, rate_hz: float = 5.0) -> None:
        super().__init__("compass-twin")
        self.world, self.port, self.rate_hz = world, port, rate_hz

    def _run(self) -> None:
        while not self._stop.wait(1.0 / self.rate_hz):
            w = self.world
            mag = (w.head_heading_deg - w.declination_deg) % 360.0
            var = w.declination_deg
            pitch, roll = w.head_tilt()
            self.port.write(
                sentence(f"HCHDG,{mag:.1f},0.0,E,{abs(var):.1f},{'E' if var >= 0 else 'W'}")
                + sentence(f"HCXDR,A,{pitch:.2f},D,PITCH,A,{roll:.2f},D,ROLL")
            )
