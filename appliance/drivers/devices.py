"""Device objects with the interface the acquisition daemons use, the same on hardware and in sim.

Each wraps a protocol driver; every method may raise :class:`DeviceError` (unplugged, stalled,
stuck) and never returns an invented value.  Times are UTC nanoseconds.

* ``gps.poll() -> list[GpsFix]``: fixes completed since the last call (non-blocking beyond the
  port's read timeout; a lost receiver is reopened with back-off).
* ``tilt.read_tilt() -> TiltSample`` (``time_ns``, ``roll_deg``, ``pitch_deg``; roll positive
  right side down, pitch positive nose up), averaged and offset-corrected.
* ``compass.read_field() -> FieldSample`` (``time_ns``, ``x``, ``y``, ``z`` in tesla in the head's
  frame x forward, y right, z down), hard/soft-iron calibration applied (identity until fitted);
  ``compass.read_heading() -> HeadingSample`` (magnetic heading, tilt-compensated, and true heading
  by the WMM at the last GPS position when one is known).
* ``stage.move_to(angle_deg) -> float``: absolute pan angle (deg clockwise seen from above); returns
  the angle the stage reports when it stopped (a missed step shows as a difference, and is logged).
* ``camera.intrinsics`` and ``camera.capture() -> CameraFrame`` (``time_ns``, ``image`` BGR).
"""

from __future__ import annotations

import datetime as dt
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from appliance.drivers.accelerometer import Adxl345, TiltOffset
from appliance.drivers.attitude import tilt_compensated_heading
from appliance.drivers.gps import GpsFix
from appliance.drivers.heading import (
    AttitudeReading,
    HeadingDecoder,
    HeadingReading,
    HeadingReference,
    magnetic_to_true,
)
from appliance.drivers.magnetometer import HardSoftIron, Hmc5883l
from appliance.drivers.nmea_framer import NmeaFramer
from appliance.drivers.ptu import PanTiltUnit
from appliance.drivers.transport import ByteStream
from appliance.errors import DeviceError, InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TiltSample:
    time_ns: int
    roll_deg: float
    pitch_deg: float


@dataclass(frozen=True)
class FieldSample:
    """Magnetic field (tesla) in the head's frame: x forward, y right, z down."""

    time_ns: int
    x: float
    y: float
    z: float


@dataclass(frozen=True)
class HeadingSample:
    time_ns: int
    magnetic_deg: float
    true_deg: float | None  # None until a GPS position and date give the declination
    declination_deg: float | None
    model: str | None  # the magnetic model used, e.g. "WMM-2025"


class AccelTilt:
    def __init__(self, chip: Adxl345, samples: int = 16, offset: TiltOffset | None = None,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.chip, self.samples, self._clock_ns = chip, samples, clock_ns
        self.offset = offset or TiltOffset()

    def read_tilt(self) -> TiltSample:
        t = self.chip.read_tilt(self.samples, self.offset)
        return TiltSample(self._clock_ns(), t.roll_deg, t.pitch_deg)


class MagnetometerCompass:
    """HMC5883L + calibration; heading tilt-compensated by the inclinometer when one is given."""

    def __init__(self, chip: Hmc5883l, calibration: HardSoftIron | None = None, tilt: AccelTilt | None = None,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.chip, self.tilt, self._clock_ns = chip, tilt, clock_ns
        self.calibration = calibration or HardSoftIron()
        self.position: GpsFix | None = None  # set by the owner to enable true heading
        self._last_raw: tuple[float, float, float] | None = None
        self._repeats = 0

    def _read_flu(self) -> tuple[float, float, float]:
        raw = self.chip.read_tesla()
        self._repeats = self._repeats + 1 if raw == self._last_raw else 0
        self._last_raw = raw
        if self._repeats >= 3:
            log.warning("HMC5883L: %d identical readings %s (stuck)", self._repeats + 1, raw)
            raise DeviceError(f"HMC5883L: {self._repeats + 1} identical readings in a row, sensor stuck")
        return self.calibration.apply(raw)

    def read_field(self) -> FieldSample:
        x, y, z = self._read_flu()
        return FieldSample(self._clock_ns(), x, -y, -z)

    def read_heading(self) -> HeadingSample:
        m = self._read_flu()
        pitch = roll = 0.0
        if self.tilt is not None:
            t = self.tilt.read_tilt()
            pitch, roll = t.pitch_deg, t.roll_deg
        mag = tilt_compensated_heading(m, pitch, roll)
        return _with_true(self._clock_ns(), mag, self.position)


def _with_true(t_ns: int, mag: float, fix: GpsFix | None) -> HeadingSample:
    if fix is None or fix.utc is None:
        return HeadingSample(t_ns, mag, None, None, None)
    try:
        true, dec = magnetic_to_true(mag, fix.lat_deg, fix.lon_deg, fix.alt_ellipsoid_m or fix.alt_msl_m or 0.0,
                                     fix.utc)
    except InputError as exc:
        log.warning("no true heading: %s", exc)
        return HeadingSample(t_ns, mag, None, None, None)
    return HeadingSample(t_ns, mag, true, dec.declination_deg, dec.model)


class NmeaCompass:
    """An NMEA compass (HDG/HDM/HDT/PTNTHTM, XDR attitude) on a byte stream; keeps the latest values."""

    def __init__(self, stream: ByteStream, tnt_angle_scale_deg: float = 1.0,
                 clock_ns: Callable[[], int] = time.time_ns, max_age_s: float = 2.0) -> None:
        self.stream = stream
        self.framer = NmeaFramer()
        self.decoder = HeadingDecoder(tnt_angle_scale_deg=tnt_angle_scale_deg)
        self._clock_ns = clock_ns
        self.max_age_ns = int(max_age_s * 1e9)
        self.heading: HeadingReading | None = None
        self.attitude: AttitudeReading | None = None
        self.position: GpsFix | None = None

    def _pump(self) -> None:
        data = self.stream.read(512)
        for r in self.decoder.feed(self.framer.feed(data, self._clock_ns())):
            if isinstance(r, HeadingReading):
                self.heading = r
            elif r.pitch_deg is not None and r.roll_deg is not None:
                self.attitude = r

    def _fresh(self, t_ns: int | None) -> bool:
        return t_ns is not None and self._clock_ns() - t_ns <= self.max_age_ns

    def read_heading(self) -> HeadingSample:
        self._pump()
        h = self.heading
        if h is None or not self._fresh(h.receive_time_ns):
            raise DeviceError("NMEA compass: no heading within the last %.1f s" % (self.max_age_ns / 1e9))
        if h.reference is HeadingReference.TRUE:
            return HeadingSample(h.receive_time_ns, h.heading_deg, h.heading_deg, None, None)
        return _with_true(h.receive_time_ns, h.heading_deg, self.position)

    def read_tilt(self) -> TiltSample:
        self._pump()
        a = self.attitude
        if a is None or not self._fresh(a.receive_time_ns) or a.pitch_deg is None or a.roll_deg is None:
            raise DeviceError("NMEA compass: no pitch and roll within the last %.1f s" % (self.max_age_ns / 1e9))
        return TiltSample(a.receive_time_ns, a.roll_deg, a.pitch_deg)


class PtuStage:
    """The PTU's pan axis with angles in [0, 360) mapped onto the unit's signed range."""

    def __init__(self, unit: PanTiltUnit) -> None:
        self.unit = unit

    def move_to(self, angle_deg: float) -> float:
        signed = (angle_deg + 180.0) % 360.0 - 180.0
        return self.unit.move_to_deg(signed, strict=False) % 360.0


class SystemClock:
    def now_ns(self) -> int:
        return time.time_ns()

    def monotonic_s(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(seconds, 0.0))


def utc_from_ns(t_ns: int) -> dt.datetime:
    return dt.datetime.fromtimestamp(t_ns / 1e9, tz=dt.timezone.utc)
