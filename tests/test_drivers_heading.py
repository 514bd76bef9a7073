"""Heading/attitude sentences against gpsd's decodes (``ATT`` records in the ``.chk`` files) and
hand-checked values from logs without a ``.chk``.

gpsd's ``ATT`` after a TNT ``$PTNTHTM`` carries the raw device numbers (heading 14223); the log's
own header says "Can't be transmitting angles in degrees".  We compare our device-unit decode
(:func:`parse_tnt_htm`) with gpsd's, and convert to degrees only with an explicit scale.  The same
device's ``$HCXDR`` claims unit ``D`` for PITCH 171: gpsd reports pitch 171, we reject it (a pitch
beyond 90 deg is no pitch); that is the one place the test expects a refusal instead of agreement.
"""

from __future__ import annotations

import datetime as dt
import json

import pytest

from appliance.drivers.heading import (
    AttitudeReading,
    HeadingDecoder,
    HeadingReading,
    HeadingReference,
    declination,
    decode_heading_sentence,
    magnetic_to_true,
    parse_tnt_htm,
)
from appliance.drivers.nmea import split_checked
from appliance.drivers.nmea_framer import NmeaFramer, RawSentence
from appliance.drivers.policy import ErrorPolicy
from appliance.drivers.transport import LogReplay
from appliance.errors import InputError, ProtocolError
from tests.conftest import data_file

CHK_LOGS = ["pypilot", "rst39", "saab-r4", "skytraq-PX1172RH_DS", "hemi", "tnt-revolution"]


def chk_pairs(name: str) -> list[tuple[str, dict]]:
    """(sentence, ATT record) for every ATT gpsd printed right after a sentence."""
    out, last = [], None
    text = data_file(f"heading_attitude/{name}.log.chk").read_text(encoding="ascii", errors="replace")
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("$"):
            last = line
        elif line.startswith('{"class":"ATT"') and last is not None:
            out.append((last, json.loads(line)))
    return out


def ours(sentence: str) -> dict[str, float]:
    address, fields = split_checked(sentence)
    if address == "PTNTHTM":
        r = parse_tnt_htm(fields)
        return {k: v for k, v in (("heading", r.heading), ("pitch", r.pitch), ("roll", r.roll), ("dip", r.dip))
                if v is not None}
    got: dict[str, float] = {}
    try:
        readings = decode_heading_sentence(RawSentence(sentence, 0))
    except ProtocolError:
        # TNT's $HCXDR sends PITCH 171 with unit D: gpsd passes it on, we refuse a pitch > 90 deg
        assert address == "HCXDR" and name_of(sentence) == "PITCH"
        return {}
    for rd in readings:
        if isinstance(rd, HeadingReading) and rd.reference is HeadingReference.TRUE:
            got["heading"] = rd.heading_deg
        elif isinstance(rd, AttitudeReading):
            got.update({k: v for k, v in (("pitch", rd.pitch_deg), ("roll", rd.roll_deg)) if v is not None})
    return got


def name_of(sentence: str) -> str:
    return sentence.split(",")[4]


@pytest.mark.parametrize("name", CHK_LOGS)
def test_agrees_with_gpsd_att(name: str) -> None:
    compared = 0
    for sentence, att in chk_pairs(name):
        for key, value in ours(sentence).items():
            if key in att:
                assert value == pytest.approx(att[key], abs=1e-3), (name, sentence, key)
                compared += 1
    assert compared >= 1


def read_all(name: str, scale: float = 1.0) -> tuple[list, HeadingDecoder]:
    replay = LogReplay(data_file(f"heading_attitude/{name}.log"))
    framer = NmeaFramer()
    dec = HeadingDecoder(ErrorPolicy.SKIP, tnt_angle_scale_deg=scale)
    readings = dec.feed(framer.feed(replay.read(10**7), 0) + framer.flush(0))
    return readings, dec


def test_numeric_talkers_hdg_hdm() -> None:
    readings, _ = read_all("n2kd-183-merrimac")
    sources = {r.source for r in readings}
    assert {"24HDG", "04HDM"} <= sources
    hdg = next(r for r in readings if r.source == "24HDG")
    assert hdg.heading_deg == pytest.approx(182.1) and hdg.reference is HeadingReference.MAGNETIC
    assert hdg.variation_deg == pytest.approx(0.0)


def test_bundg_hdg_with_variation_and_xdr_heel_trim() -> None:
    readings, _ = read_all("bundg_zeus_9")
    hdg = next(r for r in readings if isinstance(r, HeadingReading))
    # $SDHDG,229.8,,,1.3,E
    assert hdg.heading_deg == pytest.approx(229.8) and hdg.variation_deg == pytest.approx(1.3)
    att = next(r for r in readings if isinstance(r, AttitudeReading))
    # $IIXDR,...,A,-1.0,D,HEEL,A,2.9,D,TRIM,...
    assert att.roll_deg == pytest.approx(-1.0) and att.pitch_deg == pytest.approx(2.9)


def test_hemi_empty_heading_is_no_reading() -> None:
    assert decode_heading_sentence(RawSentence("$GPHDT,,T*1B", 0)) == []


def test_tnt_default_scale_rejects_counts_but_scaled_values_are_plausible() -> None:
    _, dec = read_all("tnt-revolution")
    assert dec.errors.counts["malformed field"] >= 40  # 14223 is no heading in degrees
    readings, dec = read_all("tnt-revolution", scale=0.01)
    heads = [r.heading_deg for r in readings if isinstance(r, HeadingReading)]
    assert len(heads) == 50 and all(138.0 < h < 146.0 for h in heads)


def test_hdg_deviation_applied_and_bad_direction_rejected() -> None:
    body = "HCHDG,98.3,2.0,W,12.6,W"
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    (r,) = decode_heading_sentence(RawSentence(f"${body}*{cs:02X}", 7))
    assert r.heading_deg == pytest.approx(96.3) and r.variation_deg == pytest.approx(-12.6)
    assert r.receive_time_ns == 7
    with pytest.raises(ProtocolError, match="checksum"):
        decode_heading_sentence(RawSentence("$HCHDG,98.3,0.0,E,12.6,W*58", 0))


def test_wmm_declination_agrees_with_gpsd_magvar() -> None:
    """gpsd reports magvar 13.8 deg at the Quectel L70 fix (Calgary, 2022-03-09)."""
    when = dt.datetime(2022, 3, 9, 15, 1, 19, tzinfo=dt.timezone.utc)
    d = declination(51.068098, -114.095645, 1084.9, when)
    assert d.declination_deg == pytest.approx(13.8, abs=0.05)
    assert d.model == "WMM-2020"
    true, _ = magnetic_to_true(350.0, 51.068098, -114.095645, 1084.9, when)
    assert true == pytest.approx((350.0 + d.declination_deg) % 360.0)
    with pytest.raises(InputError):
        declination(0.0, 0.0, 0.0, dt.datetime(1990, 1, 1))
