"""Running a one-shot command in a warm process: the client side of ``viper serve``.

Importing numpy, numba, pyproj and the estimator takes about half a second, more than a whole
estimate on a small map.  ``viper serve`` imports them once and listens on a Unix socket.  A spare worker,
forked from it ahead of time and with the kernels loaded, takes the next connection: it takes over
the client's standard streams (passed as file descriptors), working folder, environment and umask,
and runs the command line as ``viper`` would.  Each command runs in a fresh fork of the warm
process, so commands share nothing.

The client (``viper`` itself, before importing anything heavy) forwards the commands of
FORWARDED when a server listens on :func:`socket_path` and agrees to take them; otherwise, or when
``VIPER_SOCKET`` is empty, the command runs in process as before.  A server takes a command only
from a process of its own user, only for the same installed code (:func:`code_identity`), and only
when numba's settings in the environment are its own (they are read once, at import).

The client, in turn, sends nothing to a server it cannot trust with its streams and environment: the
socket and its folder must be its user's, the folder writable by no one else, and the process that
listens its user's (SO_PEERCRED); otherwise it says why on stderr and runs the command itself.  It
sends only the environment a command needs (:func:`passed_environment`), and passes its signals on
only to a child of that process of its user.

Messages are one JSON object per line.  The client sends the request, with its three standard
streams attached; the server answers ``{"pid": N}`` (the worker, which the client's signals are
passed on to) or ``{"refused": reason}``, and the worker ends with ``{"exit": code}``.
"""

from __future__ import annotations

import array
import json
import os
import signal
import socket
import stat
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: Commands that a server runs: one-shot commands whose start-up is most of their time.
FORWARDED = frozenset({"estimate", "locate", "render", "skyline"})
#: Environment variables whose values a server fixed at start and a worker cannot change: numba's
#: and the BLAS's settings, read once at import, PROJ's and GDAL's (which may cache them once
#: loaded), and where Python finds modules and how it hashes.
FIXED_PREFIXES = ("NUMBA_", "OMP_", "OPENBLAS_", "MKL_", "PROJ_", "GDAL_")
FIXED_NAMES = frozenset({"PYTHONPATH", "PYTHONHASHSEED", "PYTHONHOME", "PYTHONSAFEPATH"})
#: The environment a command is given: the fixed settings above, the appliance's own (``VIPER_*``),
#: locale and time zone, the user's folders (``XDG_*``, the units' ``CACHE_DIRECTORY``), the terminal,
#: and whether stderr is the journal.  Nothing else (tokens, keys, passwords) leaves the client.
PASSED_PREFIXES = (*FIXED_PREFIXES, "VIPER_", "LC_", "XDG_")
PASSED_NAMES = FIXED_NAMES | {"PATH", "HOME", "USER", "LOGNAME", "LANG", "LANGUAGE", "TZ", "TMPDIR",
                              "CACHE_DIRECTORY", "TERM", "COLUMNS", "LINES", "NO_COLOR", "JOURNAL_STREAM"}
#: The longest request accepted (argv, folder and environment), bytes.
MAX_REQUEST_BYTES = 1 << 20
PASSED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)
PACKAGE = Path(__file__).resolve().parents[1]


def socket_path() -> Path | None:
    """Where a server listens: ``$VIPER_SOCKET`` when set (empty: no server), otherwise
    ``viper/commands.sock`` in ``$XDG_RUNTIME_DIR`` (the user's runtime folder, where a user unit's
    socket lives); None when neither is set."""
    explicit = os.environ.get("VIPER_SOCKET")
    if explicit is not None:
        return Path(explicit) if explicit else None
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    return Path(runtime) / "viper" / "commands.sock" if runtime else None


def code_identity() -> str:
    """The installed package: its folder and the newest modification of its modules, so that a
    server started before an upgrade or an edit refuses to run the new code's commands."""
    newest = 0
    stack = [PACKAGE]
    while stack:
        with os.scandir(stack.pop()) as entries:
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    if e.name != "__pycache__":
                        stack.append(Path(e.path))
                elif e.name.endswith(".py"):
                    newest = max(newest, e.stat().st_mtime_ns)
    return f"{PACKAGE}:{newest}"


def fixed_environment(env: dict[str, str]) -> dict[str, str]:
    """The variables of ``env`` that a warm process cannot change for one command."""
    return {k: v for k, v in env.items() if k.startswith(FIXED_PREFIXES) or k in FIXED_NAMES}


def passed_environment(env: dict[str, str]) -> dict[str, str]:
    """The variables of ``env`` that a command run by a server is given (PASSED_NAMES, PASSED_PREFIXES)."""
    return {k: v for k, v in env.items() if k.startswith(PASSED_PREFIXES) or k in PASSED_NAMES}


def send_message(sock: socket.socket, message: dict[str, Any]) -> None:
    sock.sendall(json.dumps(message).encode() + b"\n")


class LineReader:
    """JSON lines from a stream socket."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buffer = b""

    def read(self, limit: int = MAX_REQUEST_BYTES) -> dict[str, Any] | None:
        """The next message; None at the end of the stream (or a partial line before it)."""
        while b"\n" not in self.buffer:
            if len(self.buffer) > limit:
                raise ValueError(f"message longer than {limit} bytes")
            chunk = self.sock.recv(65536)
            if not chunk:
                return None
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        message = json.loads(line)
        if not isinstance(message, dict):
            raise ValueError("message is not a JSON object")
        return message


def forward(argv: Sequence[str], command: str | None) -> int | None:
    """Run ``argv`` in a server's worker and return its exit status; None when no server takes it
    (the caller then runs the command itself).  Nothing has run when None is returned."""
    if command not in FORWARDED:
        return None
    path = socket_path()
    if path is None:
        return None
    connected = _connect(path)
    if connected is None:
        return None
    sock, server = connected
    try:
        try:
            cwd = os.getcwd()
        except OSError:  # a working folder since removed: run in process, as ever
            return None
        request = {"argv": list(argv), "cwd": cwd, "env": passed_environment(dict(os.environ)), "umask": _umask(),
                   "code": code_identity()}
        data = json.dumps(request).encode() + b"\n"
        try:
            sent = sock.sendmsg([data[:4096]], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [0, 1, 2]))])
            sock.sendall(data[sent:])
            reader = LineReader(sock)
            reply = reader.read()
        except (OSError, ValueError):
            return None
        if reply is None or "pid" not in reply:
            return None
        return _wait(reader, _worker(reply["pid"], server), server, command)
    finally:
        sock.close()


def _connect(path: Path) -> tuple[socket.socket, int] | None:
    """A connection to the server listening on ``path`` and the pid of the process that listens, when
    this user alone could have put the socket there (:func:`_distrust`) and that process is this
    user's; None otherwise, with the reason on stderr when a socket is there but not trusted.  The
    socket is reached through its open folder, so that the folder checked is the one connected to."""
    try:
        folder = os.open(path.parent, os.O_PATH | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        return _connect_in(folder, path)
    finally:
        os.close(folder)


def _connect_in(folder: int, path: Path) -> tuple[socket.socket, int] | None:
    try:
        reason = _distrust(folder, path.name)
    except OSError:  # no socket there: no server
        return None
    if reason is not None:
        _not_using(path, reason)
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(f"/proc/self/fd/{folder}/{path.name}")
    except OSError:
        sock.close()
        return None
    pid, uid, _ = peer_credentials(sock)
    if uid != os.getuid():
        sock.close()
        _not_using(path, f"its server runs as uid {uid}")
        return None
    return sock, pid


def _not_using(path: Path, reason: str) -> None:
    _say(f"viper: not using the command server at {path}: {reason}")


def _distrust(folder: int, name: str) -> str | None:
    """Why another user may have put the socket ``name`` in the open ``folder``: the folder is not
    this user's, or others may write to it, or the socket is not this user's; None when none of these
    holds.  Raises OSError when there is no file ``name``."""
    own = os.getuid()
    sock = os.stat(name, dir_fd=folder, follow_symlinks=False)
    where = os.fstat(folder)
    if where.st_uid != own:
        return f"its folder belongs to uid {where.st_uid}"
    if where.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"others may write to its folder (mode {stat.S_IMODE(where.st_mode):o})"
    if not stat.S_ISSOCK(sock.st_mode):
        return "not a socket"
    if sock.st_uid != own:
        return f"the socket belongs to uid {sock.st_uid}"
    return None


def peer_credentials(sock: socket.socket) -> tuple[int, int, int]:
    """The pid, uid and gid of the process at the other end of a Unix socket (of the process that
    listened, seen from a client)."""
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    return pid, uid, gid


def is_own_child(pid: int, parent: int) -> bool:
    """Whether process ``pid`` is a child of process ``parent`` and runs as this user (all its user
    ids are this process's), read from /proc."""
    try:
        with open(f"/proc/{pid}/status", encoding="utf-8", errors="replace") as f:
            fields = dict(line.partition(":")[::2] for line in f)
    except OSError:
        return False
    own = str(os.getuid())
    return fields.get("PPid", "").strip() == str(parent) and set(fields.get("Uid", "").split()) == {own}


def _worker(named: object, server: int) -> int | None:
    """The worker the server named, when it is a child of the server of this user: the one process
    this process's signals may be passed on to; None (said on stderr) for any other."""
    if type(named) is int and named > 0 and is_own_child(named, server):
        return named
    _say(f"viper: the command server named {named!r} as its worker, not a child of its own: no signal is passed on")
    return None


def _say(line: str) -> None:
    try:
        os.write(2, line.encode(errors="backslashreplace") + b"\n")
    except OSError:
        pass


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _wait(reader: LineReader, pid: int | None, server: int, command: str) -> int:
    """The worker's exit status, passing this process's signals on to it meanwhile (to ``pid``, while
    it is still a child of the server's; none without a worker).  Interrupted without a worker to pass
    the interrupt on to, this process stops waiting, as the command run alone would."""

    passed: list[int] = []

    def pass_on(signum: int, frame: object) -> None:
        passed.append(signum)
        if pid is not None and is_own_child(pid, server):
            try:
                os.kill(pid, signum)
            except ProcessLookupError:
                pass

    previous = {s: signal.signal(s, pass_on) for s in PASSED_SIGNALS} if pid is not None else {}
    try:
        reply = _read_exit(reader)
    except KeyboardInterrupt:
        _say(f"viper {command}: interrupted")
        return 130
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if reply is None and passed and passed[-1] != signal.SIGINT:
        # the worker ended by the signal this process was sent: so does this process, as it would have alone
        signal.signal(passed[-1], signal.SIG_DFL)
        os.kill(os.getpid(), passed[-1])
    if reply is None or not isinstance(reply.get("exit"), int):
        _say(f"viper {command}: error: the command server's worker ended without an exit status")
        return 1
    return int(reply["exit"])


def _read_exit(reader: LineReader) -> dict[str, Any] | None:
    """The worker's last message; None when the connection ends without one."""
    while True:
        try:
            return reader.read()
        except InterruptedError:
            continue
        except (OSError, ValueError):
            return None
