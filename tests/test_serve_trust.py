"""The `viper` client trusts a command server with its streams, environment and signals only when the
server is its own user's: fake servers on real Unix sockets, in this process or in processes of
their own, and the client run as a user runs it.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from appliance.cli import _forward
from tests.test_command_server import RENDER, VIPER, _env, _workers

NOBODY = 65534


class FakeServer:
    """A server listening on ``path`` in a thread of this process: it keeps every byte each client
    sends until its first line, and then refuses the command."""

    def __init__(self, path: Path) -> None:
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(str(path))
        self.listener.listen(4)
        self.listener.settimeout(0.1)
        self.received: list[bytes] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.done.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(5)
                data = b""
                while b"\n" not in data:
                    chunk = conn.recv(65536)
                    if not chunk:
                        break
                    data += chunk
                self.received.append(data)
                if data:
                    conn.sendall(b'{"refused": "a fake server"}\n')

    def close(self) -> None:
        self.done.set()
        self.thread.join()
        self.listener.close()


def _folder(where: Path, mode: int, uid: int | None = None) -> Path:
    where.mkdir()
    if uid is not None:
        os.chown(where, uid, -1)
    os.chmod(where, mode)
    return where


@pytest.fixture(scope="module")
def alone() -> bytes:
    """The render's output, run in process."""
    done = subprocess.run([*VIPER, *RENDER], capture_output=True, env=_env(""), timeout=300)
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 91
    return done.stdout


@pytest.mark.parametrize("mode", [0o1777, 0o777, 0o770], ids=oct)
def test_a_socket_in_a_folder_others_may_write_is_not_used(tmp_path, alone, mode):
    """Another user could have put the socket there: the command runs in process, the server gets nothing."""
    sock = _folder(tmp_path / "shared", mode) / "commands.sock"
    fake = FakeServer(sock)
    try:
        done = subprocess.run([*VIPER, *RENDER], capture_output=True, env=_env(sock), timeout=300)
    finally:
        fake.close()
    assert done.returncode == 0 and done.stdout == alone
    assert done.stderr.decode().splitlines() == [
        f"viper: not using the command server at {sock}: others may write to its folder (mode {mode:o})"]
    assert b"".join(fake.received) == b""


def _forwarded(sock: Path, monkeypatch, **env: str) -> int | None:
    monkeypatch.setenv("VIPER_SOCKET", str(sock))
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    return _forward.forward(["render", "jacksboro"], "render")


def _needs_root() -> None:
    if os.getuid() != 0:
        pytest.skip("needs root, to act as another user (uid 65534)")


def test_a_socket_or_folder_of_another_user_is_not_used(tmp_path, monkeypatch, capfd):
    _needs_root()
    theirs = _folder(tmp_path / "theirs", 0o700, uid=NOBODY) / "commands.sock"
    mine = _folder(tmp_path / "mine", 0o700) / "commands.sock"
    fakes = [FakeServer(theirs), FakeServer(mine)]
    os.chown(mine, NOBODY, -1)
    try:
        assert _forwarded(theirs, monkeypatch) is None
        assert _forwarded(mine, monkeypatch) is None
    finally:
        for fake in fakes:
            fake.close()
    assert capfd.readouterr().err.splitlines() == [
        f"viper: not using the command server at {theirs}: its folder belongs to uid {NOBODY}",
        f"viper: not using the command server at {mine}: the socket belongs to uid {NOBODY}"]
    assert [f.received for f in fakes] == [[], []]


def test_a_server_of_another_user_is_not_used(tmp_path, monkeypatch, capfd):
    """A socket and folder of this user's, but listened on by a process of another user (SO_PEERCRED):
    the client connects and sends nothing."""
    _needs_root()
    sock = _folder(tmp_path / "run", 0o700) / "commands.sock"
    ready_r, ready_w = os.pipe()
    got_r, got_w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            listener.bind(str(sock))
            os.setuid(NOBODY)  # the credentials a client reads are those of the process that listens
            listener.listen(1)
            os.write(ready_w, b"1")
            conn, _ = listener.accept()
            conn.settimeout(10)
            received = b""
            while chunk := conn.recv(65536):
                received += chunk
            os.write(got_w, str(len(received)).encode())
        finally:
            os._exit(0)
    os.close(ready_w)
    os.close(got_w)
    try:
        assert os.read(ready_r, 1) == b"1"
        assert _forwarded(sock, monkeypatch) is None
        assert os.read(got_r, 64) == b"0"
    finally:
        os.waitpid(pid, 0)
        os.close(ready_r)
        os.close(got_r)
    assert capfd.readouterr().err.splitlines() == [
        f"viper: not using the command server at {sock}: its server runs as uid {NOBODY}"]


def test_the_environment_sent_holds_only_what_a_command_needs(tmp_path, monkeypatch):
    sock = _folder(tmp_path / "run", 0o700) / "commands.sock"
    fake = FakeServer(sock)
    try:
        assert _forwarded(sock, monkeypatch, MADE_UP_SECRET_TOKEN="s3cret", AWS_SECRET_ACCESS_KEY="k3y",
                          NUMBA_NUM_THREADS="3", LC_TIME="C") is None
    finally:
        fake.close()
    (received,) = fake.received
    env = json.loads(received)["env"]
    assert "MADE_UP_SECRET_TOKEN" not in env and "AWS_SECRET_ACCESS_KEY" not in env
    assert b"s3cret" not in received and b"k3y" not in received
    assert env["VIPER_SOCKET"] == str(sock) and env["LC_TIME"] == "C" and env["PATH"] == os.environ["PATH"]
    # what a server compares with its own settings all goes
    assert _forward.fixed_environment(env) == _forward.fixed_environment(dict(os.environ))
    assert env["NUMBA_NUM_THREADS"] == "3"


#: A server of this user, in a process of its own, that names ``argv[2]`` as the worker of the
#: first command sent to ``argv[1]``, says so on stdout, and waits for the client to go.
NAMING_SERVER = """
import socket, sys
listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
listener.bind(sys.argv[1])
listener.listen(1)
print("listening", flush=True)
conn, _ = listener.accept()
data = b""
while b"\\n" not in data:
    data += conn.recv(65536)
conn.sendall(b'{"pid": %d}\\n' % int(sys.argv[2]))
print("named", flush=True)
while conn.recv(65536):
    pass
"""


def _line(proc: subprocess.Popen, timeout: float) -> str:
    """The next line ``proc`` writes on stdout; what it wrote so far if none comes within ``timeout`` s."""
    assert proc.stdout is not None
    fd, got = proc.stdout.fileno(), b""
    deadline = time.monotonic() + timeout
    while not got.endswith(b"\n") and select.select([fd], [], [], max(0.0, deadline - time.monotonic()))[0]:
        chunk = os.read(fd, 1)
        if not chunk:
            break
        got += chunk
    return got.decode().rstrip("\n")


def test_a_signal_goes_to_no_process_but_a_child_of_the_server(tmp_path):
    """A server that names another process of this user as its worker (here a `sleep` of this
    process): the client's SIGTERM ends the client, as it would alone, and the `sleep` lives on."""
    sock = _folder(tmp_path / "run", 0o700) / "commands.sock"
    started = [subprocess.Popen(["sleep", "300"])]
    try:
        victim = started[0]
        server = subprocess.Popen([sys.executable, "-c", NAMING_SERVER, str(sock), str(victim.pid)],
                                  stdout=subprocess.PIPE)
        started.append(server)
        assert _line(server, 30) == "listening"
        client = subprocess.Popen([*VIPER, *RENDER], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(sock))
        started.append(client)
        assert _line(server, 60) == "named", "the client sent the fake server no command"
        time.sleep(1.0)  # the client has read the answer and waits for the command's end
        client.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        assert victim.poll() is None, "the client's signal reached a process that is not the server's"
        out, err = client.communicate(timeout=60)
        assert client.returncode == -signal.SIGTERM and out == b""
        assert err.decode().splitlines() == [f"viper: the command server named {victim.pid} as its worker, "
                                             "not a child of its own: no signal is passed on"]
    finally:
        for proc in started:
            proc.kill()
            proc.wait()


def test_a_worker_is_a_child_of_the_server_of_this_user():
    child = subprocess.Popen(["sleep", "300"])
    try:
        assert _forward.is_own_child(child.pid, os.getpid())
        assert not _forward.is_own_child(child.pid, os.getppid())
        assert not _forward.is_own_child(os.getpid(), os.getpid())
        assert not _forward.is_own_child(-1, os.getpid()) and not _forward.is_own_child(0, 0)
    finally:
        child.kill()
        child.wait()
    if os.getuid() == 0:  # a child of this process of another user
        other = subprocess.Popen(["sleep", "300"], user=NOBODY)
        try:
            assert not _forward.is_own_child(other.pid, os.getpid())
        finally:
            other.kill()
            other.wait()


def _as_fd_3(fd: int) -> None:
    """``fd`` as the first socket systemd passes (fd 3), left open across exec."""
    os.dup2(fd, 3)
    os.set_inheritable(3, True)


def test_under_a_service_manager_the_server_listens_as_itself(tmp_path):
    """systemd's user manager listens on the socket and passes it to `viper serve`: the server listens
    again, so that its clients read its pid and pass their signals to its workers; a client that
    connected before (it read the manager's pid) is refused, and runs its command itself."""
    sock = _folder(tmp_path / "run", 0o700) / "commands.sock"
    manager = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    manager.bind(str(sock))
    manager.listen(16)
    early = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    early.connect(str(sock))
    assert _forward.peer_credentials(early)[0] == os.getpid()
    log = tmp_path / "serve.log"
    fd = manager.fileno()
    with log.open("w") as err:
        proc = subprocess.Popen(["sh", "-c", 'LISTEN_PID=$$ LISTEN_FDS=1 exec "$@"', "sh", *VIPER,
                                 "--log-level", "debug", "serve"], stdout=subprocess.DEVNULL, stderr=err,
                                env=_env(""), close_fds=False, preexec_fn=lambda: _as_fd_3(fd))
    manager.close()
    try:
        early.settimeout(60)
        assert _forward.LineReader(early).read() == {"refused": "connected before the server listened"}
        deadline = time.monotonic() + 60
        while "serving" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as late:
            late.connect(str(sock))
            assert _forward.peer_credentials(late)[0] == proc.pid
        before = len(_workers(log))
        client = subprocess.Popen([*VIPER, "render", "jacksboro", "--lat", "36.5521", "--lon", "-84.1911",
                                   "--azimuths", "36000"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                  env=_env(sock))
        while len(_workers(log)) == before:
            assert client.poll() is None and time.monotonic() < deadline + 60
            time.sleep(0.05)
        time.sleep(0.5)
        client.send_signal(signal.SIGINT)
        _, client_err = client.communicate(timeout=120)
        assert client.returncode == 130 and client_err.decode().splitlines() == ["viper render: interrupted"]
    finally:
        early.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
