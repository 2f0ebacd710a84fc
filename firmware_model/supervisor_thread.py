"""``canergy supervisor`` (its real ``main``) in a thread of this process, for the live benches
of the guarded devices on python-can's virtual bus: its books, status file and control socket in
a temporary folder, and a stop through the socket when the bench closes."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from canergy.cli import main as canergy_main
from canergy.live.supervisor.control import request


@dataclass
class SupervisorThread:
    tmp: Path
    control: Path
    result: list[int]
    """The exit status of ``main`` once it returned."""
    thread: threading.Thread

    def status(self) -> dict[str, Any] | None:
        """The last status file (None before the first, or while one is being replaced)."""
        try:
            return dict(json.loads((self.tmp / "status.json").read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def device(self, profile: str, node: int) -> dict[str, Any] | None:
        """One guarded device's part of the status."""
        status = self.status()
        if status is None:
            return None
        return dict(status["cia402"]["devices"][profile][str(node)])

    def stop(self) -> dict[str, Any]:
        """Stop the supervisor through its socket; its last status (it must exit 0)."""
        request(self.control, {"stop": True}, 30)
        self.thread.join(timeout=60)
        final = self.status()
        assert final is not None and self.result == [0], self.result
        return final


@contextlib.contextmanager
def supervisor_thread(tmp: Path, *args: str) -> Iterator[SupervisorThread]:
    """``canergy supervisor ARGS``, its books (unless ``ARGS`` name a file of their own), status
    file (every 50 ms) and control socket in ``tmp``; stopped, if still running, when the block
    ends."""
    control = tmp / "ctl.sock"
    argv = [
        *("supervisor", "--state", str(tmp / "s.json"), *args, "--no-fsync"),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(control)),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(canergy_main(argv)), daemon=True)
    thread.start()
    try:
        yield SupervisorThread(tmp, control, result, thread)
    finally:
        if thread.is_alive() and control.exists():
            request(control, {"stop": True}, 30)
        thread.join(timeout=60)
