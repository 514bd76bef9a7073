"""What a field user reads and gives: the 'ambiguous' status in the log summary, the detector's
confidence in the skyline CSV, and the platform's own body masked by stage angle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.acquisition.onboard import mask_stage_angles
from appliance.errors import InputError
from appliance.logbook.summary import LogSummary
from appliance.skyline import Skyline, format_skyline_csv, parse_skyline_csv


def _summary(estimate: dict | None) -> LogSummary:
    return LogSummary(path=Path("s.mcap"), size_bytes=1, complete=True, problem=None, topics={}, estimate=estimate,
                      truth=None)


def test_log_info_says_when_an_estimate_may_be_wrong():
    amb = _summary({"lat": 36.5, "lon": -84.2, "ambiguous": True, "region": {"n_cells": 312}})
    line = [x for x in amb.lines() if x.startswith("estimate:")][0]
    assert "ambiguous" in line and "312 cells" in line
    ok = _summary({"lat": 36.5, "lon": -84.2, "ambiguous": False, "region": {"n_cells": 3}})
    assert [x for x in ok.lines() if x.startswith("estimate:")][0].endswith("ok")
    old = _summary({"lat": 36.5, "lon": -84.2})  # a record without the flag: never "ok"
    assert [x for x in old.lines() if x.startswith("estimate:")][0].endswith("unknown")


def test_confidence_round_trips_through_the_csv():
    az = np.arange(0.0, 360.0, 45.0)
    el = np.array([1.0, np.nan, 2.5, 3.0, 0.5, -1.0, 4.0, 2.0])
    conf = np.array([1.0, 0.0, 0.6, 0.75, 0.5, 0.9, 1.0, 0.55])
    back = parse_skyline_csv(format_skyline_csv(Skyline(az, el, conf)))
    ok = np.isfinite(el)
    assert back.confidence is not None
    assert np.allclose(back.confidence[ok], conf[ok], atol=1e-3)
    assert np.array_equal(np.isnan(back.elevation_deg), ~ok)
    plain = parse_skyline_csv("azimuth_deg,elevation_deg\n0,1\n1,2\n")
    assert plain.confidence is None


@pytest.mark.parametrize("text,message", [
    ("azimuth_deg,elevation_deg,confidence\n0,1,1.5\n", "outside \\[0, 1\\]"),
    ("azimuth_deg,elevation_deg,confidence\n0,1,high\n", "not a number"),
    ("azimuth_deg,elevation_deg,confidence\n0,1\n", "expected 3 fields"),
])
def test_bad_confidence_is_a_one_line_error(text, message):
    with pytest.raises(InputError, match=message):
        parse_skyline_csv(text, "s.csv")


def test_the_platforms_own_mast_is_masked_by_stage_angle():
    az = np.arange(360.0)
    sky = Skyline(az, np.full(360, 2.0), np.ones(360))
    # platform heading 100 deg: stage 170..190 looks at true azimuths 270..290; 350..10 wraps to 90..110
    out = mask_stage_angles(sky, 100.0, [(170.0, 190.0), (350.0, 10.0)])
    hidden = np.isnan(out.elevation_deg)
    expect = ((az >= 270) & (az <= 290)) | ((az >= 90) & (az <= 110))
    assert np.array_equal(hidden, expect)
    assert out.confidence is not None and np.all(out.confidence[expect] == 0.0)
    assert mask_stage_angles(sky, 100.0, []) is sky
