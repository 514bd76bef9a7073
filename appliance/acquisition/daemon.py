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

Devices that do not answer when a session opens them (a PTU still powering up) put the daemon in a
degraded state instead of ending it: it tries again after :data:`RETRY_FIRST_S`, doubling the wait
up to :data:`RETRY_MAX_S`, says so in STATUS= at every attempt and on stderr (the journal) when the
fault starts, changes and ends, and the first session that runs again writes the fault into its
log.  A session that could not write its log is skipped with one line on stderr; a daemon whose
``max_sessions`` sessions all wrote nothing exits 1.
"""

from __future__ import annotations

import enum
import fcntl
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from appliance.acquisition import retention
from appliance.acquisition.notify import Notifier
from appliance.acquisition.session import SessionResult, earlier_faults
from appliance.config import Config, LogbookConfig
from appliance.errors import DeviceError, LogError, OutputError, ProtocolError

LOG = logging.getLogger(__name__)
#: the wait before the daemon opens devices that did not answer again (s); it doubles at every
#: failed attempt, up to :data:`RETRY_MAX_S`
RETRY_FIRST_S = 2.0
RETRY_MAX_S = 60.0

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
    logbook: LogbookConfig | None = None,
) -> SessionResult:
    """One session under the session lock, and the map's layers of its estimate written beside its log
    (:func:`write_session_layers`); with ``logbook``, its retention limits enforced before the session
    (room for its log, else :class:`appliance.acquisition.retention.NoRoomError`) and after."""
    with session_lock(log_dir):
        if logbook is not None:
            retention.make_room(log_dir, logbook)
        result = run_session(log_dir, should_stop, on_status)
        write_session_layers(result)
        if logbook is not None:
            retention.enforce(log_dir, logbook, open_log=result.log_path)
        return result


def write_session_layers(result: SessionResult) -> None:
    """The map's layers of ``result``'s estimate beside its log, named after it (none without an
    estimate, its database or a sealed log); a failure to write them is the result's
    ``layers_error`` and a problem, not the session's end: the log is what matters."""
    if result.estimate is None or result.database is None or result.log_error is not None:
        return
    # the writers (rasterio, matplotlib) load only once a session has estimated: the daemon starts without them
    from appliance.outputs.files import write_map_layers

    t = result.truth
    truth = None if t is None or t.lat_deg is None or t.lon_deg is None else (t.lat_deg, t.lon_deg)
    try:
        result.map_layers = write_map_layers(result.database, result.estimate, result.log_path.parent,
                                             result.log_path.stem, truth)
    except OutputError as exc:
        result.layers_error = str(exc)
        result.problems.append(f"map layers: {exc}")
        LOG.error("%s", exc)


class NoRoom(enum.Enum):
    """A session that did not start for want of room within the retention limits."""

    NO_ROOM = "no room"


NO_ROOM = NoRoom.NO_ROOM


@dataclass
class DeviceOutage:
    """Devices that did not answer when sessions opened them: since when (monotonic s), how many
    attempts failed, the last error and the wait before the next attempt."""

    since_s: float
    error: str
    wait_s: float
    attempts: int = 1

    def note(self, now_s: float) -> str:
        """The warning the first session after the outage writes into its log."""
        return (f"devices: did not answer for {now_s - self.since_s:.0f} s before this session "
                f"({self.attempts_text}); last: {self.error}")

    @property
    def attempts_text(self) -> str:
        return f"{self.attempts} failed attempt{'' if self.attempts == 1 else 's'}"


class SessionDaemon:
    """Runs ``run_session`` on the schedule of ``config.session`` (see the module's description);
    ``retry_s`` is the first and the longest wait before opening devices that did not answer again."""

    def __init__(
        self, config: Config, log_dir: Path, notifier: Notifier, run_session: SessionRunner,
        clock: Callable[[], float] = time.monotonic,
        retry_s: tuple[float, float] = (RETRY_FIRST_S, RETRY_MAX_S),
    ) -> None:
        self.config, self.log_dir, self.notifier = config, log_dir, notifier
        self.run_session = run_session
        self._stop = threading.Event()
        self._clock = clock
        self.retry_first_s, self.retry_max_s = retry_s
        self.results: list[SessionResult] = []
        self.outage: DeviceOutage | None = None
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
        self.notifier.notify(STATUS=" ".join(text.splitlines()), WATCHDOG=1)

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
        n = written = 0
        while not self._stop.is_set():
            outcome = self._session(n + 1)
            if outcome is NO_ROOM:  # not a session either: the next slot tries again
                self._wait(cfg.interval_s)
                continue
            if outcome is None:  # the devices did not answer: not a session, try again later
                self._wait(self.outage.wait_s if self.outage is not None else self.retry_first_s)
                continue
            n += 1
            written += outcome
            if cfg.max_sessions and n >= cfg.max_sessions:
                break
            self._wait(cfg.interval_s)
        self.notifier.stopping(status="stopping")
        if cfg.max_sessions and n >= cfg.max_sessions and not written:
            LOG.error("no session was written: all %d sessions failed to write their log", n)
            return 1
        return 0

    def _session(self, n: int) -> bool | None | NoRoom:
        """Session ``n``: whether it wrote a log; None when the devices did not answer, :data:`NO_ROOM`
        when the retention limits left no room for its log."""
        self._status(f"session {n} starting")
        notes = [] if self.outage is None else [self.outage.note(self._clock())]
        try:
            with earlier_faults(notes):
                result = run_one_session(self.run_session, self.log_dir, self._stop.is_set, self._status,
                                         self.config.logbook)
        except (DeviceError, ProtocolError) as exc:  # the procedures catch their own: opening the devices failed
            self._devices_down(exc)
            return None
        except retention.NoRoomError as exc:
            LOG.error("session %d not started: %s; trying again in %g s", n, exc, self.config.session.interval_s)
            self._status(f"session {n} not started: {exc}; next attempt in {self.config.session.interval_s:g} s")
            return NO_ROOM
        except LogError as exc:
            LOG.error("session %d skipped: %s", n, exc)
            self._status(f"session {n} skipped: {exc}")
            return False
        if self.outage is not None:
            LOG.info("devices answer again after %.0f s (%s); sessions resume",
                     self._clock() - self.outage.since_s, self.outage.attempts_text)
            self.outage = None
        self.results.append(result)
        if result.log_error is not None:
            LOG.error("session %d: %s", n, result.log_error)
        err = "n/a" if result.error_m is None else f"{result.error_m:.0f} m"
        clock = ""
        if result.clock_fault is not None:
            LOG.warning("session %d: %s", n, result.clock_fault)
            clock = f"; CLOCK OFF by {result.clock_offset_s:+.1f} s"
        self._status(
            f"session {n} {result.status.value} ({result.frames} frames, error {err}{clock}): {result.log_path.name}"
        )
        return True

    def _devices_down(self, exc: DeviceError | ProtocolError) -> None:
        """A failed attempt to open the devices: the degraded state's STATUS, a line on stderr when
        the fault starts or changes, and the wait before the next attempt."""
        error, o = str(exc), self.outage
        if o is None:
            o = self.outage = DeviceOutage(self._clock(), error, self.retry_first_s)
            LOG.warning("devices do not answer: %s; degraded, trying again after %g s, then up to every %g s",
                        error, o.wait_s, self.retry_max_s)
        else:
            o.attempts += 1
            o.wait_s = min(2.0 * o.wait_s, self.retry_max_s)
            if error != o.error:
                LOG.warning("devices still do not answer, now: %s", error)
            o.error = error
        self._status(f"degraded: devices do not answer ({error}); attempt {o.attempts} failed, "
                     f"next in {o.wait_s:g} s")
