"""systemd's notification protocol (sd_notify) over ``$NOTIFY_SOCKET``, without a dependency.

A service of ``Type=notify`` sends newline-separated ``KEY=VALUE`` assignments in one datagram to
the AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace):
``READY=1`` once started, ``WATCHDOG=1`` at least every ``$WATCHDOG_USEC`` microseconds (we send
at half that), ``STATUS=...`` for ``systemctl status`` and ``STOPPING=1`` on the way out.  Outside
systemd (no ``$NOTIFY_SOCKET``) every call does nothing.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

from appliance.errors import DeviceError


class Notifier:
    """Sends notifications to systemd; ``address`` None disables it (not under systemd)."""

    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        self.address = address
        self.watchdog_usec = watchdog_usec
        self._sock: socket.socket | None = None

    @classmethod
    def from_environment(cls, env: Mapping[str, str] | None = None, pid: int | None = None) -> Notifier:
        """Read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` (read once, at the edge)."""
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET") or None
        watchdog_usec: int | None = None
        raw = env.get("WATCHDOG_USEC")
        if raw:
            try:
                watchdog_usec = int(raw)
            except ValueError:
                raise DeviceError(f"WATCHDOG_USEC: expected microseconds, got {raw!r}") from None
            wd_pid = env.get("WATCHDOG_PID")
            if wd_pid and int(wd_pid) != (os.getpid() if pid is None else pid):
                watchdog_usec = None  # the watchdog is meant for another process
        return cls(address, watchdog_usec)

    @property
    def enabled(self) -> bool:
        return self.address is not None

    @property
    def watchdog_s(self) -> float | None:
        """systemd's watchdog timeout (WatchdogSec, seconds), or None without watchdog."""
        return None if self.watchdog_usec is None else self.watchdog_usec / 1e6

    def notify(self, **fields: str | int) -> None:
        """Send ``KEY=VALUE`` lines, e.g. ``notify(READY=1, STATUS="idle")``."""
        if self.address is None:
            return
        lines = []
        for key, value in fields.items():
            text = str(value)
            if "\n" in text:
                raise DeviceError(f"sd_notify: {key} must be one line, got {text!r}")
            lines.append(f"{key}={text}")
        addr = self.address
        target = "\0" + addr[1:] if addr.startswith("@") else addr
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto("\n".join(lines).encode(), target)
        except OSError as exc:
            raise DeviceError(f"sd_notify: cannot send to {addr}: {exc.strerror or exc}") from None

    def ready(self, status: str | None = None) -> None:
        self.notify(READY=1, **({"STATUS": status} if status else {}))

    def watchdog(self) -> None:
        self.notify(WATCHDOG=1)

    def status(self, text: str) -> None:
        self.notify(STATUS=text)

    def stopping(self, status: str | None = None) -> None:
        self.notify(STOPPING=1, **({"STATUS": status} if status else {}))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
