"""The GPS and NMEA-compass twins over a real pty, read by the real drivers; faults injected."""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
import time
from pathlib import Path

import pytest

from appliance.config import SimConfig, SimFaultsConfig
from appliance.drivers.gps_reader import GpsReader, GpsSourceOptions, open_gps
from appliance.drivers.heading import AttitudeReading, HeadingDecoder, HeadingReading
from appliance.drivers.nmea_framer import NmeaFramer
from appliance.drivers.policy import ErrorPolicy
from appliance.drivers.transport import Backoff, open_serial
from appliance.sim.nmea_twins import GpsTwin, NmeaCompassTwin, gps_epoch_sentences
from appliance.sim.pty_port import PtyPort
from appliance.sim.world import SimClock, SimWorld

START = dt.datetime(2026, 6, 1, 12, 0, 0, tzinfo=dt.timezone.utc)
RATE = 20.0  # simulated seconds per real second: one epoch every 50 ms


def make_world() -> SimWorld:
    return SimWorld(36.6, -84.25, 500.0, heading_deg=30.0, tilt_north_deg=1.0, tilt_east_deg=-0.5,
                    clock=SimClock(START, RATE))


def collect(reader: GpsReader, real_s: float) -> list:
    out, end = [], time.monotonic() + real_s
    while time.monotonic() < end:
        out.extend(reader.poll())
    return out


def run_gps(tmp_path: Path, faults: SimFaultsConfig, real_s: float, sim: SimConfig | None = None):
    sim = sim or SimConfig(gps_sigma_m=2.0)
    world = make_world()
    port = PtyPort(tmp_path / "gps")
    twin = GpsTwin(world, port, sim, faults)
    reader = open_gps(str(port.path), GpsSourceOptions(read_timeout_s=0.02), ErrorPolicy.LOG,
                      Backoff(initial_s=0.02, maximum_s=0.1))
    twin.start()
    try:
        fixes = collect(reader, real_s)
    finally:
        twin.stop()
        reader.close()
        port.close()
    return world, twin, reader, fixes


def horizontal_error_m(world: SimWorld, lat: float, lon: float) -> float:
    dn = math.radians(lat - world.lat_deg) * 6_371_008.8
    de = math.radians(lon - world.lon_deg) * 6_371_008.8 * math.cos(math.radians(world.lat_deg))
    return math.hypot(dn, de)


def test_epoch_sentences_round_trip_through_the_decoder() -> None:
    from appliance.drivers.gps import GpsDecoder

    t = dt.datetime(2026, 6, 1, 23, 59, 59, 500000, tzinfo=dt.timezone.utc)
    data = b"".join(gps_epoch_sentences(t, -45.87766, 170.50013, 101.25, 7.5, 11, 0.8, 1.5))
    dec = GpsDecoder(ErrorPolicy.RAISE)
    fr = NmeaFramer()
    (fix,) = dec.feed(fr.feed(data, 0)) + dec.flush()
    assert fix.utc == t
    assert fix.lat_deg == pytest.approx(-45.87766, abs=1e-8) and fix.lon_deg == pytest.approx(170.50013, abs=1e-8)
    assert fix.alt_msl_m == pytest.approx(101.25) and fix.alt_ellipsoid_m == pytest.approx(108.75)
    assert fix.satellites == 11 and fix.hdop == pytest.approx(0.8)
    assert fix.sigma_m == pytest.approx(1.5, abs=0.02)


def test_gps_twin_over_pty(tmp_path: Path) -> None:
    world, twin, reader, fixes = run_gps(tmp_path, SimFaultsConfig(), 0.8)
    assert len(fixes) >= 5
    for f in fixes:
        assert horizontal_error_m(world, f.lat_deg, f.lon_deg) < 12.0  # 6 sigma of a 2 m receiver
        assert f.alt_msl_m == pytest.approx(501.5) and f.alt_ellipsoid_m == pytest.approx(471.5)
        assert START <= f.utc <= START + dt.timedelta(seconds=RATE * 2)
    assert reader.counts().get("bad checksum", 0) == 0


def test_gps_unplug_and_replug_resumes_with_warnings(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    faults = SimFaultsConfig(gps_unplug_at_s=4.0, gps_replug_after_s=6.0)
    with caplog.at_level(logging.WARNING):
        _, twin, reader, fixes = run_gps(tmp_path, faults, 1.5)
    assert twin.unplugged_at is not None
    assert reader.stream.reconnects >= 1  # type: ignore[attr-defined]
    before = [f for f in fixes if f.utc < twin.unplugged_at]
    after = [f for f in fixes if f.utc > twin.unplugged_at + dt.timedelta(seconds=6.0)]
    assert before and after
    assert "lost" in caplog.text and "reopened" in caplog.text


def test_gps_garbage_and_bad_checksums_are_counted_not_decoded(tmp_path: Path) -> None:
    faults = SimFaultsConfig(gps_garbage_rate=0.5, gps_bad_checksum_rate=0.3)
    world, _, reader, fixes = run_gps(tmp_path, faults, 1.0)
    counts = reader.counts()
    assert counts["bad checksum"] > 0 and counts["garbage bytes"] > 0
    assert fixes and all(horizontal_error_m(world, f.lat_deg, f.lon_deg) < 12.0 for f in fixes)


def test_gps_stuck_and_drift(tmp_path: Path) -> None:
    _, _, _, stuck = run_gps(tmp_path, SimFaultsConfig(gps_stuck_at_s=2.0), 0.8)
    late = [(f.lat_deg, f.lon_deg) for f in stuck if f.utc > START + dt.timedelta(seconds=3)]
    assert len(late) >= 3 and len(set(late)) == 1
    sim = SimConfig(gps_sigma_m=0.01)
    world, _, _, drift = run_gps(tmp_path, SimFaultsConfig(gps_drift_m_per_s=5.0), 0.8, sim)
    north_m = [math.radians(f.lat_deg - world.lat_deg) * 6_371_008.8 for f in drift]
    elapsed = [(f.utc - START).total_seconds() for f in drift]
    for n, e in zip(north_m, elapsed):
        assert n == pytest.approx(5.0 * e, abs=5.0 * 1.0 + 0.1)  # within one epoch of the drift


def test_wrong_baud_gives_no_fix_and_counts(tmp_path: Path) -> None:
    """Bytes at the wrong rate arrive as noise: they are counted, nothing is invented."""
    world = make_world()
    port = PtyPort(tmp_path / "gps")
    noise = bytes(((b * 37) ^ 0x5A) & 0xFF for b in b"".join(
        gps_epoch_sentences(START, 36.6, -84.25, 500.0, -30.0, 9, 0.9, 2.0)) * 5).replace(b"$", b"\x01")
    reader = GpsReader(open_serial(str(port.path), 9600, 0.05), ErrorPolicy.LOG)
    port.write(noise + b"\r\n")
    fixes = collect(reader, 0.3)
    port.close()
    assert fixes == [] and reader.counts()["garbage bytes"] > 0
    assert world.lat_deg == 36.6


def test_nmea_compass_twin(tmp_path: Path) -> None:
    world = make_world()
    port = PtyPort(tmp_path / "compass")
    twin = NmeaCompassTwin(world, port, rate_hz=50.0)
    stream = open_serial(str(port.path), 4800, 0.02)
    dec = HeadingDecoder(ErrorPolicy.RAISE)
    fr = NmeaFramer()
    twin.start()
    readings: list = []
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        readings += dec.feed(fr.feed(stream.read(256), 0))
    twin.stop()
    stream.close()
    port.close()
    heads = [r for r in readings if isinstance(r, HeadingReading)]
    atts = [r for r in readings if isinstance(r, AttitudeReading)]
    assert heads and atts
    true = (heads[-1].heading_deg + heads[-1].variation_deg) % 360.0
    assert true == pytest.approx(world.head_heading_deg, abs=0.15)
    pitch, roll = world.head_tilt()
    assert atts[-1].pitch_deg == pytest.approx(pitch, abs=0.01) and atts[-1].roll_deg == pytest.approx(roll, abs=0.01)


def test_sim_config_is_frozen() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        SimConfig().seed = 3  # type: ignore[misc]
