"""The GPS and NMEA-compass twins over a real pty, read by the real drivers; faults injected."""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
import time
from fractions import Fraction
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


def uart_received(data: bytes, tx_baud: int, rx_baud: int) -> tuple[bytes, int]:
    """What a UART at ``rx_baud`` delivers when ``data`` is sent at ``tx_baud``, 8N1, frames back to back.

    The receiver waits, idle, for a falling edge (a start bit), checks the line is still low half a
    bit later, samples each of the 8 data bits and the stop bit at its middle (by its own clock), and
    is ready again at the middle of the stop bit.  A stop bit read as 0 is a framing error: the byte
    is delivered as NUL, as Linux delivers it on a port without IGNPAR or PARMRK.  Returns the bytes
    delivered and the number of framing errors.
    """
    bits = [1]  # the idle line before the first frame
    for byte in data:
        bits += [0, *((byte >> i) & 1 for i in range(8)), 1]

    def level(t: Fraction) -> int:
        k = int(t * tx_baud)
        return bits[k] if k < len(bits) else 1

    out, framing_errors, ready = bytearray(), 0, Fraction(0)
    for k in range(1, len(bits)):
        t0 = Fraction(k, tx_baud)
        if not (bits[k - 1] == 1 and bits[k] == 0 and t0 >= ready):
            continue
        samples = [level(t0 + Fraction(2 * j + 1, 2 * rx_baud)) for j in range(10)]
        ready = t0 + Fraction(19, 2 * rx_baud)
        if samples[0] != 0:
            continue  # a glitch, not a start bit
        if samples[9] == 1:
            out.append(sum(bit << i for i, bit in enumerate(samples[1:9])))
        else:
            out.append(0)
            framing_errors += 1
    return bytes(out), framing_errors


def test_wrong_baud_gives_no_fix_and_counts(tmp_path: Path) -> None:
    """A receiver sending NMEA 0183's 4800 baud to a port opened at 9600: every byte that arrives is
    counted as garbage, nothing is invented."""
    world = make_world()
    sent = b"".join(b"".join(gps_epoch_sentences(START + dt.timedelta(seconds=i), world.lat_deg, world.lon_deg,
                                                 world.alt_msl_m, world.geoid_separation_m, 9, 0.9, 2.0))
                    for i in range(5))
    assert uart_received(sent, 4800, 4800) == (sent, 0)  # the line model itself: same rates, same bytes
    received, framing_errors = uart_received(sent, 4800, 9600)
    # each bit read twice: every byte starts with a 0 bit and repeats bits in pairs, so no '$', no '!',
    # no line end, and a stop bit that lands on a 0 data bit (a framing error, delivered as NUL)
    assert not {ord("$"), ord("!"), ord("\r"), ord("\n")} & set(received)
    assert len(sent) < len(received) < 2 * len(sent)
    assert framing_errors == received.count(0) and framing_errors > len(sent) // 2

    port = PtyPort(tmp_path / "gps")
    reader = GpsReader(open_serial(str(port.path), 9600, 0.05), ErrorPolicy.LOG)
    port.write(received)
    fixes = collect(reader, 0.3)
    assert fixes == [] and reader.framer.flush(0) == []  # and what the framer still holds is no sentence
    port.close()
    assert reader.framer.stats.candidates == 0
    assert reader.counts() == {"garbage bytes": len(received), "binary segments": 0}


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
