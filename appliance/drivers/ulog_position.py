"""A rover's own record of where it drove: PX4's local position from a ULog, and the displacements
between given times that a traverse's stops take as their odometry.

PX4 logs ``vehicle_local_position`` in its local frame (NED: ``x`` metres north, ``y`` metres east of
the origin, true north where the estimator knows the declination), with ``eph``, the standard
deviation of the horizontal position (m), ``xy_valid`` and ``xy_reset_counter``.  Times are
microseconds since the autopilot booted; the UTC of the boot comes from the GPS
(``vehicle_gps_position.time_utc_usec`` beside its ``timestamp``) or from the caller.

:func:`ulog_problem` walks the file's message headers (bytes in, no pyulog) and says where a cut or
damaged file ends inside a message: pyulog reads such a file silently up to the cut.
:func:`read_local_positions` reads a file into :class:`LocalPositions`; :func:`displacements` is
pure: positions and stop times in, one :class:`~appliance.drivers.odometry.OdometryReport` per leg out.
"""

from __future__ import annotations

import io
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.drivers.odometry import OdometryReport
from appliance.errors import InputError
from appliance.extras import require
from appliance.inputs import open_regular

#: the first seven bytes of every ULog file (then a version byte and the start time, uint64 us)
MAGIC = b"ULog\x01\x12\x35"
HEADER_BYTES = 16
TOPIC = "vehicle_local_position"
GPS_TOPIC = "vehicle_gps_position"


@dataclass(frozen=True)
class LocalPositions:
    """PX4's local position samples, in time order: ``time_us`` since boot, ``north_m`` (x) and
    ``east_m`` (y) in the local frame, ``eph_m`` the horizontal standard deviation, ``xy_valid`` and
    ``reset_counter`` (a change means the frame's origin moved).  ``boot_utc_us``: the UTC of the boot
    (us since the Unix epoch) when the log's GPS gives it, else None."""

    path: Path
    time_us: np.ndarray
    north_m: np.ndarray
    east_m: np.ndarray
    eph_m: np.ndarray
    xy_valid: np.ndarray
    reset_counter: np.ndarray
    boot_utc_us: int | None

    @property
    def span_us(self) -> tuple[int, int]:
        return int(self.time_us[0]), int(self.time_us[-1])


def ulog_problem(data: bytes) -> str | None:
    """Why ``data`` is not a whole ULog file (no ULog header; the last message cut short), or None.
    Each message is a uint16 payload size, a type byte and the payload: the sizes must lead exactly
    to the file's end."""
    if len(data) < HEADER_BYTES or data[:len(MAGIC)] != MAGIC:
        return "not a ULog file (no ULog header)"
    pos = HEADER_BYTES
    while pos + 3 <= len(data):
        (size,) = struct.unpack_from("<H", data, pos)
        if pos + 3 + size > len(data):
            return (f"its last message (at byte {pos}, {size} bytes) is cut at byte {len(data)}: "
                    "the file is truncated")
        pos += 3 + size
    if pos != len(data):
        return f"it ends inside a message header at byte {len(data)}: the file is truncated"
    return None


def read_local_positions(path: str | Path) -> LocalPositions:
    """The ``vehicle_local_position`` samples of the ULog file ``path``; a file that is not a whole
    ULog, or holds no local position, raises :class:`InputError` in one line."""
    try:
        with open_regular(path, "ULog") as fh:
            data = fh.read()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the ULog: {exc.strerror}") from None
    problem = ulog_problem(data)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    pyulog = require("pyulog", "reading a PX4 ULog (--odometry-log)")
    try:
        ulog = pyulog.ULog(io.BytesIO(data), [TOPIC, GPS_TOPIC])
    except (pyulog.core.ULogException, ValueError, struct.error, IndexError) as exc:
        raise InputError(f"{path}: unreadable ULog: {exc}") from None
    sets = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    lp = sets.get((TOPIC, 0))
    if lp is None or len(lp["timestamp"]) == 0:
        raise InputError(f"{path}: the ULog holds no {TOPIC} message")
    missing = [k for k in ("x", "y", "eph", "xy_valid", "xy_reset_counter") if k not in lp]
    if missing:
        raise InputError(f"{path}: {TOPIC} lacks the fields {', '.join(missing)}")
    t = np.asarray(lp["timestamp"], dtype=np.int64)
    order = np.argsort(t, kind="stable")
    return LocalPositions(
        Path(path), t[order], np.asarray(lp["x"], float)[order], np.asarray(lp["y"], float)[order],
        np.asarray(lp["eph"], float)[order], np.asarray(lp["xy_valid"]).astype(bool)[order],
        np.asarray(lp["xy_reset_counter"], dtype=np.int64)[order], _boot_utc_us(sets.get((GPS_TOPIC, 0))))


def _boot_utc_us(gps: dict[str, np.ndarray] | None) -> int | None:
    """The UTC of the boot (us) from the GPS's UTC beside its boot time, median over the fixes that
    have one; None without a GPS time."""
    if gps is None or "time_utc_usec" not in gps:
        return None
    utc = np.asarray(gps["time_utc_usec"], dtype=np.int64)
    ok = utc > 0
    if not ok.any():
        return None
    return int(np.median(utc[ok] - np.asarray(gps["timestamp"], dtype=np.int64)[ok]))


def position_at(pos: LocalPositions, time_us: int) -> tuple[float, float, float]:
    """(north_m, east_m, eph_m) at ``time_us`` since boot, linear between the two samples around it;
    a time outside the samples, or between samples not both valid or of different frames, raises
    :class:`InputError`."""
    t0, t1 = pos.span_us
    if not t0 <= time_us <= t1:
        raise InputError(f"{pos.path}: time {time_us / 1e6:.3f} s since boot lies outside its {TOPIC} "
                         f"samples ({t0 / 1e6:.3f} to {t1 / 1e6:.3f} s)")
    hi = int(np.searchsorted(pos.time_us, time_us, side="left"))
    lo = max(hi - 1, 0) if pos.time_us[hi] != time_us else hi
    if not (pos.xy_valid[lo] and pos.xy_valid[hi]):
        raise InputError(f"{pos.path}: {TOPIC} at {time_us / 1e6:.3f} s since boot is not valid (xy_valid false)")
    if pos.reset_counter[lo] != pos.reset_counter[hi]:
        raise InputError(f"{pos.path}: {TOPIC} was reset at {time_us / 1e6:.3f} s since boot")
    span = float(pos.time_us[hi] - pos.time_us[lo])
    w = 0.0 if span == 0.0 else (time_us - float(pos.time_us[lo])) / span

    def at(a: np.ndarray) -> float:
        return float(a[lo] + w * (a[hi] - a[lo]))

    return at(pos.north_m), at(pos.east_m), at(pos.eph_m)


def displacements(pos: LocalPositions, stop_times_ns: Sequence[int], boot_utc_ns: int) -> list[OdometryReport]:
    """The rover's displacement from each stop to the next, as the odometry line of the later stop
    (stop ids 1, 2, ...): the local positions at the stops' UTC times (ns; the log's clock), placed on
    the ULog's clock by ``boot_utc_ns``, the UTC of its boot.  ``sigma_m`` is the two positions' ``eph``
    in quadrature (their errors taken as independent, which never understates a leg's error); a leg
    across a reset of the local frame raises :class:`InputError`."""
    at = [(t, position_at(pos, (t - boot_utc_ns) // 1000)) for t in stop_times_ns]
    legs = []
    for k in range(1, len(at)):
        (ta, a), (tb, b) = at[k - 1], at[k]
        lo, hi = sorted(((ta - boot_utc_ns) // 1000, (tb - boot_utc_ns) // 1000))
        inside = pos.reset_counter[(pos.time_us >= lo) & (pos.time_us <= hi)]
        if inside.size and inside.min() != inside.max():
            raise InputError(f"{pos.path}: {TOPIC} was reset between stop {k - 1} and stop {k}: no displacement")
        legs.append(OdometryReport(k, b[1] - a[1], b[0] - a[0], math.hypot(a[2], b[2]), tb))
    return legs
