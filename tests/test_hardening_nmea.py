"""NMEA decoders under hostile input: only the project's own errors may escape.

Sentences from the real receiver and compass logs in shared/data are mutated (fields replaced with
hostile values, bytes flipped, inserted, deleted, the line cut) and, mostly, given a valid checksum
again so that the mutation reaches the field decoders.  Every sentence goes through the framer, the
GPS decoder and the heading decoder with the RAISE policy: a :class:`ProtocolError` (a ViperError)
is the only exception allowed.  With the LOG policy nothing escapes at all.  The long run (one
million inputs) is ``bench/nmea_fuzz.py``.
"""

from __future__ import annotations

import datetime as dt
import json
import logging

import pynmea2
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.drivers.gps import GpsDecoder, decode_gps_sentence
from appliance.drivers.heading import HeadingDecoder
from appliance.drivers.nmea import parse_sentence
from appliance.drivers.nmea_framer import NmeaFramer, RawSentence
from appliance.drivers.policy import ErrorPolicy
from appliance.errors import ProtocolError, ViperError
from tests.conftest import SHARED_DATA

HOSTILE_FIELDS = [
    "", "99999999999999999999", "999999999999999999999999999999", "-1", "nan", "NaN", "inf", "-inf",
    "1e999", "1_000", "0x1F", "+", "-", ".", "..", "1.2.3", " ", "00", "60", "99", "235960.99", "9999",
    "0000", "-0", "1e-400", "4916.4X", "A", "V", "N", "S", "\x7e", "12345678901234567890.12345",
]


def _logs(folder: str) -> list[str]:
    base = SHARED_DATA / folder
    if not base.is_dir():
        return []
    lines = []
    for p in sorted(base.glob("*.log")):
        for raw in p.read_bytes().splitlines():
            text = raw.decode("ascii", "replace").strip().lstrip("|")
            if text.startswith(("$", "!")) and "*" in text:
                lines.append(text)
    return lines


SENTENCES = _logs("nmea_gps") + _logs("heading_attitude")


def with_checksum(body: str) -> str:
    """``$BODY*HH`` with the checksum of ``BODY``."""
    return f"${body}*{pynmea2.NMEASentence.checksum(body):02X}"


def run_all(data: bytes, policy: ErrorPolicy) -> None:
    framer = NmeaFramer(strip_chars=b"|")
    gps = GpsDecoder(policy)
    heading = HeadingDecoder(policy)
    sentences = framer.feed(data, 1_700_000_000_000_000_000) + framer.flush(1_700_000_000_000_000_000)
    for s in sentences:
        gps.feed_one(s)
        heading.feed([s])
    gps.flush()


def require_data() -> None:
    if not SENTENCES:
        pytest.skip(f"real NMEA logs in {SHARED_DATA} are absent")


@st.composite
def mutated_sentence(draw: st.DrawFn) -> bytes:
    original = draw(st.sampled_from(SENTENCES))
    body = original[1:original.index("*")] if "*" in original else original[1:]
    fields = body.split(",")
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["field", "field", "byte", "insert", "delete", "cut", "dup"]))
        i = draw(st.integers(0, max(0, len(fields) - 1)))
        if kind == "field" and len(fields) > 1:
            fields[max(1, i)] = draw(st.sampled_from(HOSTILE_FIELDS) | st.text(
                alphabet=st.characters(min_codepoint=0x20, max_codepoint=0x7e, exclude_characters="*,$!"),
                max_size=12))
        elif kind == "byte" and fields[i]:
            j = draw(st.integers(0, len(fields[i]) - 1))
            fields[i] = fields[i][:j] + chr(draw(st.integers(0x20, 0x7e))) + fields[i][j + 1:]
        elif kind == "insert":
            fields.insert(i, draw(st.sampled_from(HOSTILE_FIELDS)))
        elif kind == "delete" and len(fields) > 1:
            del fields[max(1, i)]
        elif kind == "cut":
            fields = fields[: max(1, i)]
        elif kind == "dup":
            fields = fields + fields[1:]
    body = ",".join(fields).replace("*", "").replace("$", "").replace("!", "")
    if draw(st.booleans()) or draw(st.booleans()):
        text = with_checksum(body)
    else:
        text = "$" + body + draw(st.sampled_from(["", "*", "*0", "*ZZ", "*00"]))
    return text.encode("ascii", "replace") + draw(st.sampled_from([b"\r\n", b"\n", b"", b"\x00\r\n"]))


@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutated_sentence(), min_size=1, max_size=4))
def test_only_protocol_errors_escape_the_decoders(lines: list[bytes]) -> None:
    require_data()
    for line in lines:
        try:
            run_all(line, ErrorPolicy.RAISE)
        except ViperError as exc:
            assert isinstance(exc, ProtocolError), exc


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutated_sentence(), min_size=1, max_size=20))
def test_a_daemon_reader_survives_every_sentence(lines: list[bytes]) -> None:
    require_data()
    logging.disable(logging.WARNING)
    try:
        run_all(b"".join(lines), ErrorPolicy.SKIP)
    finally:
        logging.disable(logging.NOTSET)


def test_zda_with_a_twenty_digit_year_is_a_protocol_error() -> None:
    text = "$GPZDA,094933.00,20,08,99999999999999999999,00,00*68"
    msg = parse_sentence(text)
    with pytest.raises(ProtocolError, match="ZDA"):
        decode_gps_sentence(msg)
    gps = GpsDecoder(ErrorPolicy.SKIP)
    assert gps.feed_one(RawSentence(text, 0)) == []
    assert gps.errors.counts["malformed field"] == 1


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e999", "NaN", "1_0"])
def test_non_numbers_in_a_gga_are_refused_not_printed(value: str) -> None:
    """A receiver sending ``nan`` must never reach ``viper gps --json`` (NaN is not JSON)."""
    good = with_checksum("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
    bad = with_checksum(f"GPGGA,123520,4807.038,N,01131.000,E,1,08,{value},545.4,M,46.9,M,,")
    gps = GpsDecoder(ErrorPolicy.SKIP)
    fixes = gps.feed([RawSentence(good, 0), RawSentence(bad, 1)]) + gps.flush()
    assert [f.time_of_day for f in fixes] == [dt.time(12, 35, 19, tzinfo=dt.timezone.utc)]
    assert gps.errors.counts["malformed field"] == 1
    json.dumps(fixes[0].to_json_dict(), allow_nan=False)


def test_a_midnight_rollover_on_the_last_representable_day_is_no_crash() -> None:
    gps = GpsDecoder(ErrorPolicy.RAISE)
    lines = [with_checksum("GPZDA,235959.00,31,12,9999,00,00"),
             with_checksum("GPGGA,000001,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")]
    fixes = gps.feed([RawSentence(t, 0) for t in lines]) + gps.flush()
    assert len(fixes) == 1 and fixes[0].utc == dt.datetime(9999, 12, 31, 0, 0, 1, tzinfo=dt.timezone.utc)
