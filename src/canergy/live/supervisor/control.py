"""A running supervisor's control socket (UNIX stream, one JSON line each way).

Request ``{"grant": {"node": 5, "amount_uj": 2000000}}`` → reply once the transaction ends:
``{"node": 5, "tx": 12, "outcome": "COMMITTED", "amount_uj": 2000000}`` or ``{"error": ...}``.
A supervisor over several buses (``--bus``) names its nodes ``"node": "can1/5"`` (a plain number
only when it has one bus). ``{"status": true}`` answers the status object; ``{"stop": true}``
stops as SIGTERM does. Requests are queued for the supervisor's own loop; nothing here touches
its state.

The server never removes anything but a socket: a stale one left at its path by a supervisor that
died (nobody answers there), and at close the one it created itself.

Only the supervisor's own user and root may use it: the socket is created with mode 0600
whatever the umask, and each connection's peer (``SO_PEERCRED``) must have the supervisor's uid
or be root; others get ``{"error": "refused: ..."}``, counted per uid in ``refused`` and logged
once per uid. (Where the platform has no ``SO_PEERCRED`` the mode alone guards it.)
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import logging
import os
import queue
import secrets
import socket
import stat
import struct
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

Reply = Callable[[dict[str, Any]], None]
MAX_REQUEST = 4096
MAX_STATUS = 8 << 20
"""Largest status answer accepted (127 nodes take about 60 kB)."""
MAX_SOCKET_PATH = 107
"""Longest UNIX socket path in bytes (Linux ``sun_path`` holds 108 with the final NUL)."""


def check_control_path(path: Path, option: str = "--control") -> bool:
    """Refuse (``ValueError`` naming ``option``) a path that may not become the control socket:
    too long, something other than a socket is there, or a supervisor answers on it. True when
    a stale socket is there, which the server may replace."""
    size = len(os.fsencode(path))
    if size > MAX_SOCKET_PATH:
        raise ValueError(
            f"{option} {path}: too long for a UNIX socket ({size} bytes, at most "
            f"{MAX_SOCKET_PATH}); choose a shorter path"
        )
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False
    if not stat.S_ISSOCK(st.st_mode):
        raise ValueError(
            f"{option} {path} exists and is not a socket; refusing to replace it "
            "(choose another path)"
        )
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1)
        try:
            probe.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            return True  # nobody listens: left behind by a supervisor that died
        except OSError as exc:
            raise ValueError(f"{option} {path}: cannot tell who listens there ({exc})") from exc
    raise ValueError(f"{option} {path}: a supervisor is already listening there")


_UMASK = threading.Lock()


def _listening(path: Path) -> socket.socket:
    """A socket listening at ``path``, mode 0600 whatever the umask: umask 077 during bind (it
    is the process's: a file another thread creates in that instant comes out narrower, never
    wider), so no one else can connect at any moment. It is bound and listening under a
    temporary name in the same directory and then renamed to ``path`` without replacing
    anything there, so a client that connects as soon as the file appears is never refused
    (where the temporary name would be too long for a socket, it is bound at ``path`` itself).
    ``FileExistsError`` when something took ``path`` meanwhile."""
    temp = path.with_name(f".canergy-{secrets.token_hex(4)}")
    if len(os.fsencode(temp)) > MAX_SOCKET_PATH:
        temp = path
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        with _UMASK:
            old = os.umask(0o077)
            try:
                sock.bind(str(temp))
                sock.listen(8)
            finally:
                os.umask(old)
        os.chmod(temp, 0o600)
        if temp != path:
            try:
                _rename_no_replace(temp, path)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    temp.unlink()
    except OSError:
        sock.close()
        raise
    return sock


def _rename_no_replace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, ``FileExistsError`` where ``dst`` exists: renameat2 with
    RENAME_NOREPLACE where the C library has it, else a hard link and an unlink of ``src``
    (which leaves ``src`` in place when ``dst`` exists)."""
    libc = ctypes.CDLL(None, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is not None:
        at_fdcwd, noreplace = -100, 1
        renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p] * 2 + [ctypes.c_uint]
        if renameat2(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), noreplace) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.EINVAL, errno.ENOSYS):  # the file system or kernel lacks the flag
            raise OSError(err, os.strerror(err), str(dst))
    os.link(src, dst)
    os.unlink(src)


def peer_credentials(conn: socket.socket) -> tuple[int, int] | None:
    """The connected peer's (pid, uid), or None where the platform cannot tell."""
    option = getattr(socket, "SO_PEERCRED", None)
    if option is None:
        return None
    pid, uid, _gid = struct.unpack("iII", conn.getsockopt(socket.SOL_SOCKET, option, 12))
    return pid, uid


class ControlServer:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.requests: queue.Queue[tuple[dict[str, Any], Reply]] = queue.Queue()
        self.owner = os.geteuid()
        self.refused: dict[int, int] = {}
        """Connections refused, by peer uid (-1: credentials unreadable)."""
        self._refused_lock = threading.Lock()
        self._closed = False
        self._closed_lock = threading.Lock()
        """Held while a request is queued and while the server closes: a request taken in as
        the supervisor ends is answered, never left waiting for a loop that has stopped."""
        if check_control_path(path):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        try:
            self._sock = _listening(path)
        except OSError as exc:
            if isinstance(exc, FileExistsError) or exc.errno == errno.EADDRINUSE:
                taken = f"--control {path}: another process took it as it started"
                raise ValueError(taken) from exc
            raise
        st = os.lstat(path)
        self._made = (st.st_dev, st.st_ino)
        self._thread = threading.Thread(target=self._serve, name="canergy-control", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed
            threading.Thread(target=self._read, args=(conn,), daemon=True).start()

    def _read(self, conn: socket.socket) -> None:
        """One client's request, in its own thread: a slow client delays no one else. A refused
        peer's request is read too (never parsed): it then gets its refusal, not EPIPE."""
        conn.settimeout(5)
        refusal = self._refusal(conn)
        try:
            line = conn.makefile("rb").readline(MAX_REQUEST)
            if refusal is not None:
                _answer(conn, refusal)
                return
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("request must be a JSON object")
        except (OSError, ValueError) as exc:
            _answer(conn, refusal or {"error": f"bad request: {exc}"})
            return
        with self._closed_lock:
            if not self._closed:
                self.requests.put((request, _replier(conn)))
                return
        _answer(conn, STOPPED)

    def _refusal(self, conn: socket.socket) -> dict[str, Any] | None:
        """None for the supervisor's user or root; for anyone else the answer, counted, and
        logged the first time per uid."""
        try:
            peer = peer_credentials(conn)
        except OSError as exc:
            peer, why = (-1, -1), f"cannot tell who connected ({exc})"
        else:
            if peer is None or peer[1] in (self.owner, 0):
                return None
            why = f"uid {peer[1]} may not use this socket (only uid {self.owner} or root)"
        pid, uid = peer
        with self._refused_lock:
            count = self.refused[uid] = self.refused.get(uid, 0) + 1
        if count == 1:
            log.warning(
                "control socket %s: refused pid %d: %s; uid %d's next refusals are only counted",
                self.path,
                pid,
                why,
                uid,
            )
        return {"error": f"refused: {why}"}

    def pending(self) -> list[tuple[dict[str, Any], Reply]]:
        out = []
        while True:
            try:
                out.append(self.requests.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        """Stop listening; every request taken in and not answered gets ``STOPPED``."""
        with self._closed_lock:
            self._closed = True
        for _, reply in self.pending():
            reply(STOPPED)
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept()
        self._sock.close()
        self._thread.join(timeout=5)
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if stat.S_ISSOCK(st.st_mode) and (st.st_dev, st.st_ino) == self._made:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()  # ours; anything that replaced it stays


STOPPED: dict[str, Any] = {"error": "the supervisor has stopped"}
"""The answer to a request the supervisor took in as it ended."""


def _replier(conn: socket.socket) -> Reply:
    def reply(result: dict[str, Any]) -> None:
        _answer(conn, result)

    return reply


def _answer(conn: socket.socket, result: dict[str, Any]) -> None:
    with contextlib.suppress(OSError):
        conn.sendall((json.dumps(result) + "\n").encode())
    conn.close()


class NoSupervisor(ConnectionError):
    """Nothing serves the control socket: no file at its path, or a socket nobody listens on."""


class NoAnswer(TimeoutError):
    """A supervisor took the request but did not answer it in time."""


def request(
    path: Path, payload: dict[str, Any], timeout_s: float, max_answer: int = MAX_REQUEST
) -> dict[str, Any]:
    """Send one request to a running supervisor and wait for its answer (one line of at most
    ``max_answer`` bytes: a status takes more than a grant's outcome). ``NoSupervisor`` when
    nothing listens at ``path``, ``NoAnswer`` when the supervisor took the request and did not
    answer within ``timeout_s``."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError, NotADirectoryError) as exc:
            why = "no such file" if isinstance(exc, FileNotFoundError) else exc.strerror
            raise NoSupervisor(f"no supervisor listens on {path} ({why})") from exc
        sock.sendall((json.dumps(payload) + "\n").encode())
        try:
            line = sock.makefile("rb").readline(max_answer)
        except TimeoutError as exc:
            raise NoAnswer(
                f"the supervisor at {path} gave no answer within {timeout_s:g} s"
            ) from exc
    if not line:
        raise ConnectionError("the supervisor closed the connection without an answer")
    answer = json.loads(line)
    if not isinstance(answer, dict):
        raise ValueError("malformed answer")
    return answer
