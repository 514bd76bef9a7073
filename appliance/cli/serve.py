"""``viper serve``: run one-shot commands in a warm process (see :mod:`appliance.cli._forward`)."""

from __future__ import annotations

import argparse
import array
import importlib
import io
import logging
import math
import os
import select
import signal
import socket
import stat
import struct
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from appliance.acquisition.notify import Notifier
from appliance.cli._forward import (
    FORWARDED,
    MAX_REQUEST_BYTES,
    LineReader,
    code_identity,
    fixed_environment,
    peer_credentials,
    send_message,
    socket_path,
)
from appliance.cli.main import build_parser, main
from appliance.errors import InputError
from appliance.numerics import load_cached_kernels

LOG = logging.getLogger(__name__)

#: Modules that the forwarded commands import as they run (``python -X importtime``), imported once by
#: the server: the tiled search, the estimate's files, numpy.ma (rasterio's masks), multiprocessing
#: (the thread pools' locks), what numba's runtime imports when a parallel kernel loads, and the
#: photo's orientation fits' optimiser (``viper locate`` imports it on a thread as the photo is read).
WARM_MODULES = ("appliance.locating.tiled_search", "appliance.outputs.report", "numpy.ma",
                "multiprocessing.synchronize", "numba.cpython.charseq", "numba.cpython.randomimpl",
                "numba.misc.mergesort", "scipy.optimize")
#: Seconds between the server's checks for finished workers and a request to stop.
POLL_S = 0.5
#: How long a stopping server waits for its spare workers to end before killing them (s).
STOP_WAIT_S = 5.0
#: Seconds a client has to send its request once connected.
REQUEST_TIMEOUT_S = 10.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run estimate, locate, render and skyline in a warm process, so that they "
                                     "start at once")
    p.add_argument("--socket", help="Unix socket to listen on (default: $VIPER_SOCKET, else "
                                    "$XDG_RUNTIME_DIR/viper/commands.sock; a socket passed by systemd comes first)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    listener, owned = _listener(args.socket)
    # the settings as the server was started, as a client has them: a library may add its own while it
    # is imported (rasterio sets GDAL's and PROJ's CA bundles), and so would the client's own process
    fixed = fixed_environment(dict(os.environ))
    try:
        for name in WARM_MODULES:
            importlib.import_module(name)
        for command in sorted(FORWARDED):
            build_parser(command)
        kernels = load_cached_kernels()
        notifier = Notifier.from_environment()
        identity = code_identity()
        stopping: list[int] = []
        signal.signal(signal.SIGTERM, lambda signum, frame: stopping.append(signum))
        taken_r, taken_w = os.pipe()
        idle = {_fork_spare(listener, taken_w, identity, fixed)}
        LOG.info("serving %s (%d kernels loaded)", ", ".join(sorted(FORWARDED)), kernels)
        notifier.ready(f"serving {', '.join(sorted(FORWARDED))}")
        try:
            while not stopping:
                idle -= _reap()
                ready, _, _ = select.select([taken_r], [], [], POLL_S)
                if ready:
                    news = os.read(taken_r, 512)
                    idle -= {pid for (pid,) in struct.iter_unpack("q", news)}
                if not idle:
                    idle.add(_fork_spare(listener, taken_w, identity, fixed))
        except KeyboardInterrupt:
            pass
        _stop_spares(idle)
        notifier.stopping()
        LOG.info("stopped")
        return 0
    finally:
        listener.close()
        if owned is not None:
            try:
                owned.unlink()
            except OSError:
                pass


def _listener(option: str | None) -> tuple[socket.socket, Path | None]:
    """The listening socket, and its path when this process made it (and removes it at the end)."""
    if option is None and os.environ.get("LISTEN_PID") == str(os.getpid()) and os.environ.get("LISTEN_FDS") == "1":
        sock = socket.socket(fileno=3)
        if sock.family != socket.AF_UNIX or sock.type != socket.SOCK_STREAM:
            raise InputError("the socket passed by systemd is not a Unix stream socket")
        _listen_as_this_process(sock)
        return sock, None
    path = Path(option) if option else socket_path()
    if path is None:
        raise InputError("no socket: give --socket, or set VIPER_SOCKET or XDG_RUNTIME_DIR")
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    if path.exists() or path.is_symlink():
        if not stat.S_ISSOCK(path.lstat().st_mode):
            raise InputError(f"{path}: exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(path))
        except OSError:
            path.unlink()  # left by a server that ended without removing it
        else:
            raise InputError(f"{path}: another server is listening there")
        finally:
            probe.close()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)  # the socket is the user's alone
    try:
        sock.bind(str(path))
    finally:
        os.umask(old)
    sock.listen(16)
    return sock, path


def _listen_as_this_process(listener: socket.socket) -> None:
    """Listen again on a socket that systemd passed: the credentials a client reads (SO_PEERCRED)
    become this process's, whose children the workers are (a client passes its signals only to a
    child of the process that listens).  The connections already waiting, whose clients read the
    service manager's, are refused: those clients run their commands themselves."""
    manager, _, _ = peer_credentials(listener)
    listener.listen(16)
    if manager == os.getpid():  # systemd-socket-activate listens, then runs the server in its own process
        return
    listener.setblocking(False)
    try:
        while True:
            conn, _ = listener.accept()
            with conn:
                try:
                    send_message(conn, {"refused": "connected before the server listened"})
                except OSError:
                    pass
    except BlockingIOError:
        pass
    finally:
        listener.setblocking(True)


def _reap() -> set[int]:
    """The server's children that ended since the last call."""
    ended: set[int] = set()
    while True:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return ended
        if pid == 0:
            return ended
        ended.add(pid)


def _fork_spare(listener: socket.socket, taken: int, identity: str, fixed: dict[str, str]) -> int:
    """Fork a spare worker, which waits for the next connection; it writes its pid to ``taken`` once
    it has one, and the server then forks the next spare (as it does when a spare ends).

    SIGTERM is blocked across the fork: a spare stopped before it has put back the default action
    would otherwise run the server's handler instead, and wait for a connection that never comes;
    blocked, the signal waits until the default is in place, and then ends the spare."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        pid = os.fork()
        if pid == 0:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
            _spare(listener, taken, identity, fixed)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    return pid


def _stop_spares(idle: set[int]) -> None:
    """End the spare workers still waiting for a connection, and wait for them (SIGKILL after
    STOP_WAIT_S), so that none outlives the server, even as a zombie under an init that does not reap."""
    for pid in idle:
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    deadline = time.monotonic() + STOP_WAIT_S
    left = set(idle)
    while left:
        for pid in list(left):
            try:
                done, _ = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:
                done = pid
            if done:
                left.discard(pid)
        if left and time.monotonic() > deadline:
            for pid in left:
                os.kill(pid, signal.SIGKILL)
            deadline = math.inf
        if left:
            time.sleep(0.01)


def _spare(listener: socket.socket, taken: int, identity: str, fixed: dict[str, str]) -> None:
    """A worker waiting for one connection, with the parallel kernels loaded as well (this process
    forks no more, so the threading layer may load); then the command, or its refusal.  Each
    connection has a process of its own, so a slow client holds up no other.  Never returns."""
    fds: list[int] = []
    try:
        load_cached_kernels(parallel=True)
        listener.settimeout(None)
        conn, _ = listener.accept()
        os.write(taken, struct.pack("q", os.getpid()))
        listener.close()
        conn.settimeout(REQUEST_TIMEOUT_S)
        _, uid, _ = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
        request = None
        if uid == os.getuid():
            data, ancillary, _, _ = conn.recvmsg(65536, socket.CMSG_SPACE(3 * array.array("i").itemsize))
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                    got = array.array("i")
                    got.frombytes(payload[: len(payload) - len(payload) % got.itemsize])
                    fds.extend(got)
            reader = LineReader(conn)
            reader.buffer = data
            request = reader.read(MAX_REQUEST_BYTES) if data else None
        reason = _refusal(request, uid, fds, identity, fixed)
        if reason is not None:
            LOG.debug("refused a command: %s", reason)
            send_message(conn, {"refused": reason})
        else:
            assert request is not None
            try:
                os.chdir(request["cwd"])
            except OSError as exc:  # a folder this server cannot enter: the client runs the command itself
                LOG.debug("refused a command: its folder: %s", exc)
                send_message(conn, {"refused": f"its folder: {exc}"})
                return
            LOG.debug("worker %d: viper %s", os.getpid(), " ".join(request["argv"]))
            _worker(conn, fds, request)
    except (OSError, ValueError) as exc:
        LOG.warning("a request failed: %s", exc)
    finally:
        os._exit(0)


def _refusal(request: dict[str, Any] | None, uid: int, fds: list[int], identity: str,
             fixed: dict[str, str]) -> str | None:
    if uid != os.getuid():
        return "another user's command"
    if request is None or len(fds) != 3:
        return "not a request with three standard streams"
    argv, env = request.get("argv"), request.get("env")
    if not (isinstance(argv, list) and all(isinstance(a, str) for a in argv)):
        return "argv is not a list of strings"
    if not (isinstance(env, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in env.items())):
        return "env is not a mapping of strings"
    if not isinstance(request.get("cwd"), str) or not isinstance(request.get("umask"), int):
        return "no working folder or umask"
    if request.get("code") != identity:
        return "the installed code changed since the server started"
    if fixed_environment(env) != fixed:
        return "numba's, BLAS's or Python's settings differ from the server's"
    return None


def _worker(conn: socket.socket, fds: list[int], request: dict[str, Any]) -> None:
    """Take the client's streams, environment and umask (its folder is already this process's),
    then run the command line as ``viper`` runs it; never returns."""
    code = 1
    try:
        conn.settimeout(None)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGCHLD):
            signal.signal(s, signal.SIG_DFL)
        for i, fd in enumerate(fds):
            os.dup2(fd, i)
            os.close(fd)
        fds.clear()
        sys.stdin = io.TextIOWrapper(io.FileIO(0, "r", closefd=False), encoding="utf-8")
        sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8",
                                      line_buffering=os.isatty(1))
        sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8", errors="backslashreplace",
                                      line_buffering=True)
        send_message(conn, {"pid": os.getpid()})
        os.umask(request["umask"])
        os.environ.clear()
        os.environ.update(request["env"])
        sys.argv = [sys.argv[0], *request["argv"]]
        try:
            code = main(request["argv"])
        except SystemExit as exc:
            code = _exit_status(exc.code)
        except KeyboardInterrupt:
            code = 130
        except BaseException:  # what a process of its own would print before exiting with 1
            traceback.print_exc()
            code = 1
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
    finally:
        try:
            send_message(conn, {"exit": code})
        finally:
            os._exit(0)


def _exit_status(value: object) -> int:
    """The status ``sys.exit(value)`` gives a process: None is 0, a message is printed and 1."""
    if value is None:
        return 0
    if isinstance(value, int):
        return value
    print(value, file=sys.stderr)
    return 1

