"""The shipped drop-ins (a venv's ExecStart, network inputs) pass `systemd-analyze verify` applied to
the session unit, and say what they must; the units order themselves after time-sync.target without
pulling it in."""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNITS = Path(__file__).resolve().parents[1] / "systemd"
EXAMPLE_VENV_VIPER = "/opt/viper/venv/bin/viper"


def _analyze() -> str:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    return tool


def _venv_viper() -> Path:
    viper = Path(sys.executable).with_name("viper")
    if not viper.exists():
        pytest.skip(f"{viper} is not installed (pip install -e .)")
    return viper


def _verify_with_dropins(tmp_path: Path, unit: str, dropins: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """`systemd-analyze verify` of ``unit`` with ``dropins`` (name -> text) in its ``.d`` folder; the
    folder is on the unit path so that the drop-ins are read (verify reads a unit's drop-ins from there)."""
    (tmp_path / unit).write_text((UNITS / unit).read_text())
    d = tmp_path / f"{unit}.d"
    d.mkdir()
    for name, text in dropins.items():
        (d / name).write_text(text)
    env = dict(os.environ, SYSTEMD_UNIT_PATH=f"{tmp_path}:")
    return subprocess.run([_analyze(), "verify", f"./{unit}"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, check=False, timeout=120)


def test_the_venv_dropin_verifies_with_the_venv_path(tmp_path):
    viper = _venv_viper()
    text = (UNITS / "viper-venv.conf").read_text()
    assert f"ExecStart=\nExecStart={EXAMPLE_VENV_VIPER} daemon session" in text
    network = (UNITS / "viper-session-network.conf").read_text()
    r = _verify_with_dropins(tmp_path, "viper-session.service",
                             {"venv.conf": text.replace(EXAMPLE_VENV_VIPER, str(viper)), "network.conf": network})
    assert r.returncode == 0 and r.stderr.strip() == "" and r.stdout.strip() == "", r.stderr


def test_verify_reads_the_dropins(tmp_path):
    """The check above can fail: the drop-in as shipped names a venv that is not here, and verify says so."""
    _analyze()
    venv = (UNITS / "viper-venv.conf").read_text()
    r = _verify_with_dropins(tmp_path, "viper-session.service",
                             {"venv.conf": venv, "bad.conf": "[Service]\nNoSuchKey=1\n"})
    assert f"Command {EXAMPLE_VENV_VIPER} is not executable" in r.stderr and r.returncode != 0
    assert "bad.conf:2: Unknown key 'NoSuchKey'" in r.stderr


def _section(text: str, name: str) -> dict[str, list[str]]:
    """Every assignment of section ``name`` of a unit file (keys may repeat)."""
    out: dict[str, list[str]] = {}
    section = None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("["):
            section = line.strip("[]")
        elif line and not line.startswith("#") and section == name:
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


def test_the_network_dropin_opens_ip_to_the_configured_peers_only():
    unit = _section((UNITS / "viper-session.service").read_text(), "Service")
    net = _section((UNITS / "viper-session-network.conf").read_text(), "Service")
    assert unit["PrivateNetwork"] == ["yes"] and unit["RestrictAddressFamilies"] == ["AF_UNIX"]
    assert unit["IPAddressDeny"] == ["any"]
    assert net["PrivateNetwork"] == ["no"]
    assert set(net["RestrictAddressFamilies"][0].split()) == {"AF_UNIX", "AF_INET", "AF_INET6"}
    assert "IPAddressDeny" not in net  # the unit's deny-all stays; the peers are let through one by one
    assert net["IPAddressAllow"] == ["192.0.2.10", "192.0.2.20"]


@pytest.mark.parametrize("name", ["viper-session.service", "viper-capture.service"])
def test_units_order_after_time_sync_without_pulling_it_in(name):
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    cp.read_string((UNITS / name).read_text())
    assert "time-sync.target" in cp["Unit"]["After"].split()
    assert "time-sync.target" not in cp["Unit"].get("Wants", "").split()


def test_the_dropins_ship_as_package_data():
    text = (UNITS.parent / "pyproject.toml").read_text()
    assert '"appliance.systemd" = ["*.service", "*.timer", "*.socket", "*.conf"]' in text
    assert {"viper-venv.conf", "viper-session-network.conf"} <= {p.name for p in UNITS.glob("*.conf")}
