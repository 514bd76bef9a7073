"""`viper serve`: commands run in a warm process give what they give in a process of their own.

A real server runs as a separate process on a real Unix socket; the client is the `viper` command
run as a user runs it, with the server's socket in VIPER_SOCKET.
"""

from __future__ import annotations

import array
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from appliance.cli import _forward
from appliance.cli.serve import _refusal

VIPER = [sys.executable, "-m", "appliance.cli.main"]
RENDER = ["render", "jacksboro", "--lat", "36.5521", "--lon", "-84.1911", "--azimuths", "90"]


#: What this test process's own imports may have added to its environment (rasterio: GDAL's and PROJ's CA
#: bundles).  A user's shell, where the server and the clients start, has none of it.
ADDED_BY_IMPORTS = ("GDAL_CURL_CA_BUNDLE", "PROJ_CURL_CA_BUNDLE")


def _env(sock: Path | str, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ADDED_BY_IMPORTS}
    env.update(VIPER_SOCKET=str(sock), **extra)
    return env


def _start_server(where: Path) -> tuple[subprocess.Popen, Path]:
    """A `viper --log-level debug serve` on a socket in ``where``, once it serves; its stderr in where/serve.log."""
    sock = where / "run" / "commands.sock"
    with (where / "serve.log").open("w") as log:
        proc = subprocess.Popen([*VIPER, "--log-level", "debug", "serve", "--socket", str(sock)],
                                stdout=subprocess.DEVNULL, stderr=log, env=_env(""))
    deadline = time.monotonic() + 60
    while "serving" not in (where / "serve.log").read_text():
        assert proc.poll() is None, (where / "serve.log").read_text()
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.1)
    return proc, sock


def _living_with(text: str) -> list[int]:
    """The processes alive (not zombies) whose command line holds ``text``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if text in cmdline and state != "Z":
            found.append(int(entry.name))
    return found


def _stop_server(proc: subprocess.Popen, sock: Path) -> None:
    """Stop it as systemd does (SIGTERM): it ends cleanly, removes its socket and leaves no worker behind."""
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 0
    assert not sock.exists(), "the server left its socket behind"
    assert _living_with(str(sock)) == [], "a worker outlived the server"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A running `viper --log-level debug serve` and its socket; its stderr lines in a file."""
    where = tmp_path_factory.mktemp("serve")
    proc, sock = _start_server(where)
    yield sock, where / "serve.log"
    _stop_server(proc, sock)


def _workers(log: Path) -> list[str]:
    return [line for line in log.read_text().splitlines() if "worker " in line]


def _run(args: list[str], sock: Path | str, cwd: Path | None = None, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([*VIPER, *args], capture_output=True, env=_env(sock, **env), cwd=cwd, timeout=300)


def test_a_forwarded_command_gives_the_same_output_as_one_run_in_process(server):
    sock, log = server
    before = len(_workers(log))
    warm = _run(RENDER, sock)
    alone = _run(RENDER, "")
    assert warm.returncode == alone.returncode == 0, warm.stderr
    assert warm.stdout == alone.stdout and len(warm.stdout.splitlines()) == 91
    assert warm.stderr == alone.stderr
    ran = _workers(log)[before:]
    assert len(ran) == 1 and "viper render jacksboro" in ran[0]


def test_the_worker_takes_the_clients_folder_and_umask(server, tmp_path):
    sock, log = server
    done = subprocess.run(["sh", "-c", 'umask 077 && exec "$@"', "sh", *VIPER, *RENDER, "--out", "sky.csv"],
                          capture_output=True, env=_env(sock), cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "sky.csv"
    assert (out.stat().st_mode & 0o777) == 0o600
    assert out.read_bytes() == _run(RENDER, "").stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sky.csv"]


def test_errors_and_exit_statuses_come_through_as_in_process(server, tmp_path):
    sock, log = server
    before = len(_workers(log))
    for args in (["estimate", str(tmp_path / "absent.viperdb"), str(tmp_path / "absent.csv")],
                 ["render", "jacksboro", "--lat", "95", "--lon", "0"],
                 ["render", "jacksboro", "--no-such-option"]):
        warm, alone = _run(args, sock), _run(args, "")
        assert warm.returncode == alone.returncode != 0
        assert warm.stderr == alone.stderr and len(warm.stderr.splitlines()) == 1, warm.stderr
    assert len(_workers(log)) - before == 3


def test_a_command_whose_numba_settings_differ_runs_in_process(server):
    sock, log = server
    before = len(_workers(log))
    done = _run(RENDER, sock, NUMBA_NUM_THREADS="1")
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 91
    assert len(_workers(log)) == before
    assert "refused a command: numba's" in log.read_text()


def _long_render_running(sock: Path, log: Path) -> subprocess.Popen:
    """A client whose long render (36,000 azimuths) a worker of the server has started."""
    before = len(_workers(log))
    proc = subprocess.Popen([*VIPER, "render", "jacksboro", "--lat", "36.5521", "--lon", "-84.1911",
                             "--azimuths", "36000"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env=_env(sock))
    deadline = time.monotonic() + 60
    while len(_workers(log)) == before:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.05)
    time.sleep(0.5)
    return proc


def test_an_interrupt_reaches_the_worker(server):
    proc = _long_render_running(*server)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130
    assert err.decode().strip().splitlines() == ["viper render: interrupted"]


def test_a_socket_nobody_listens_on_leaves_the_command_in_process(tmp_path, monkeypatch):
    stale = tmp_path / "commands.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(stale))
    s.close()
    monkeypatch.setenv("VIPER_SOCKET", str(stale))
    assert _forward.forward(["render", "jacksboro"], "render") is None
    done = _run(RENDER, stale)
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 91
    # only the forwarded commands are ever sent
    assert _forward.forward(["precompute", "jacksboro"], "precompute") is None


def test_a_second_server_on_the_same_socket_is_refused(server):
    sock, _ = server
    done = _run(["serve", "--socket", str(sock)], "")
    assert done.returncode != 0
    assert done.stderr.decode().strip() == f"viper serve: error: {sock}: another server is listening there"


def test_requests_the_server_must_refuse():
    identity = _forward.code_identity()
    fixed = _forward.fixed_environment(dict(os.environ))
    good = {"argv": ["render"], "env": dict(os.environ), "cwd": "/", "umask": 0o22, "code": identity}
    assert _refusal(good, os.getuid(), [0, 1, 2], identity, fixed) is None
    assert _refusal(good, os.getuid() + 1, [0, 1, 2], identity, fixed) == "another user's command"
    assert _refusal(good, os.getuid(), [0, 1], identity, fixed) is not None
    assert _refusal(dict(good, code=identity + "0"), os.getuid(), [0, 1, 2], identity, fixed) \
        == "the installed code changed since the server started"
    assert _refusal(dict(good, argv="render"), os.getuid(), [0, 1, 2], identity, fixed) is not None
    assert _refusal(dict(good, env={"A": 1}), os.getuid(), [0, 1, 2], identity, fixed) is not None


def test_the_code_identity_moves_when_a_module_changes(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("")
    (pkg / "sub" / "b.py").write_text("")
    monkeypatch.setattr(_forward, "PACKAGE", pkg)
    first = _forward.code_identity()
    os.utime(pkg / "sub" / "b.py", ns=(time.time_ns() + 10**9, time.time_ns() + 10**9))
    assert _forward.code_identity() != first


def test_a_client_that_sends_nothing_holds_up_no_other(server):
    sock, log = server
    silent = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    silent.connect(str(sock))
    try:
        # well within the time a silent client is given to send its request (10 s)
        done = subprocess.run([*VIPER, *RENDER], capture_output=True, env=_env(sock), timeout=8)
        assert done.returncode == 0 and len(done.stdout.splitlines()) == 91
    finally:
        silent.close()
    deadline = time.monotonic() + 10
    while "refused a command: not a request with three standard streams" not in log.read_text():
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_a_terminated_command_ends_as_it_would_alone(server):
    proc = _long_render_running(*server)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGTERM and err == b""


def test_a_removed_working_folder_gives_what_it_gives_in_process(server, tmp_path):
    sock, _ = server
    script = 'mkdir "$1" && cd "$1" && rmdir "$1" && shift && exec "$@"'
    warm, alone = (subprocess.run(["sh", "-c", script, "sh", str(tmp_path / "gone"), *VIPER, *RENDER, "--out",
                                   "sky.csv"], capture_output=True, env=_env(s), timeout=300) for s in (sock, ""))
    assert warm.returncode == alone.returncode != 0
    assert warm.stderr == alone.stderr and len(warm.stderr.splitlines()) == 1, warm.stderr


def _refused_for_its_folder(sock: Path, folder: Path) -> dict:
    """A request as the client sends it, for ``folder``; the server's reply."""
    request = {"argv": RENDER, "cwd": str(folder), "env": _env(""),
               "umask": 0o022, "code": _forward.code_identity()}
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.connect(str(sock))
        conn.sendmsg([json.dumps(request).encode() + b"\n"],
                     [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [0, 1, 2]))])
        reply = _forward.LineReader(conn).read()
    assert reply is not None
    return reply


def test_a_folder_the_server_cannot_enter_is_refused_before_anything_runs(server, tmp_path):
    """A folder the server cannot enter (here one that is gone): the answer is a refusal, so that
    the client runs the command itself."""
    reply = _refused_for_its_folder(server[0], tmp_path / "gone")
    assert reply["refused"].startswith("its folder: ")
    assert "No such file or directory" in reply["refused"]


def test_a_server_stopped_just_after_a_command_leaves_no_worker_behind(tmp_path):
    """A refusal comes back at once, and the server forks the next spare worker as it goes: stopped
    right then, the new spare must end with it rather than wait for a connection forever."""
    for k in range(3):
        where = tmp_path / f"s{k}"
        where.mkdir()
        proc, sock = _start_server(where)
        try:
            assert "refused" in _refused_for_its_folder(sock, tmp_path / "gone")
        finally:
            _stop_server(proc, sock)
