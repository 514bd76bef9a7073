"""The rover's odometry line protocol: parsing good and bad lines (one-line errors), the decoder's error
policy, and the transports over a real pty and a real UDP socket."""

from __future__ import annotations

import socket
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.drivers.odometry import MAX_STOP_ID, OdometryDecoder, OdometryReport, checksum, format_line, parse_line
from appliance.drivers.odometry_reader import open_odometry
from appliance.errors import ConfigError, DeviceError, ErrorPolicy, ProtocolError
from appliance.sim.pty_port import PtyPort


def line(body: str, cs: str | None = None) -> str:
    return f"{body}*{checksum(body) if cs is None else cs}"


def test_the_documented_example_parses():
    r = parse_line("ODO,3,212.40,-87.05,15.00*4F\r\n", 123)
    assert r == OdometryReport(3, 212.40, -87.05, 15.0, 123)


@pytest.mark.parametrize("text", [
    line("ODO,1,0,0,0"),
    line("ODO,1,.5,-7.,3") + "\n",
    line("ODO,1,+10.25,-0.5,2.5") + "\r\n",
    line("ODO,12,10,20,1").lower().replace("odo", "ODO"),  # lower-case checksum digits
])
def test_good_lines(text):
    r = parse_line(text)
    assert r.stop_id >= 1 and r.sigma_m >= 0


@given(st.integers(1, MAX_STOP_ID), st.floats(-50_000, 50_000), st.floats(-50_000, 50_000), st.floats(0, 5_000))
def test_format_then_parse_is_the_report_to_the_centimetre(stop_id, east_m, north_m, sigma_m):
    r = parse_line(format_line(OdometryReport(stop_id, east_m, north_m, sigma_m)), 7)
    assert r.stop_id == stop_id and r.receive_time_ns == 7
    assert abs(r.east_m - east_m) <= 0.005 + 1e-9 and abs(r.north_m - north_m) <= 0.005 + 1e-9
    assert abs(r.sigma_m - sigma_m) <= 0.005 + 1e-9


@pytest.mark.parametrize("text,reason", [
    ("", "does not start with 'ODO,'"),
    ("$GPGGA,1,2*00", "does not start with 'ODO,'"),
    ("ODO,1,2,3,4", "no '*HH' checksum"),
    ("ODO,1,2,3,4*0", "no '*HH' checksum"),
    (line("ODO,1,2,3,4", "00"), "checksum 00 !="),
    (line("ODO,1,2,3"), "3 fields, expected 4"),
    (line("ODO,1,2,3,4,5"), "5 fields, expected 4"),
    (line("ODO,0,2,3,4"), "stop_id: expected an integer 1.."),
    (line("ODO,-1,2,3,4"), "stop_id"),
    (line("ODO,1.5,2,3,4"), "stop_id"),
    (line("ODO,99999999999,2,3,4"), "stop_id"),
    (line("ODO,1,nan,3,4"), "east_m: not a plain decimal"),
    (line("ODO,1,2,1e3,4"), "north_m: not a plain decimal"),
    (line("ODO,1,2, 3,4"), "north_m: not a plain decimal"),
    (line("ODO,1,2,3,"), "sigma_m: not a plain decimal"),
    (line("ODO,1,2,3,-4"), "sigma_m '-4': expected 0.."),
    (line("ODO,1,200000,3,4"), "more than 100000 m"),
    ("ODO,1," + "1" * 90 + "*00", "longer than 80 characters"),
    (b"ODO,1,2,3,\xff4*00", "not ASCII"),
])
def test_bad_lines_raise_one_line_naming_the_fault(text, reason):
    with pytest.raises(ProtocolError) as err:
        parse_line(text)
    message = str(err.value)
    assert reason in message and "\n" not in message


def test_decoder_frames_a_stream_and_drops_bad_lines_under_its_policy():
    d = OdometryDecoder(ErrorPolicy.SKIP)
    good1, good2 = format_line(OdometryReport(1, 10, 20, 3)), format_line(OdometryReport(2, -5, 0, 3))
    out = d.feed(b"\x00\xffnoise\n" + good1[:7], 1)
    out += d.feed(good1[7:] + line("ODO,2,1,1,1", "00").encode() + b"\r\n" + good2, 2)
    assert [r.stop_id for r in out] == [1, 2] and out[0].receive_time_ns == 2
    assert d.errors.counts["bad odometry line"] == 2
    d.feed(b"x" * 500, 3)  # no line end: discarded, never a value
    assert d.errors.counts["garbage bytes"] == 500 and d.feed(good1, 4)[0].stop_id == 1
    with pytest.raises(ProtocolError, match="checksum"):
        OdometryDecoder(ErrorPolicy.RAISE).feed(line("ODO,2,1,1,1", "00").encode() + b"\n", 0)


def _poll_until(reader, n, timeout_s=10.0):
    got, deadline = [], time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        got += reader.poll()
    return got


def test_serial_transport_over_a_real_pty(tmp_path):
    port = PtyPort(tmp_path / "odometry")
    reader = open_odometry(str(port.path), read_timeout_s=0.05, policy=ErrorPolicy.SKIP, clock_ns=lambda: 42)
    try:
        port.write(b"garbage\r\n" + format_line(OdometryReport(1, 250.0, -40.0, 30.0)))
        port.write(format_line(OdometryReport(2, -0.5, 12.25, 30.0))[:10])
        port.write(format_line(OdometryReport(2, -0.5, 12.25, 30.0))[10:])
        got = _poll_until(reader, 2)
        assert got == [OdometryReport(1, 250.0, -40.0, 30.0, 42), OdometryReport(2, -0.5, 12.25, 30.0, 42)]
        assert reader.counts()["bad odometry line"] == 1
    finally:
        reader.close()
        port.close()


def test_udp_transport_over_a_real_socket():
    reader = open_odometry("udp://127.0.0.1:0", read_timeout_s=0.05, policy=ErrorPolicy.SKIP, clock_ns=lambda: 9)
    try:
        assert reader.udp_port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"ODO,1,2,3,4*00", ("127.0.0.1", reader.udp_port))  # bad checksum: counted, dropped
            tx.sendto(format_line(OdometryReport(1, 300.0, 0.0, 20.0)), ("127.0.0.1", reader.udp_port))
            tx.sendto(format_line(OdometryReport(2, 0.0, -300.0, 20.0)).rstrip(), ("127.0.0.1", reader.udp_port))
            got = _poll_until(reader, 2)
        assert got == [OdometryReport(1, 300.0, 0.0, 20.0, 9), OdometryReport(2, 0.0, -300.0, 20.0, 9)]
        assert reader.counts()["bad odometry line"] == 1
        assert reader.poll() == []  # nothing more: waits at most the read timeout
    finally:
        reader.close()


def test_a_port_in_use_or_absent_is_a_device_error(tmp_path):
    first = open_odometry("udp://127.0.0.1:0")
    try:
        with pytest.raises(DeviceError, match="cannot listen"):
            open_odometry(f"udp://127.0.0.1:{first.udp_port}")
    finally:
        first.close()
    with pytest.raises(DeviceError, match="cannot open serial port"):
        open_odometry(str(tmp_path / "no-such-port"))


@pytest.mark.parametrize("text,key", [
    ('[devices.odometry]\nsource = "udp://localhost"\n', "devices.odometry.source"),
    ('[devices.odometry]\nsource = "udp://:70000"\n', "devices.odometry.source"),
    ("[devices.odometry]\nread_timeout_s = 0\n", "devices.odometry.read_timeout_s"),
    ("[traverse]\nstops = -1\n", "traverse.stops"),
    ("[traverse]\nodometry_timeout_s = 0\n", "traverse.odometry_timeout_s"),
    ("[sim]\nleg_length_m = [400.0, 200.0]\n", "sim.leg_length_m"),
    ("[sim]\nodometry_sigma_m = -1.0\n", "sim.odometry_sigma_m"),
])
def test_odometry_and_traverse_settings_are_checked_at_load(tmp_path, text, key):
    p = tmp_path / "v.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(p)
