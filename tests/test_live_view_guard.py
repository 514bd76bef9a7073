"""What a live-view client sends never reaches the journal as it was sent: a real WebSocket client sends
line ends, escape sequences and 10 kB to the real ``viper daemon session --live``, whose stderr then
holds one printable, capped line per bad message; and the lines a flood of them causes are limited."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.logbook.live import SDK_LINE_CHARS, ClientTextGuard, printable

REPO = Path(__file__).resolve().parents[1]
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
HOSTILE = [
    json.dumps({"op": "evil\nFORGED journal line\x1b[31mred"}),
    json.dumps({"op": "A" * 10_000}),
    "not json\n\x1b[2J<6>FORGED",
]


def test_printable_escapes_everything_but_printable_ascii_and_caps_the_length():
    assert printable("a\r\nb\x1b[31m\x00\x7f\u00e9\u2028") == "a\\r\\nb\\x1b[31m\\x00\\x7f\\xe9\\u2028"
    assert printable("quote ' and \" stay") == "quote ' and \" stay"
    capped = printable("\n" * 10_000)
    assert capped == "\\n" * 40 + "... (10000 characters)"


async def _send_hostile(port: int) -> None:
    import websockets

    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:
        for message in HOSTILE:
            await ws.send(message)
        await asyncio.sleep(1.0)  # the server reads and logs them


def test_a_clients_messages_reach_stderr_as_one_printable_capped_line_each(tmp_path):
    cfg = tmp_path / "viper.toml"
    cfg.write_text('[platform]\nkind = "hardware"\n[session]\ninterval_s = 3600.0\n'
                   '[devices.compass]\nkind = "nmea"\n[devices.inclinometer]\nkind = "nmea"\n')
    proc = subprocess.Popen(
        [sys.executable, "-m", "appliance.cli.main", "daemon", "session", "--config", str(cfg), "--log-dir",
         str(tmp_path / "logs"), "--live", "127.0.0.1:0"],
        cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        first = proc.stderr.readline()
        assert first.startswith("live view: ws://127.0.0.1:"), first
        port = int(first.split()[2].rsplit(":", 1)[1])
        asyncio.run(_send_hostile(port))
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and out == ""
    assert "\x1b" not in err and "\r" not in err
    lines = err.splitlines()
    bad = [x for x in lines if x.startswith("live view: Invalid message from 127.0.0.1:")]
    assert len(bad) == len(HOSTILE), lines
    assert not [x for x in lines if "FORGED" in x and x not in bad]  # no line of the client's own
    assert "`evil\\nFORGED journal line\\x1b[31mred`" in bad[0]
    longest = len("live view: ") + SDK_LINE_CHARS + len("... (10000 characters)")
    assert all(len(x) <= longest for x in lines)
    assert bad[1].endswith(" characters)") and "A" * 100 in bad[1] and "A" * 200 not in bad[1]


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_flood_of_client_lines_is_limited_and_counted(caplog):
    clock = _Clock()
    guard = ClientTextGuard(per_window=3, window_s=10.0, clock=clock)
    sdk = logging.getLogger("foxglove.test-flood")
    sdk.propagate = False
    sdk.addHandler(guard)
    try:
        with caplog.at_level(logging.INFO, logger="appliance.logbook.live"):
            for i in range(5):
                sdk.error("Invalid message %d\n", i)
            clock.now = 10.5
            sdk.error("Invalid message %d\n", 5)
    finally:
        sdk.removeHandler(guard)
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.WARNING, "live view: Invalid message 0\\n"),
        (logging.WARNING, "live view: Invalid message 1\\n"),
        (logging.WARNING, "live view: Invalid message 2\\n"),
        (logging.WARNING, "live view: 2 more lines of the WebSocket server left out"),
        (logging.WARNING, "live view: Invalid message 5\\n"),
    ]


DROP_IN = REPO / "examples" / "viper-session-live.conf"


def test_the_live_drop_in_listens_on_localhost_only_and_verifies(tmp_path):
    active = [x for x in DROP_IN.read_text().splitlines() if x and not x.startswith("#")]
    assert "ExecStart=/usr/local/bin/viper daemon session --config /etc/viper/viper.toml --live 127.0.0.1:8765" \
        in active
    assert "IPAddressAllow=localhost" in active
    assert not [x for x in active if "0.0.0.0" in x or "IPAddressAllow=" in x and x != "IPAddressAllow=localhost"]
    tool, viper = shutil.which("systemd-analyze"), Path(sys.executable).with_name("viper")
    if tool is None or not viper.exists():
        pytest.skip("systemd-analyze or an installed viper is missing")
    (tmp_path / "viper-session.service.d").mkdir()
    for src, dst in ((REPO / "systemd" / "viper-session.service", "viper-session.service"),
                     (DROP_IN, "viper-session.service.d/live.conf")):
        (tmp_path / dst).write_text(src.read_text().replace("/usr/local/bin/viper", str(viper)))
    r = subprocess.run([tool, "verify", "viper-session.service"], cwd=tmp_path, capture_output=True, text=True,
                       env=dict(os.environ, SYSTEMD_UNIT_PATH=f"{tmp_path}:"), timeout=120, check=False)
    assert r.returncode == 0 and r.stdout.strip() == r.stderr.strip() == "", r.stderr
