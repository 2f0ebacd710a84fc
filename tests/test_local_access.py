"""Local access to the supervisor's control socket and to key files (security second pass,
items 10 and 11).

The control socket is 0600 whatever the umask, and every connection's peer must be the
supervisor's own uid or root: run as root here, a forked child that drops to ``nobody`` is
refused. A key file must be a regular file of a bounded size, read without blocking: a FIFO,
``/dev/zero`` or a huge file is refused at once, with one line naming the file, by every program
that reads keys.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from canergy.auth.keys import KEY_FILE_MAX, KeyFileError, load_key, new_master, write_key
from canergy.live.supervisor.control import ControlServer, request

NOBODY = 65534
STRANGER = 65533  # a second unprivileged uid (need not exist in /etc/passwd)
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="changes uid: needs root")


def _as_user(uid: int, action: Callable[[], Any]) -> dict[str, Any]:
    """``{"ok": action()}`` or ``{"raised": name, "message": ...}``, from a forked child that
    dropped to ``uid`` (group ``uid``, no supplementary groups) before calling ``action``."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        try:
            os.close(read)
            os.setgroups([])
            os.setgid(uid)
            os.setuid(uid)
            try:
                result: dict[str, Any] = {"ok": action()}
            except Exception as exc:
                result = {"raised": type(exc).__name__, "message": str(exc)}
            os.write(write, json.dumps(result).encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        data = pipe.read()
    os.waitpid(pid, 0)
    return dict(json.loads(data))


def _request_as(uid: int, path: Path, payload: dict[str, Any]) -> dict[str, Any]:
    return _as_user(uid, lambda: request(path, payload, 5))


@pytest.fixture
def shared_dir() -> Iterator[Path]:
    """A directory every uid can reach and write (pytest's tmp_path is 0700)."""
    with tempfile.TemporaryDirectory(prefix="canergy-access-") as name:
        os.chmod(name, 0o1777)
        yield Path(name)


# --- item 10: the control socket --------------------------------------------------------------


def test_the_control_socket_is_0600_under_umask_000(tmp_path: Path) -> None:
    old = os.umask(0)
    try:
        server = ControlServer(tmp_path / "ctl.sock")
    finally:
        os.umask(old)
    try:
        mode = os.lstat(tmp_path / "ctl.sock").st_mode
        assert stat.S_ISSOCK(mode) and stat.S_IMODE(mode) == 0o600, oct(mode)
    finally:
        server.close()
    assert os.umask(old) == old  # the umask is as it was


def _answer_all(server: ControlServer, until: float, done: Callable[[], bool]) -> None:
    """Answer every request with what it asked, until ``done()`` or the deadline."""
    while time.monotonic() < until and not done():
        for req, reply in server.pending():
            reply({"served": req})
        time.sleep(0.01)


def _ask_root(server: ControlServer, path: Path) -> list[dict[str, Any]]:
    """A status request from this process (root here), answered by ``server``'s queue."""
    served: list[dict[str, Any]] = []
    ask = threading.Thread(target=lambda: served.append(request(path, {"status": True}, 5)))
    ask.start()
    _answer_all(server, time.monotonic() + 5, lambda: not ask.is_alive())
    return served


@as_root
def test_root_is_served_and_another_uid_is_refused_and_counted(
    shared_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = shared_dir / "ctl.sock"
    server = ControlServer(path)
    try:
        refused = _request_as(NOBODY, path, {"stop": True})
        assert refused["raised"] == "PermissionError"  # 0600: nobody cannot even connect
        os.chmod(path, 0o666)  # widened by hand: the peer check still refuses
        for _ in range(2):
            refused = _request_as(NOBODY, path, {"stop": True})
            assert "refused" in refused["ok"]["error"] and "65534" in refused["ok"]["error"]
        assert server.pending() == [] and server.refused == {NOBODY: 2}
        assert len([r for r in caplog.records if "uid 65534" in r.getMessage()]) == 1
        assert _ask_root(server, path) == [{"served": {"status": True}}]
    finally:
        server.close()


@as_root
def test_the_supervisors_own_uid_is_served_when_it_is_not_root(shared_dir: Path) -> None:
    """A server run by ``nobody`` serves ``nobody`` and root, refuses another user."""
    path = shared_dir / "ctl.sock"
    ready, done = shared_dir / "ready", shared_dir / "done"

    def serve() -> int:
        server = ControlServer(path)
        os.chmod(path, 0o666)
        ready.touch()
        _answer_all(server, time.monotonic() + 20, done.exists)
        refusals = server.refused
        server.close()
        return sum(refusals.values())

    pid = os.fork()
    if pid == 0:
        try:
            os.setgroups([])
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            os._exit(serve())
        finally:
            os._exit(99)
    try:
        deadline = time.monotonic() + 10
        while not ready.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert request(path, {"status": 1}, 5) == {"served": {"status": 1}}  # root
        own = _request_as(NOBODY, path, {"status": 2})
        assert own == {"ok": {"served": {"status": 2}}}
        other = _request_as(STRANGER, path, {"status": 3})
        assert "refused" in other.get("ok", {}).get("error", ""), other
    finally:
        done.touch()
        _, code = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(code) == 1  # one refusal, counted by the server


def _canergy(*args: str) -> list[str]:
    return [sys.executable, "-m", "canergy", *args]


@as_root
def test_nobody_can_neither_grant_nor_stop_a_supervisor_run_under_umask_000(
    shared_dir: Path,
) -> None:
    path = shared_dir / "ctl.sock"
    argv = ["supervisor", "-i", "virtual", "-c", f"access-{uuid.uuid4().hex}", "--nodes", "1"]
    argv += ["--initial", "10J", "--state", str(shared_dir / "s.json"), "--no-fsync"]
    sup = subprocess.Popen(
        _canergy(*argv, "--control", str(path)), umask=0, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 30
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert stat.S_IMODE(os.lstat(path).st_mode) == 0o600
        grant = {"grant": {"node": 1, "amount_uj": 3_000_000}}
        assert _request_as(NOBODY, path, grant)["raised"] == "PermissionError"
        os.chmod(path, 0o666)
        for payload in (grant, {"stop": True}):
            answer = _request_as(NOBODY, path, payload)
            assert "refused" in answer.get("ok", {}).get("error", ""), answer
        assert sup.poll() is None
        status = request(path, {"status": True}, 10)
        assert status["usable_uj"] == 10_000_000
        assert status["control_refused"] == {str(NOBODY): 2}  # the grant and the stop
        assert request(path, {"stop": True}, 10) == {"stopping": True}
        _, err = sup.communicate(timeout=30)
    finally:
        if sup.poll() is None:
            sup.send_signal(signal.SIGKILL)
            sup.wait()
    assert sup.returncode == 0, err
    assert "refused" in err and "uid 65534" in err and "Traceback" not in err, err


@as_root
def test_refused_peers_that_hang_up_or_stay_silent_do_not_stop_the_server(
    shared_dir: Path,
) -> None:
    path = shared_dir / "ctl.sock"
    server = ControlServer(path)
    os.chmod(path, 0o666)

    def hang_up() -> str:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(str(path))
            s.shutdown(socket.SHUT_WR)  # no request at all: still the refusal
            return s.recv(4096).decode()

    try:
        assert "refused" in _as_user(NOBODY, hang_up)["ok"]
        for _ in range(3):  # gone before the answer
            _as_user(NOBODY, lambda: socket.socket(socket.AF_UNIX).connect(str(path)))
        deadline = time.monotonic() + 5  # each connection is refused in its own thread
        while server.refused != {NOBODY: 4} and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.refused == {NOBODY: 4}
        assert _ask_root(server, path) == [{"served": {"status": True}}]
    finally:
        server.close()


# --- item 11: key files -----------------------------------------------------------------------


def _bad_key_file(kind: str, folder: Path) -> Path:
    if kind == "/dev/zero":
        return Path("/dev/zero")
    path = folder / f"{kind}.key"
    if kind == "fifo":
        os.mkfifo(path, 0o600)
    elif kind == "oversize":  # a valid key, then comments up to one byte too many
        write_key(path, new_master(1))
        with open(path, "a", encoding="ascii") as f:
            f.write("#" * (KEY_FILE_MAX + 1 - path.stat().st_size))
    elif kind == "directory":
        path.mkdir(mode=0o700)
    return path


BAD_KEYS = {
    "fifo": "not a regular file (a FIFO)",
    "/dev/zero": "not a regular file (a character device)",
    "oversize": f"{KEY_FILE_MAX + 1} bytes, more than a key file holds ({KEY_FILE_MAX})",
    "directory": "not a regular file (a directory)",
}


@pytest.mark.parametrize("kind", ["fifo", "oversize", "directory"])  # /dev/zero: in a child
def test_load_key_refuses_what_is_not_a_small_regular_file(kind: str, tmp_path: Path) -> None:
    path = _bad_key_file(kind, tmp_path)
    errors: list[Exception] = []

    def load() -> None:
        try:
            load_key(path)
        except Exception as exc:
            errors.append(exc)

    reader = threading.Thread(target=load)
    reader.start()
    reader.join(timeout=5)
    if reader.is_alive():  # blocked opening the FIFO: a writer that closes at once frees it
        with open(path, "wb"):
            pass
        reader.join()
    assert [type(e) for e in errors] == [KeyFileError] and not reader.is_alive()
    assert str(errors[0]) == f"{path}: {BAD_KEYS[kind]}"


def _limited() -> None:
    """A child's memory limit: a key reader that reads /dev/zero fails fast, not at 1.3 GB."""
    resource.setrlimit(resource.RLIMIT_DATA, (512 << 20, 512 << 20))


def _program(name: str, key: Path, tmp: Path) -> list[str]:
    bus = ["-i", "virtual", "-c", f"keys-{uuid.uuid4().hex}"]
    if name == "supervisor":
        return _canergy("supervisor", *bus, "--nodes", "1", "--state", str(tmp / "s.json"))
    if name == "keys --master":
        return _canergy("keys", "--master", str(key), "--nodes", "1", "-o", str(tmp / "out"))
    return [sys.executable, "-m", "firmware_model", "--node", "1", *bus, "--nv", str(tmp / "n")]


@pytest.mark.parametrize("kind", ["fifo", "/dev/zero", "oversize"])
@pytest.mark.parametrize("program", ["supervisor", "keys --master", "firmware_model"])
def test_every_key_reader_refuses_at_once(program: str, kind: str, tmp_path: Path) -> None:
    key = _bad_key_file(kind, tmp_path)
    argv = _program(program, key, tmp_path)
    if program != "keys --master":
        argv += ["--auth", str(key)]
    run = subprocess.run(
        argv, capture_output=True, text=True, timeout=20, cwd=tmp_path, preexec_fn=_limited
    )
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and "Traceback" not in run.stderr, run.stderr
    assert f"{key}: {BAD_KEYS[kind]}" in run.stderr, run.stderr
    assert not (tmp_path / "s.json").exists() and not (tmp_path / "out").exists()


def test_a_good_key_file_still_loads_and_the_old_checks_hold(tmp_path: Path) -> None:
    path = tmp_path / "m.key"
    key = new_master(7)
    write_key(path, key)
    assert load_key(path) == key
    link = tmp_path / "link.key"
    link.symlink_to(path)  # a symlink to a key file is read as the file
    assert load_key(link) == key
    path.chmod(0o640)
    with pytest.raises(KeyFileError, match="chmod 600"):
        load_key(path)
    path.chmod(0o600)
    path.write_text(path.read_text() + "extra=1\n")
    with pytest.raises(KeyFileError, match="holds exactly"):
        load_key(path)
