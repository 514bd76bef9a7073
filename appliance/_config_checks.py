"""The checks every configuration section's values pass, each raising a ConfigError that names the
key (its dotted name in the TOML file) and the value found."""

from __future__ import annotations

import enum
import math
import re
from typing import Any

from appliance.errors import ConfigError


def _require(ok: bool, key: str, expected: str, value: Any) -> None:
    """Raise a ConfigError naming ``key`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{key}: expected {expected}, got {value!r}")


def _positive(key: str, value: float) -> None:
    _require(math.isfinite(value) and value > 0, key, "a finite number > 0", value)


def _non_negative(key: str, value: float) -> None:
    _require(math.isfinite(value) and value >= 0, key, "a finite number >= 0", value)


def _within(key: str, value: float, lo: float, hi: float) -> None:
    _require(math.isfinite(value) and lo <= value <= hi, key, f"a number in [{lo:g}, {hi:g}]", value)


def _finite(key: str, value: float) -> None:
    _require(math.isfinite(value), key, "a finite number", value)


def _baud(key: str, value: int) -> None:
    _require(50 <= value <= 4_000_000, key, "a baud rate in [50, 4000000]", value)


UDP_SCHEME = "udp://"
_UDP = re.compile(r"udp://(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/\[\]]*)):(?P<port>\d{1,5})")


def udp_address(source: str, key: str) -> tuple[str, int]:
    """(host, port) of ``udp://HOST:PORT`` (``udp://:5600``: every IPv4 interface); raises naming ``key``."""
    m = _UDP.fullmatch(source)
    _require(m is not None and int(m.group("port")) <= 65535, key, "udp://HOST:PORT with a port in [0, 65535]",
             source)
    assert m is not None
    return m.group("v6") or m.group("host") or "0.0.0.0", int(m.group("port"))


def _choices(kind: type[enum.Enum]) -> str:
    names = [repr(m.value) for m in kind]
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"
