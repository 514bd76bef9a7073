"""Retention of the session logs: the oldest complete logs are removed so that the disk keeps
``[logbook] keep_free_bytes`` free and the logs take at most ``[logbook] max_total_bytes``.

What counts: the session logs of the log folder (``viper-*.mcap``), the reserve files beside the
logs being written (``.viper-*.mcap.reserve``) and each log's companions: the map's layers a session
writes beside its log (``LOG-posterior.tif`` and the others of
:data:`appliance.outputs.styles.MAP_LAYER_SUFFIXES`) and its replayed marker.  Other files there (a
skyline database, the lock) are neither counted nor removed.  Sizes are the files' lengths; free
space is what ``statvfs`` gives an unprivileged writer (``f_bavail``).

What may be removed: a *complete* log (it ends with the MCAP magic: sealed, footer written), oldest
first by its modification time (the simulated platform's clock names logs by a simulated time, so
names do not order them), never the log a session has open (it has no footer yet, and the caller
names it), never a log cut short by a power cut (``viper log recover`` needs it), and with
``[logbook] keep_unreplayed = true`` never a log that was not replayed.  A log is *replayed* when a
marker ``LOG.mcap.replayed`` stands beside it: ``viper replay`` writes it after it has written the
log's results; an operator who copied the logs elsewhere may ``touch`` it.  Its companions go with a
removed log.

Before a session the daemon makes room for one more log (:func:`make_room`): the limits must still
hold once the next log is written, its size taken from the largest of the newest complete logs (or
the configuration's least log, :attr:`LogbookConfig.least_log_bytes`, before the first); when that
room cannot be made, :class:`NoRoomError` says why and the session does not start.  After a session
the limits are enforced as they stand (:func:`enforce`).  Every removal is one line on stderr.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from appliance.atomic import write_text_atomic
from appliance.config import LogbookConfig
from appliance.errors import ConfigError, LogError, OutputError
from appliance.outputs.styles import MAP_LAYER_SUFFIXES

LOG = logging.getLogger(__name__)

LOG_GLOB = "viper-*.mcap"
RESERVE_GLOB = ".viper-*.mcap.reserve"
REPLAYED_SUFFIX = ".replayed"
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: how many of the newest complete logs give the size of the next one, and the margin added to it
NEWEST_LOGS = 5
SIZE_MARGIN = 0.1


class NoRoomError(LogError):
    """No room for the next log within the retention limits, even after removing what may be removed."""


@dataclass(frozen=True)
class LogFile:
    """A session log of the folder: its size (bytes), modification time (ns) and state."""

    path: Path
    size_bytes: int
    mtime_ns: int
    complete: bool
    replayed: bool


@dataclass
class Retention:
    """What one pass did: the logs removed, and whether the limits hold after it."""

    removed: list[LogFile] = field(default_factory=list)
    holds: bool = True
    free_bytes: int = 0
    total_bytes: int = 0
    reason: str = ""


def replayed_marker(log: Path) -> Path:
    """The marker that says ``log`` was replayed: ``LOG.mcap.replayed`` beside it."""
    return log.with_name(log.name + REPLAYED_SUFFIX)


def mark_replayed(log: Path, note: str) -> None:
    """Write the replayed marker of ``log`` (``note``: where the results went)."""
    write_text_atomic(replayed_marker(log), note.rstrip("\n") + "\n")


def mark_replayed_into(log: Path, out: Path) -> None:
    """After a replay into ``out``: ``log``'s replayed marker (retention's ``keep_unreplayed`` may now
    remove it), or a warning that it could not be written; the replay's results stand either way."""
    try:
        mark_replayed(log, f"replayed into {out.absolute()}")
    except OutputError as exc:
        LOG.warning("%s: not marked replayed: %s", log, exc)


def companions(log: Path) -> list[Path]:
    """The files that belong to ``log`` and go with it: its map's layers and its replayed marker
    (those that may exist; :func:`_size` reads 0 for one that does not)."""
    return [log.with_name(log.stem + suffix) for suffix in MAP_LAYER_SUFFIXES] + [replayed_marker(log)]


def _size(path: Path) -> int:
    """``path``'s length in bytes, 0 when it is not there."""
    try:
        return path.stat().st_size
    except OSError:
        return 0


def is_complete(path: Path) -> bool:
    """Whether ``path`` starts and ends with the MCAP magic (a sealed log with its footer)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
            f.seek(0, os.SEEK_END)
            if f.tell() < 2 * len(MCAP_MAGIC):
                return False
            f.seek(-len(MCAP_MAGIC), os.SEEK_END)
            return head == MCAP_MAGIC and f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def session_logs(log_dir: Path) -> list[LogFile]:
    """The session logs of ``log_dir``, oldest first (modification time, then name)."""
    logs = []
    for p in Path(log_dir).glob(LOG_GLOB):
        try:
            st = p.stat()
        except OSError:  # removed meanwhile
            continue
        logs.append(LogFile(p, st.st_size, st.st_mtime_ns, is_complete(p), replayed_marker(p).exists()))
    return sorted(logs, key=lambda f: (f.mtime_ns, f.path.name))


def logs_total_bytes(log_dir: Path) -> int:
    """The bytes the session logs, their companions and the reserve files take in ``log_dir``."""
    total = sum(_size(p) for p in Path(log_dir).glob(RESERVE_GLOB))
    for log in Path(log_dir).glob(LOG_GLOB):
        total += _size(log) + sum(_size(c) for c in companions(log))
    return total


def disk_free_bytes(log_dir: Path) -> int:
    """Free bytes for an unprivileged writer on the file system of ``log_dir``."""
    st = os.statvfs(log_dir)
    return st.f_bavail * st.f_frsize


def next_log_bytes(logs: list[LogFile], cfg: LogbookConfig) -> int:
    """The room the next log needs: its reserve and the largest of the newest complete logs plus a
    tenth, at least :attr:`LogbookConfig.least_log_bytes`."""
    sizes = [f.size_bytes for f in logs if f.complete][-NEWEST_LOGS:]
    if not sizes:
        return cfg.least_log_bytes
    return max(cfg.least_log_bytes, cfg.reserve_bytes + int(max(sizes) * (1.0 + SIZE_MARGIN)))


def _shortfall(cfg: LogbookConfig, free: int, total: int, room: int) -> str:
    """Which limit fails with ``room`` more bytes written ("" when both hold)."""
    why = []
    if cfg.keep_free_bytes and free - room < cfg.keep_free_bytes:
        why.append(f"{free} bytes free{f' less {room} for the next log' if room else ''}, "
                   f"keep_free_bytes {cfg.keep_free_bytes}")
    if cfg.max_total_bytes and total + room > cfg.max_total_bytes:
        why.append(f"logs take {total} bytes{f' plus {room} for the next log' if room else ''}, "
                   f"max_total_bytes {cfg.max_total_bytes}")
    return "; ".join(why)


def removable(f: LogFile, cfg: LogbookConfig, open_log: Path | None) -> bool:
    """Whether retention may remove ``f`` (see the module's description)."""
    if not f.complete or (cfg.keep_unreplayed and not f.replayed):
        return False
    return open_log is None or f.path.resolve() != Path(open_log).resolve()


def enforce(log_dir: Path, cfg: LogbookConfig, room_bytes: int = 0, open_log: Path | None = None,
            say: Callable[[str], None] = LOG.info) -> Retention:
    """Remove the oldest removable logs of ``log_dir`` until both limits hold with ``room_bytes``
    more written; each removal is one line given to ``say``."""
    out = Retention()
    if not (cfg.keep_free_bytes or cfg.max_total_bytes):
        return out
    logs = session_logs(log_dir)
    candidates = [f for f in logs if removable(f, cfg, open_log)]
    while True:
        out.free_bytes, out.total_bytes = disk_free_bytes(log_dir), logs_total_bytes(log_dir)
        out.reason = _shortfall(cfg, out.free_bytes, out.total_bytes, room_bytes)
        if not out.reason or not candidates:
            break
        f = candidates.pop(0)
        try:
            f.path.unlink()
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise LogError(f"{f.path}: retention cannot remove it: {exc.strerror}") from None
        for c in companions(f.path):
            try:
                c.unlink(missing_ok=True)
            except OSError as exc:
                raise LogError(f"{c}: retention cannot remove it with its log: {exc.strerror}") from None
        out.removed.append(f)
        say(f"retention: removed {f.path} ({f.size_bytes} bytes, the oldest complete log"
            f"{', replayed' if f.replayed else ''}): {out.reason}")
    out.holds = not out.reason
    return out


def make_room(log_dir: Path, cfg: LogbookConfig, say: Callable[[str], None] = LOG.info) -> Retention:
    """Before a session: room for one more log within the limits, or :class:`NoRoomError`."""
    if not (cfg.keep_free_bytes or cfg.max_total_bytes):
        return Retention()
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    room = next_log_bytes(session_logs(log_dir), cfg)
    out = enforce(log_dir, cfg, room, say=say)
    if not out.holds:
        kept = "; the rest are not replayed (keep_unreplayed)" if cfg.keep_unreplayed else ""
        raise NoRoomError(f"{log_dir}: no room for the next log ({out.reason}) after removing "
                          f"{len(out.removed)} log{'' if len(out.removed) == 1 else 's'}{kept}")
    return out


def check_retention(cfg: LogbookConfig, log_dir: Path) -> None:
    """The retention settings against the disk of ``log_dir`` (the nearest folder that exists):
    ``keep_free_bytes`` above the disk's size is a :class:`ConfigError`."""
    if not cfg.keep_free_bytes:
        return
    where = Path(log_dir).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    st = os.statvfs(where)
    size = st.f_blocks * st.f_frsize
    if cfg.keep_free_bytes >= size:
        raise ConfigError(f"logbook.keep_free_bytes: expected less than the size of the disk of {log_dir} "
                          f"({size} bytes), got {cfg.keep_free_bytes}")
