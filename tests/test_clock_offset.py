"""The system clock against the GPS time: measured in every session from the receiver's RMC date and
time, written to /session/clock, and a session farther off than [logbook] max_clock_offset_s flagged
in its log and in the daemon's STATUS."""

from __future__ import annotations

import datetime as dt
import json
import threading

import pytest
from mcap.reader import make_reader

from appliance.acquisition.clock_check import check_clock
from appliance.acquisition.daemon import SessionDaemon
from appliance.cli._platform import session_runner
from appliance.config import load_config
from appliance.drivers.gps import GpsDecoder
from appliance.drivers.nmea_framer import RawSentence
from appliance.sim.nmea_twins import gps_epoch_sentences
from bench.soak import config_text, write_dem
from tests.test_retention import RecordingNotifier

T0 = dt.datetime(2026, 6, 1, 12, 0, 0, tzinfo=dt.timezone.utc)


def fixes_received(late_s: list[float]) -> list:
    """Fixes of one epoch a second from T0, each received ``late_s[i]`` seconds after its GPS time."""
    decoder = GpsDecoder()
    out = []
    for i, late in enumerate(late_s):
        t = T0 + dt.timedelta(seconds=i)
        receive_ns = round((t.timestamp() + late) * 1e9)
        for s in gps_epoch_sentences(t, 36.6, -84.25, 400.0, -30.0, 9, 0.9, 2.0):
            out += decoder.feed_one(RawSentence(s.decode().strip(), receive_ns))
    return out + decoder.flush()


@pytest.mark.parametrize(("late_s", "offset_s", "flagged", "words"), [
    ([3.9, 3.4, 3.6], 3.4, True, "3.4 s ahead of the GPS time"),
    ([-2.5, -2.2], -2.5, True, "2.5 s behind the GPS time"),
    ([0.7, 0.45, 0.9], 0.45, False, None),
])
def test_the_offset_is_the_least_difference_over_the_fixes(late_s, offset_s, flagged, words):
    fixes = fixes_received(late_s)
    assert len(fixes) == len(late_s) and all(f.utc is not None for f in fixes)
    c = check_clock(fixes, 2.0)
    assert c.offset_s == pytest.approx(offset_s, abs=1e-6) and c.fixes == len(late_s) and c.flagged is flagged
    fault = c.fault()
    assert (fault is None) if words is None else (words in fault and "max_clock_offset_s 2" in fault)


def test_no_fix_with_a_date_is_no_offset():
    c = check_clock([], 2.0)
    assert c.offset_s is None and not c.flagged and c.payload() == {
        "offset_s": None, "max_offset_s": 2.0, "fixes": 0, "flagged": False}


def test_a_session_whose_clock_is_off_is_flagged_in_its_log_and_status(tmp_path):
    dem = tmp_path / "dem.tif"
    write_dem(dem)
    # 20 times real time and 20 s of truth: a second of fixes, and a latency of 10 ms a fifth of a simulated second
    text = config_text(dem, tmp_path / "logs", 1, 0, camera=False, time_rate=20.0, truth_s=20.0)
    (tmp_path / "c.toml").write_text(text.replace("camera_unplug_after = 0\n",
                                                  "camera_unplug_after = 0\nclock_offset_s = 5.0\n"))
    config = load_config(tmp_path / "c.toml")
    notifier = RecordingNotifier()
    daemon = SessionDaemon(config, tmp_path / "logs", notifier, session_runner(config))
    rc: list[int] = []
    thread = threading.Thread(target=lambda: rc.append(daemon.run()))
    thread.start()
    thread.join(timeout=300)
    assert rc == [0] and len(daemon.results) == 1
    r = daemon.results[0]
    # the receiver's latency only adds to the offset
    assert r.clock_offset_s is not None and 5.0 <= r.clock_offset_s < 6.0
    assert r.clock_fault is not None and r.clock_fault in r.problems
    assert r.clock_fault.startswith(f"clock: the system clock is {r.clock_offset_s:.1f} s ahead of the GPS time")
    last = [s for s in notifier.statuses if s.startswith("session 1 ")][-1]
    assert f"CLOCK OFF by +{r.clock_offset_s:.1f} s" in last
    with open(r.log_path, "rb") as f:
        records = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/session/clock"])]
    assert len(records) == 1 and records[0]["flagged"] is True and records[0]["max_offset_s"] == 2.0
    assert records[0]["offset_s"] == pytest.approx(r.clock_offset_s) and records[0]["fixes"] >= 1
