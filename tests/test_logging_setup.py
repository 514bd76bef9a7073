"""Logging: journal priorities under systemd, the plain message elsewhere, the global --log-level,
and the human times of ``viper log info``."""

from __future__ import annotations

import io
import logging
import os

import pytest

from appliance.cli.main import build_parser, command_of
from appliance.logbook.summary import utc_text
from appliance.logsetup import configure_logging, journal_priority


@pytest.fixture
def restore_logging():
    yield
    configure_logging("info")


def test_journal_priorities_follow_the_levels():
    assert [journal_priority(lv) for lv in (logging.CRITICAL, logging.ERROR, logging.WARNING, logging.INFO,
                                            logging.DEBUG)] == [3, 3, 4, 6, 7]


def test_lines_carry_their_priority_when_stderr_is_the_journal(tmp_path, restore_logging):
    with open(tmp_path / "journal", "w+") as stream:
        st = os.fstat(stream.fileno())
        configure_logging("info", stream, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        log = logging.getLogger("appliance.test")
        log.warning("compass: fit residual too large")
        log.info("session started")
        log.debug("hidden at info")
        log.error("two\nlines")
        stream.seek(0)
        assert stream.read().splitlines() == ["<4>compass: fit residual too large", "<6>session started",
                                              "<3>two", "<3>lines"]


def test_plain_lines_elsewhere_and_the_level_filters(restore_logging):
    stream = io.StringIO()
    configure_logging("warning", stream, {"JOURNAL_STREAM": "1:2"})
    log = logging.getLogger("appliance.test")
    log.info("quiet")
    log.warning("shown")
    assert stream.getvalue() == "shown\n"


def _parse(argv):
    return build_parser(command_of(argv)).parse_args(argv)


def test_log_level_is_a_global_option():
    args = _parse(["--log-level", "debug", "log", "info", "x.mcap"])
    assert args.log_level == "debug" and args.command == "log"
    assert _parse(["--log-level=warning", "log", "info", "x.mcap"]).log_level == "warning"
    assert _parse(["log", "info", "x.mcap"]).log_level == "info"
    with pytest.raises(SystemExit):
        _parse(["--log-level", "loud", "log", "info", "x.mcap"])


def test_the_command_is_found_after_the_log_level():
    assert command_of(["--log-level", "debug", "capture", "--seed", "3"]) == "capture"
    assert command_of(["--log-level=error", "estimate", "db", "a.csv"]) == "estimate"
    assert command_of(["--log-level", "info"]) is None


def test_log_times_are_utc_text():
    assert utc_text(1_780_315_205_250_000_000) == "2026-06-01T12:00:05.250Z"
    assert utc_text(0) == "1970-01-01T00:00:00.000Z"
