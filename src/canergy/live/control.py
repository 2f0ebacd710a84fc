"""A running supervisor's control socket (UNIX stream, one JSON line each way).

Request ``{"grant": {"node": 5, "amount_uj": 2000000}}`` → reply once the transaction ends:
``{"node": 5, "tx": 12, "outcome": "COMMITTED", "amount_uj": 2000000}`` or ``{"error": ...}``.
``{"status": true}`` answers the status object; ``{"stop": true}`` stops as SIGTERM does.
Requests are queued for the supervisor's own loop; nothing here touches its state.
"""

from __future__ import annotations

import contextlib
import json
import queue
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

Reply = Callable[[dict[str, Any]], None]
MAX_REQUEST = 4096


class ControlServer:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.requests: queue.Queue[tuple[dict[str, Any], Reply]] = queue.Queue()
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(str(path))
        self._sock.listen(8)
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
        """One client's request, in its own thread: a slow client delays no one else."""
        conn.settimeout(5)
        try:
            line = conn.makefile("rb").readline(MAX_REQUEST)
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("request must be a JSON object")
        except (OSError, ValueError) as exc:
            _answer(conn, {"error": f"bad request: {exc}"})
            return
        self.requests.put((request, _replier(conn)))

    def pending(self) -> list[tuple[dict[str, Any], Reply]]:
        out = []
        while True:
            try:
                out.append(self.requests.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept()
        self._sock.close()
        self._thread.join(timeout=5)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def _replier(conn: socket.socket) -> Reply:
    def reply(result: dict[str, Any]) -> None:
        _answer(conn, result)

    return reply


def _answer(conn: socket.socket, result: dict[str, Any]) -> None:
    with contextlib.suppress(OSError):
        conn.sendall((json.dumps(result) + "\n").encode())
    conn.close()


def request(path: Path, payload: dict[str, Any], timeout_s: float) -> dict[str, Any]:
    """Send one request to a running supervisor and wait for its answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        sock.sendall((json.dumps(payload) + "\n").encode())
        line = sock.makefile("rb").readline(MAX_REQUEST)
    if not line:
        raise ConnectionError("the supervisor closed the connection without an answer")
    answer = json.loads(line)
    if not isinstance(answer, dict):
        raise ValueError("malformed answer")
    return answer
