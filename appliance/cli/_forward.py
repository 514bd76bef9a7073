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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: Commands that a server runs: one-shot commands whose start-up is most of their time.
FORWARDED = frozenset({"estimate", "render", "skyline"})
#: Environment variables whose values a server fixed at start and a worker cannot change: numba's
#: and the BLAS's settings, read once at import, PROJ's and GDAL's (which may cache them once
#: loaded), and where Python finds modules and how it hashes.
FIXED_PREFIXES = ("NUMBA_", "OMP_", "OPENBLAS_", "MKL_", "PROJ_", "GDAL_")
FIXED_NAMES = frozenset({"PYTHONPATH", "PYTHONHASHSEED", "PYTHONHOME", "PYTHONSAFEPATH"})
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
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        try:
            sock.connect(str(path))
        except OSError:
            return None
        try:
            cwd = os.getcwd()
        except OSError:  # a working folder since removed: run in process, as ever
            return None
        request = {"argv": list(argv), "cwd": cwd, "env": dict(os.environ), "umask": _umask(),
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
        return _wait(sock, reader, int(reply["pid"]), command)
    finally:
        sock.close()


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _wait(sock: socket.socket, reader: LineReader, pid: int, command: str) -> int:
    """The worker's exit status, passing this process's signals on to it meanwhile."""

    passed: list[int] = []

    def pass_on(signum: int, frame: object) -> None:
        passed.append(signum)
        try:
            os.kill(pid, signum)
        except ProcessLookupError:
            pass

    previous = {s: signal.signal(s, pass_on) for s in PASSED_SIGNALS}
    try:
        while True:
            try:
                reply = reader.read()
                break
            except InterruptedError:
                continue
            except (OSError, ValueError):
                reply = None
                break
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if reply is None and passed and passed[-1] != signal.SIGINT:
        # the worker ended by the signal this process was sent: so does this process, as it would have alone
        signal.signal(passed[-1], signal.SIG_DFL)
        os.kill(os.getpid(), passed[-1])
    if reply is None or not isinstance(reply.get("exit"), int):
        os.write(2, f"viper {command}: error: the command server's worker ended without an exit status\n".encode())
        return 1
    return int(reply["exit"])
