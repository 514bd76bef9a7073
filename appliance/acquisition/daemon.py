"""The session daemon: sessions on a schedule, systemd readiness and watchdog, a clean SIGTERM.

One process: the main thread notifies READY=1, then runs a session every ``session.interval_s``
seconds (the first at once), updating STATUS= as the session progresses; a heartbeat thread sends
WATCHDOG=1 every ``watchdog_margin`` x WatchdogSec as long as the session reported progress within
``session.step_timeout_s`` (a long step, such as building a database or the estimate, does not get
the daemon restarted; a session stuck for longer does).  SIGTERM (or SIGINT) sets a flag the
session checks between steps and between captures: the current log is closed with everything
captured, STOPPING=1 is sent and the daemon exits 0.  Sessions, from the daemon or from
``viper capture``, hold an exclusive lock in the log directory so two never drive the devices at
once.
"""

from __future__ import annotations

import fcntl
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

from appliance.acquisition.notify import Notifier
from appliance.acquisition.session import SessionResult
from appliance.config import Config
from appliance.errors import LogError

#: one session: (log folder, stop requested?, progress callback) -> its result; the command line
#: chooses it (hardware or simulated, :func:`appliance.cli._platform.session_runner`)
SessionRunner = Callable[[Path, Callable[[], bool], Callable[[str], None]], SessionResult]


@contextmanager
def session_lock(log_dir: Path) -> Iterator[None]:
    """Exclusive lock on ``log_dir/.session.lock``; raises LogError if another session holds it."""
    try:
        log_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(log_dir / ".session.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
    except OSError as exc:
        raise LogError(f"{log_dir}: cannot use the log directory: {exc.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise LogError(f"{log_dir}: another session is running (lock held)") from None
        yield
    finally:
        os.close(fd)


def run_one_session(
    run_session: SessionRunner,
    log_dir: Path,
    should_stop: Callable[[], bool] = lambda: False,
    on_status: Callable[[str], None] = lambda s: None,
) -> SessionResult:
    """One session under the session lock."""
    with session_lock(log_dir):
        return run_session(log_dir, should_stop, on_status)


class SessionDaemon:
    def __init__(
        self, config: Config, log_dir: Path, notifier: Notifier, run_session: SessionRunner,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config, self.log_dir, self.notifier = config, log_dir, notifier
        self.run_session = run_session
        self._stop = threading.Event()
        self._clock = clock
        self.results: list[SessionResult] = []
        self._progress_s = clock()

    def request_stop(self, signum: int | None = None, frame: FrameType | None = None) -> None:
        self._stop.set()

    def install_signal_handlers(self) -> None:
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)

    @property
    def watchdog_interval_s(self) -> float | None:
        """WATCHDOG=1 every ``session.watchdog_margin`` x WatchdogSec; None without a watchdog."""
        timeout_s = self.notifier.watchdog_s
        return None if timeout_s is None else self.config.session.watchdog_margin * timeout_s

    def _status(self, text: str) -> None:
        self._progress_s = self._clock()
        self.notifier.notify(STATUS=text, WATCHDOG=1)

    def feed_watchdog(self) -> bool:
        """WATCHDOG=1 if the session reported progress within ``session.step_timeout_s``; whether
        it was sent (a session silent for longer is left to systemd's watchdog)."""
        if self._clock() - self._progress_s <= self.config.session.step_timeout_s:
            self.notifier.watchdog()
            return True
        return False

    def _heartbeat(self, done: threading.Event) -> None:
        """:meth:`feed_watchdog` at the watchdog's pace until ``done``."""
        interval = self.watchdog_interval_s
        if interval is None:
            return
        while not done.wait(interval):
            self.feed_watchdog()

    def _wait(self, seconds: float) -> None:
        """Wait, pinging the watchdog; returns early on a stop request."""
        step = self.watchdog_interval_s or 5.0
        remaining = seconds
        while remaining > 0 and not self._stop.is_set():
            self._stop.wait(min(step, remaining))
            remaining -= step
            self._progress_s = self._clock()

    def run(self) -> int:
        cfg = self.config.session
        self.notifier.ready(status=f"ready; a session every {cfg.interval_s:.0f} s, logs in {self.log_dir}")
        self._progress_s = self._clock()
        done = threading.Event()
        beat = threading.Thread(target=self._heartbeat, args=(done,), name="watchdog", daemon=True)
        beat.start()
        try:
            return self._loop()
        finally:
            done.set()
            beat.join(timeout=5.0)

    def _loop(self) -> int:
        cfg = self.config.session
        n = 0
        while not self._stop.is_set():
            n += 1
            self._status(f"session {n} starting")
            try:
                result = run_one_session(self.run_session, self.log_dir, self._stop.is_set, self._status)
            except LogError as exc:
                self._status(f"session {n} skipped: {exc}")
            else:
                self.results.append(result)
                err = "n/a" if result.error_m is None else f"{result.error_m:.0f} m"
                self._status(
                    f"session {n} {result.status.value} ({result.frames} frames, error {err}): {result.log_path.name}"
                )
            if cfg.max_sessions and n >= cfg.max_sessions:
                break
            self._wait(cfg.interval_s)
        self.notifier.stopping(status="stopping")
        return 0
