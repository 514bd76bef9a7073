"""The unit files pass `systemd-analyze verify` without a single warning (where the tool exists)."""

from __future__ import annotations

import configparser
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from appliance.cli._forward import fixed_environment

UNITS = Path(__file__).resolve().parents[1] / "systemd"
INSTALLED_VIPER = "/usr/local/bin/viper"


def _analyze() -> str:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    return tool


def _staged(tmp_path: Path) -> list[Path]:
    """The units with ExecStart pointing at this checkout's `viper` (verify checks it is executable)."""
    viper = Path(sys.executable).with_name("viper")
    if not viper.exists():
        pytest.skip(f"{viper} is not installed (pip install -e .)")
    out = []
    for unit in sorted(UNITS.glob("viper-*.*")):
        if unit.suffix == ".conf":  # the drop-ins: tests/test_systemd_dropins.py
            continue
        staged = tmp_path / unit.name
        staged.write_text(unit.read_text().replace(INSTALLED_VIPER, str(viper)))
        out.append(staged)
    return out


def _verify(tool: str, units: list[Path]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [tool, "verify", *[f"./{u.name}" for u in units]],
        cwd=units[0].parent,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )


def test_units_verify_without_warnings(tmp_path):
    tool = _analyze()
    units = _staged(tmp_path)
    assert {u.name for u in units} == {
        "viper-session.service",
        "viper-capture.service",
        "viper-capture.timer",
        "viper-commands.socket",
        "viper-commands.service",
    }
    r = _verify(tool, units)
    assert r.returncode == 0 and r.stderr.strip() == "" and r.stdout.strip() == "", r.stderr


def test_verify_would_catch_a_bad_unit(tmp_path):
    tool = _analyze()
    bad = tmp_path / "viper-bad.service"
    bad.write_text("[Service]\nType=notify\nNoSuchOption=yes\nExecStart=/bin/true\n")
    r = _verify(tool, [bad])
    assert "NoSuchOption" in r.stderr


def _service(name: str) -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    cp.read_string(UNITS.joinpath(name).read_text())
    return cp


def test_session_service_is_hardened_notify_with_watchdog():
    svc = _service("viper-session.service")["Service"]
    assert svc["Type"] == "notify" and int(svc["WatchdogSec"]) > 0
    assert svc["User"] == "viper" and set(svc["SupplementaryGroups"].split()) == {"dialout", "video", "i2c"}
    assert svc["NoNewPrivileges"] == "yes" and svc["ProtectSystem"] == "strict" and svc["PrivateTmp"] == "yes"
    assert svc["ReadWritePaths"] == "/var/lib/viper" and svc["ExecStart"].startswith(
        INSTALLED_VIPER + " daemon"
    )
    timer = _service("viper-capture.timer")["Timer"]
    assert timer["Unit"] == "viper-capture.service" and timer["OnCalendar"]


def test_capture_unit_says_what_capture_does_when_a_session_runs(tmp_path, capsys):
    from appliance.acquisition.daemon import session_lock
    from appliance.cli.main import main

    text = UNITS.joinpath("viper-capture.service").read_text()
    assert "Waits for a running session" not in text
    assert "fails at once" in _service("viper-capture.service")["Unit"]["Description"]
    logs = tmp_path / "logs"
    logs.mkdir()
    with session_lock(logs):
        rc = main(["capture", "--log-dir", str(logs)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1
    assert err[-1] == f"viper capture: error: {logs}: another session is running (lock held)"
    assert sorted(p.name for p in logs.iterdir()) == [".session.lock"]


def test_units_give_numba_a_writable_cache_and_numba_uses_it(tmp_path):
    import os
    import subprocess
    import sys

    for name in ("viper-session.service", "viper-capture.service"):
        text = (UNITS / name).read_text()
        assert "CacheDirectory=viper\n" in text and "ProtectSystem=strict" in text
        env = [ln.split("=", 2) for ln in text.splitlines() if ln.startswith("Environment=NUMBA_CACHE_DIR=")]
        assert len(env) == 1 and env[0][2].startswith("/var/cache/viper/")  # inside the unit's CacheDirectory
    cache = tmp_path / "numba"
    code = ("import numpy as np\nfrom appliance.terrain.sweep import horizon_tan_grid\n"
            "horizon_tan_grid(np.zeros((8, 8)), 30.0, 30.0, 10.0, 1.5, 6.4e6)\n")
    subprocess.run([sys.executable, "-c", code], check=True, env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)))
    assert list(cache.rglob("*.nbi")), "numba wrote no cache index into NUMBA_CACHE_DIR"


def test_the_command_server_takes_its_socket_from_socket_activation(tmp_path):
    """`viper serve` as the commands' units start it: systemd opens the socket and passes it on the
    first connection (systemd-socket-activate does what the socket unit does)."""
    tool = shutil.which("systemd-socket-activate")
    if tool is None:
        pytest.skip("systemd-socket-activate is not installed (apt-get install systemd)")
    sock = tmp_path / "commands.sock"
    viper = [sys.executable, "-m", "appliance.cli.main"]
    env = dict(os.environ, VIPER_SOCKET="")
    # the variables a server must share with its clients, as a unit's Environment= lines would set them
    passed = [a for k in fixed_environment(env) for a in ("-E", k)]
    activator = subprocess.Popen([tool, "-l", str(sock), *passed, *viper, "--log-level", "debug", "serve"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    try:
        deadline = time.monotonic() + 30
        while not sock.exists():
            assert activator.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        render = ["render", "jacksboro", "--lat", "36.5521", "--lon", "-84.1911", "--azimuths", "36"]
        warm = subprocess.run([*viper, *render], capture_output=True, timeout=300,
                              env=dict(os.environ, VIPER_SOCKET=str(sock)))
        alone = subprocess.run([*viper, *render], capture_output=True, timeout=300, env=env)
        assert warm.returncode == alone.returncode == 0 and warm.stdout == alone.stdout
        assert len(warm.stdout.splitlines()) == 37
    finally:
        activator.send_signal(signal.SIGTERM)
        _, err = activator.communicate(timeout=30)
    log = err.decode()
    assert "serving estimate, locate, render, skyline" in log and "worker " in log and "viper render jacksboro" in log
