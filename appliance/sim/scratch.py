"""The simulated platform's private folder (``$TMPDIR/viper-sim-*``: the twins' pty links).

The folder holds ``.lock``, locked (``flock``) for as long as its platform is open: a folder whose
lock nobody holds belongs to a process that died without closing its platform (a kill, a crash),
and :func:`remove_stale_sim_folders` removes it the next time a platform opens.  The folder is also
removed at interpreter exit if its platform was never closed.
"""

from __future__ import annotations

import atexit
import fcntl
import functools
import os
import shutil
import tempfile
from pathlib import Path

from appliance.atomic import remove_if_unheld

PREFIX = "viper-sim-"
LOCK_NAME = ".lock"


class SimFolder:
    """A new private folder, locked until :meth:`remove`."""

    def __init__(self, parent: str | Path | None = None) -> None:
        remove_stale_sim_folders(parent)
        self.path = Path(tempfile.mkdtemp(prefix=PREFIX, dir=parent))
        self._fd: int | None = os.open(self.path / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        atexit.register(self.remove)

    def remove(self) -> None:
        """Remove the folder and everything in it (idempotent)."""
        shutil.rmtree(self.path, ignore_errors=True)
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)
            atexit.unregister(self.remove)


def remove_stale_sim_folders(parent: str | Path | None = None) -> list[Path]:
    """Remove the ``viper-sim-*`` folders of processes that are gone (their lock is free)."""
    base = Path(parent if parent is not None else tempfile.gettempdir())
    removed: list[Path] = []
    try:
        folders = sorted(base.glob(PREFIX + "*"))
    except OSError:
        return removed
    for folder in folders:
        # no lock: not a folder this module made, or one being made right now
        if remove_if_unheld(folder / LOCK_NAME, functools.partial(shutil.rmtree, folder, ignore_errors=True)):
            removed.append(folder)
    return removed
