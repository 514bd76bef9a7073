"""The soak of bench/soak.py, short: `viper daemon session` through 8 simulated sessions (no frames)
with the logs capped at 3 logs' worth."""

from __future__ import annotations

from bench.soak import log_size, report, run_soak


def test_eight_sessions_under_a_cap_of_three_logs(tmp_path):
    one_log = log_size(tmp_path, camera=False, sessions=1)
    cap = 3 * one_log
    s = run_soak(tmp_path, 8, cap, 5.0, camera=False)
    assert s.exit_code == 0 and [r.n for r in s.rows] == list(range(1, 9))
    # the cap holds at every session's end and in the 20 ms samples between
    assert max(r.logs_bytes for r in s.rows) <= cap and 0 < s.peak_bytes <= cap
    # room for the next log (its reserve and the largest log plus a tenth) leaves two logs beside it
    assert [r.logs for r in s.rows] == [1, 2, 2, 2, 2, 2, 2, 2]
    assert s.left == 2 and len(s.removed) == 6 and s.incomplete_left == []
    # every session's own log was there and complete when the session ended; none removed twice
    assert all(r.present for r in s.rows) and len(set(s.removed)) == 6
    assert not {r.name for r in s.rows[-2:]} & set(s.removed)
    # no leak: the last sessions hold no more fds or threads than the first.  A session's twins may still
    # be closing a port or ending a thread when its STATUS is read (one more, now and then), so the least
    # counts are compared: a leak raises every count after it
    assert min(r.fds for r in s.rows[4:]) <= min(r.fds for r in s.rows[1:4])
    assert min(r.threads for r in s.rows[4:]) <= min(r.threads for r in s.rows[1:4])
    text, ok = report(s, 8, 3, cap, one_log, "test")
    assert "| 0 incomplete logs left | yes |" in text and "| disk never above the cap" in text
