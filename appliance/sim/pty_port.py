"""A simulated serial device: a pseudo-terminal pair with a stable path that can be unplugged.

The driver opens :attr:`PtyPort.path`, a symlink (like ``/dev/serial/by-id/...``) to the pty's
slave side, with pyserial as it would a real port; the twin reads and writes the master side.
:meth:`unplug` closes the pair and removes the link (the driver's next read fails as on a USB
unplug); :meth:`replug` makes a new pair behind the same link.
"""

from __future__ import annotations

import os
import select
import threading
import tty
from pathlib import Path


class PtyPort:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self.replug()

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def replug(self) -> None:
        with self._lock:
            if self._master is not None:
                return
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)  # a full line drops bytes (receiver overrun), never blocks the twin
            self._master, self._slave = master, slave
            tmp = self.path.with_name(self.path.name + ".new")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(os.ttyname(slave), tmp)
            os.replace(tmp, self.path)

    def unplug(self) -> None:
        with self._lock:
            if self._master is None:
                return
            if self.path.is_symlink():
                self.path.unlink()
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None

    def write(self, data: bytes) -> None:
        """Send bytes to the driver; dropped while unplugged (as a receiver talking to no one) and
        when the driver has not read for so long that the line's buffer is full (an overrun)."""
        with self._lock:
            if self._master is None:
                return
            try:
                os.write(self._master, data)
            except OSError:
                pass

    def read(self, size: int, timeout_s: float) -> bytes:
        """Bytes the driver sent, waiting at most ``timeout_s``; b'' on timeout or while unplugged."""
        master = self._master
        if master is None:
            return b""
        try:
            ready, _, _ = select.select([master], [], [], timeout_s)
            if not ready:
                return b""
            return os.read(master, size)
        except (OSError, ValueError):
            return b""

    def close(self) -> None:
        self.unplug()
