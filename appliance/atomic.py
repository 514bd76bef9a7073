"""Atomic file output: every file the appliance writes goes through here.

A file is written to a temporary file in its own folder (``.NAME.PID-XXXXXXXX.tmpSUFFIX``: the
writer's process id, so that a temporary whose writer is dead is known as stale whatever its name; a
NAME over 200 bytes cut to its start and a hash, so that every name a file system takes can be
written; the suffix, so that a library that picks the format from it sees the right one), fsynced,
given its mode and renamed over its final name, and the folder is fsynced; on any failure the
temporary file is removed and the final name is untouched.  Every write first removes the
temporaries in its folder that dead writers left (:func:`remove_dead_writers_temporaries`).  A new
file gets ``0666 & ~umask`` like any other tool's output; a replaced file keeps its mode.  Every
``OSError`` (a missing folder, a file where the folder should be, a folder where the file should be,
a read-only folder, a full disk) becomes one :class:`OutputError` line naming the path.

:func:`scratch_file` gives a writer an unnamed file beside its output for intermediate data (the
skyline database's build spills its skylines there), gone when it closes, even after a kill.

:func:`check_output_path` is what commands call before the work starts: it refuses an output that
is one of the inputs, an existing file without ``--force``, and a path whose folder cannot take it.
"""

from __future__ import annotations

import errno
import fcntl
import glob
import hashlib
import os
import re
import secrets
import shutil
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path

from appliance.errors import OutputError, ViperError

#: Marker in every temporary name (``.report.png.4242-1f2e3d4c.tmp.png``), for tests and cleanup.
TMP_MARK = ".tmp"
#: A temporary name with its writer's process id (group 1), as :func:`temporary_path` makes them.
TEMPORARY_NAME = re.compile(r"\..*\.([0-9]+)-[0-9a-f]{8}" + re.escape(TMP_MARK) + r"(\.[^/]*)?", re.DOTALL)

_REASONS = {
    errno.ENOENT: "no such file or folder",
    errno.ENOTDIR: "a path component is a file, not a folder",
    errno.EISDIR: "is a folder",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large",
    errno.ENAMETOOLONG: "file name too long",
    errno.EEXIST: "already exists",
    errno.EIO: "input/output error",
}

_umask_lock = threading.Lock()
#: Folders :func:`check_output_folder` created in this process, for :func:`remove_created_folders`.
_created_folders: list[Path] = []


#: A final name longer than this (bytes) is shortened in its temporaries' names, which then fit in
#: a file system's 255 bytes whatever the final name's length.
_STEM_BYTES = 200
_SUFFIX_BYTES = 16


def _stem(name: str) -> str:
    """The part of a temporary's name that comes from the final name: the name itself, or a long
    one's first bytes and a hash of the whole (the same for the same name, for the cleanup)."""
    raw = name.encode("utf-8", errors="surrogateescape")
    if len(raw) <= _STEM_BYTES:
        return name
    digest = hashlib.sha256(raw).hexdigest()[:8]
    head = raw[: _STEM_BYTES - 9].decode("utf-8", errors="ignore")
    return f"{head}~{digest}"


def temporary_name(name: str, suffix: str | None = None) -> str:
    """A fresh temporary's name for the final name ``name``: ``.STEM.PID-XXXXXXXX.tmpSUFFIX`` (this
    process's id; the final name's suffix unless given, left out when longer than 16 bytes), at most
    239 bytes long."""
    if suffix is None:
        suffix = Path(name).suffix
    if len(suffix.encode("utf-8", errors="surrogateescape")) > _SUFFIX_BYTES:
        suffix = ""
    return f".{_stem(name)}.{os.getpid()}-{secrets.token_hex(4)}{TMP_MARK}{suffix}"


def describe_os_error(exc: OSError) -> str:
    """A short reason for ``exc`` (no errno numbers, no Python names)."""
    if exc.errno in _REASONS:
        return _REASONS[exc.errno]
    return exc.strerror or str(exc) or type(exc).__name__


def output_error(path: str | Path, exc: OSError, doing: str = "cannot write") -> OutputError:
    """The one-line error for ``exc`` raised while writing ``path``."""
    p = Path(path)
    reason = describe_os_error(exc)
    if exc.errno == errno.ENOENT and not p.parent.exists():
        reason = f"folder {_folder(p)} does not exist"
    elif exc.errno == errno.ENOTDIR:
        reason = f"{_first_non_folder(p)} is not a folder"
    err = OutputError(f"{p}: {doing}: {reason}")
    err.errno = exc.errno
    return err


def _folder(p: Path) -> str:
    return str(p.parent) if str(p.parent) not in ("", ".") else "."


def _first_non_folder(p: Path) -> str:
    for parent in reversed(p.parents):
        if str(parent) in ("", "."):
            continue
        if parent.exists() and not parent.is_dir():
            return str(parent)
    return _folder(p)


def umask_mode() -> int:
    """``0o666 & ~umask``: the mode a new regular file gets from ``open(..., "w")``."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def fsync_folder(folder: Path) -> None:
    """Make a rename durable (best effort: some file systems refuse to fsync a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _preallocate(fd: int, size: int) -> None:
    """Reserve ``size`` bytes on disk now, so a full disk is ENOSPC here and never SIGBUS later."""
    if size <= 0:
        return
    try:
        os.posix_fallocate(fd, 0, size)
        return
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
            raise
    block = b"\0" * (1 << 20)
    os.lseek(fd, 0, os.SEEK_SET)
    left = size
    while left > 0:
        left -= os.write(fd, block[: min(left, len(block))])
    os.lseek(fd, 0, os.SEEK_SET)


@contextmanager
def atomic_output(path: str | Path, *, preallocate: int = 0) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on a clean exit it becomes ``path`` atomically.

    The body writes the temporary file by any means (``open``, ``rasterio.open``, ``savefig``, a
    memory map) and closes it.  On success: fsync, mode (the umask's, or the replaced file's), rename,
    folder fsync.  On any exception the temporary file is removed and ``path`` is untouched; an
    ``OSError`` (from the body too) becomes one :class:`OutputError` line.

    ``preallocate`` > 0 (memory-mapped writers): the temporary file is created with that many bytes
    allocated on disk (zeros), so a full disk fails here with ENOSPC instead of killing the process
    with SIGBUS when a page of the map is first written.  Open it ``"r+b"`` then, not ``"wb"``
    (which would give the allocation back).

    The temporary file stays locked (``flock``) while it is written; the unlocked temporaries of the
    same name that a killed writer left are removed first.
    """
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise OutputError(f"{p}: cannot write: is a folder")
    try:
        mode = p.stat().st_mode & 0o7777
    except OSError:
        mode = umask_mode()
    remove_stale_temporaries(folder, p.name)
    remove_dead_writers_temporaries(folder)
    tmp = temporary_path(p)
    try:
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise output_error(p, exc) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            _preallocate(fd, preallocate)
            yield tmp
            written = os.open(tmp, os.O_RDONLY | os.O_CLOEXEC)  # the body may have made a new file
            try:
                os.fsync(written)
            finally:
                os.close(written)
            os.chmod(tmp, mode)
            os.replace(tmp, p)
        finally:
            os.close(fd)
    except OSError as exc:
        _remove(tmp)
        if isinstance(exc, ViperError):
            raise
        raise output_error(p, exc) from None
    except BaseException:
        _remove(tmp)
        raise
    fsync_folder(folder)


@contextmanager
def scratch_file(path: str | Path, *, preallocate: int = 0) -> Iterator[int]:
    """Yield the descriptor of an unnamed scratch file in ``path``'s folder, for a writer's
    intermediate data (read and written with ``os.pwrite``/``os.preadv``); it is gone when the block
    exits, whatever happens.

    The file has no name from the start (``O_TMPFILE``; where the file system lacks it, a name that
    is unlinked at once), so not even a killed process leaves it behind: its disk space returns when
    the descriptor closes.  ``preallocate`` > 0 reserves that many bytes on disk first, so a full disk
    fails here, before the work.  Every ``OSError`` becomes one :class:`OutputError` line naming
    ``path``: "cannot write its scratch file: ..." when the file cannot be made or allocated, and
    "cannot write: ..." (as :func:`atomic_output` says) from the body."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    try:
        fd = _unnamed_file(folder, p.name)
        try:
            _preallocate(fd, preallocate)
        except BaseException:
            os.close(fd)
            raise
    except OSError as exc:
        raise output_error(p, exc, "cannot write its scratch file") from None
    try:
        try:
            yield fd
        finally:
            os.close(fd)
    except OSError as exc:
        if isinstance(exc, ViperError):
            raise
        raise output_error(p, exc) from None


def _unnamed_file(folder: Path, name: str) -> int:
    """A new file in ``folder`` that no name refers to, open for reading and writing."""
    flags = os.O_RDWR | os.O_CLOEXEC
    tmpfile = getattr(os, "O_TMPFILE", 0)
    if tmpfile:
        try:
            return os.open(folder, flags | tmpfile, 0o600)
        except OSError as exc:
            # no O_TMPFILE on this file system (EOPNOTSUPP) or kernel (EISDIR, EINVAL): a named file
            if exc.errno not in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
                raise
    tmp = temporary_path(folder / name, ".scratch")
    fd = os.open(tmp, flags | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        tmp.unlink()
    except BaseException:
        os.close(fd)
        _remove(tmp)
        raise
    return fd


def _remove(tmp: Path) -> None:
    try:
        tmp.unlink()
    except FileNotFoundError:
        pass
    except OSError:
        pass


def write_bytes_atomic(path: str | Path, data: bytes | bytearray | memoryview) -> None:
    """Replace ``path`` with ``data`` atomically (see :func:`atomic_output`)."""
    with atomic_output(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_CLOEXEC)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)


def write_text_atomic(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    """Replace ``path`` with ``text`` atomically; newlines are written as given."""
    write_bytes_atomic(path, text.encode(encoding))


def check_output_path(path: str | Path, inputs: Iterable[str | Path] = (), force: bool = False) -> Path:
    """Refuse, before any work, an output the command could not or should not write.

    Refused: an empty path; a path that names one of ``inputs`` (also through links); an existing
    folder; a missing folder or a file in its place; a read-only folder; an existing file unless
    ``force``.  Returns the path.
    """
    p = Path(path)
    if str(path) == "":
        raise OutputError("output path is empty")
    for inp in inputs:
        if _same_file(p, Path(inp)):
            raise OutputError(f"{p}: is also an input; refusing to overwrite it")
    if p.is_dir():
        raise OutputError(f"{p}: is a folder, expected a file name")
    _check_folder(p)
    if (p.exists() or p.is_symlink()) and not force:
        raise OutputError(f"{p}: already exists (pass --force to replace it)")
    return p


def check_output_folder(path: str | Path, inputs: Iterable[str | Path] = (), files: Iterable[str] = (),
                        force: bool = True) -> Path:
    """Create the output folder ``path`` (and its parents) or refuse it in one line.

    ``files`` are the names the command will write into it: unless ``force``, one that exists
    already is refused, before the folder is created and before any work.
    """
    p = Path(path)
    if str(path) == "":
        raise OutputError("output folder is empty")
    for inp in inputs:
        if _same_file(p, Path(inp)):
            raise OutputError(f"{p}: is also an input; refusing to write into it")
    if p.exists() and not p.is_dir():
        raise OutputError(f"{p}: is a file, expected a folder")
    if not force:
        for name in files:
            q = p / name
            if q.exists() or q.is_symlink():
                raise OutputError(f"{q}: already exists (pass --force to replace it)")
    missing = [q for q in (p, *p.parents) if not q.exists()]
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(p, exc, "cannot create the folder") from None
    _created_folders.extend(reversed(missing))
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"{p}: cannot write into the folder: "
                          f"{'read-only file system' if _read_only(p) else 'permission denied'}")
    if _read_only(p):
        raise OutputError(f"{p}: cannot write into the folder: read-only file system")
    return p


def remove_created_folders() -> None:
    """Remove the folders :func:`check_output_folder` created that are still empty (a command
    that failed leaves no empty report folder behind), deepest first; forget them all."""
    while _created_folders:
        try:
            _created_folders.pop().rmdir()
        except OSError:
            pass


def forget_created_folders() -> None:
    """Keep the folders created so far (the command that made them succeeded)."""
    _created_folders.clear()


def _check_folder(p: Path) -> None:
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.exists():
        if any(q.exists() and not q.is_dir() for q in folder.parents):
            raise OutputError(f"{p}: cannot write: {_first_non_folder(p)} is not a folder")
        raise OutputError(f"{p}: cannot write: folder {_folder(p)} does not exist")
    if not folder.is_dir():
        raise OutputError(f"{p}: cannot write: {folder} is not a folder")
    if _read_only(folder):
        raise OutputError(f"{p}: cannot write: read-only file system")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{p}: cannot write: permission denied on folder {_folder(p)}")


def _read_only(folder: Path) -> bool:
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    try:
        return a.resolve() == b.resolve()
    except (OSError, RuntimeError):
        return False


def remove_if_unheld(lock_path: Path, remove: Callable[[], None]) -> bool:
    """Call ``remove`` if no live process holds ``lock_path``'s flock (its owner was killed); True if
    it was called.  The lock is held while removing, so a live owner is never raced."""
    try:
        fd = os.open(lock_path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False
        try:
            remove()
        except OSError:
            return False
        return True
    finally:
        os.close(fd)


def remove_stale_temporaries(folder: str | Path, name: str) -> list[Path]:
    """Remove the temporary files of ``folder/name`` that no live writer holds (a killed one's)."""
    try:
        candidates = sorted(Path(folder).glob(f".{glob.escape(_stem(name))}.*{TMP_MARK}*"))
    except OSError:
        return []
    return [q for q in candidates if remove_if_unheld(q, q.unlink)]


def temporary_path(path: Path, suffix: str | None = None) -> Path:
    """A new temporary name beside ``path``: hidden, with this process's id and a random part, and
    ``suffix`` (by default ``path``'s own)."""
    folder = path.parent if str(path.parent) else Path(".")
    return folder / temporary_name(path.name, suffix)


def temporary_writer(name: str) -> int | None:
    """The process id in a temporary's name (see :data:`TEMPORARY_NAME`), or None for another name."""
    match = TEMPORARY_NAME.fullmatch(name)
    return int(match.group(1)) if match else None


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it exists, as another user's
        return True
    return True


def remove_dead_writers_temporaries(folder: str | Path) -> list[Path]:
    """Remove the temporaries in ``folder``, of any output, whose writer is dead: its process id no
    longer runs here and nothing holds the file's lock (a live writer on another host of a shared
    folder is known by its lock).  A live writer's temporaries are left alone; a temporary folder (a staging
    folder named as a temporary) goes with its contents."""
    try:
        with os.scandir(folder) as entries:
            found = [(e.name, temporary_writer(e.name)) for e in entries if e.name.startswith(".")]
    except OSError:
        return []
    removed = []
    for name, pid in sorted(found, key=lambda f: f[0]):
        if pid is None or _process_alive(pid):
            continue
        q = Path(folder) / name
        if remove_if_unheld(q, partial(shutil.rmtree, q) if q.is_dir() and not q.is_symlink() else q.unlink):
            removed.append(q)
    return removed
