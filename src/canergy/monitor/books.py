"""The supervisor's books: its status object, from ``--status-file`` or the ``--control`` socket.

A ``BooksPoller`` thread fetches the status every period and hands each result (or the reason
there is none) to a callback; the monitor never writes to either. The status file is replaced
atomically by the supervisor, so a read sees a whole file or the previous one.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from canergy.live.supervisor.control import MAX_STATUS, request


@dataclass(frozen=True, slots=True)
class BookNode:
    """What the supervisor's books say of one node."""

    state: str
    level_uj: int | None
    lost: bool
    committed: int
    aborted: int
    written_off: int
    returns: int


@dataclass(frozen=True, slots=True)
class Books:
    """One status of the supervisor, or ``error`` saying why there is none."""

    at: float
    """When it was read (the monitor's clock)."""
    source: str
    usable_uj: int = 0
    reserved_uj: int = 0
    variant: str = ""
    listen_only: bool = False
    stopping: bool = False
    nodes: dict[str, BookNode] | None = None
    lag_s: float = 0.0
    """How old the status already was when read: the file's age (the supervisor rewrites it
    every --status-period); 0 for the socket, which answers with a fresh one."""
    error: str | None = None


def _int(obj: dict[str, Any], key: str) -> int:
    value = obj.get(key)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"{key} is not an integer")
    return value


def _opt_int(obj: dict[str, Any], key: str) -> int | None:
    return None if obj.get(key) is None else _int(obj, key)


def parse_status(status: object, at: float, source: str) -> Books:
    """``Books`` from a supervisor's status object; ``ValueError`` when it is not one."""
    if not isinstance(status, dict):
        raise ValueError("not a JSON object")
    if status.get("role", "supervisor") != "supervisor" or "usable_uj" not in status:
        raise ValueError(f"not a supervisor's status (role {status.get('role')!r})")
    nodes_in = status.get("nodes")
    if not isinstance(nodes_in, dict):
        raise ValueError("nodes is not an object")
    nodes = {}
    for name, n in nodes_in.items():
        if not isinstance(n, dict):
            raise ValueError(f"node {name} is not an object")
        nodes[str(name)] = BookNode(
            state=str(n.get("state", "?")),
            level_uj=_opt_int(n, "level_uj"),
            lost=bool(n.get("lost", False)),
            committed=_int(n, "committed"),
            aborted=_int(n, "aborted"),
            written_off=_int(n, "written_off"),
            returns=_int(n, "returns"),
        )
    return Books(
        at=at,
        source=source,
        usable_uj=_int(status, "usable_uj"),
        reserved_uj=_int(status, "reserved_uj"),
        variant=str(status.get("variant", "")),
        listen_only=bool(status.get("listen_only", False)),
        stopping=bool(status.get("stopping", False)),
        nodes=nodes,
    )


def from_status_file(path: Path, at: float) -> Books:
    source = str(path)
    try:
        with open(path, "rb") as f:
            written = os.fstat(f.fileno()).st_mtime
            text = f.read(MAX_STATUS + 1)
        if len(text) > MAX_STATUS:
            raise ValueError(f"larger than {MAX_STATUS >> 20} MiB")
        books = parse_status(json.loads(text), at, source)
    except (OSError, ValueError) as exc:
        return Books(at=at, source=source, error=_reason(exc))
    return replace(books, lag_s=max(0.0, time.time() - written))


def from_control(path: Path, at: float, timeout_s: float) -> Books:
    source = str(path)
    try:
        answer = request(path, {"status": True}, timeout_s, max_answer=MAX_STATUS)
        if "error" in answer:
            raise ValueError(str(answer["error"]))
        return parse_status(answer, at, source)
    except (OSError, ValueError) as exc:
        return Books(at=at, source=source, error=_reason(exc))


def _reason(exc: Exception) -> str:
    if isinstance(exc, FileNotFoundError):
        return "no such file (is the supervisor running with it?)"
    if isinstance(exc, ConnectionRefusedError):
        return "nobody answers (is the supervisor running?)"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


class BooksPoller:
    """Calls ``fetch(now)`` every ``period_s`` in a daemon thread and passes the result on."""

    def __init__(
        self,
        fetch: Callable[[float], Books],
        period_s: float,
        on_books: Callable[[Books], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._fetch, self._period, self._on_books, self._clock = fetch, period_s, on_books, clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="canergy-books", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._on_books(self._fetch(self._clock()))
            self._stop.wait(self._period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
