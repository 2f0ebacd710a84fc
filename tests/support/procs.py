"""Separate processes for a test, and reading what they write.

``Procs`` starts and stops a test's processes (the pytest plugin's ``Process``), each with its
stderr in a file of the test's directory; ``procs`` is the fixture (one ``Procs`` in
``tmp_path``, whatever still runs killed at the end). ``python`` is an argv for this
interpreter, ``status`` reads a status file a process writes, ``wait`` polls until a condition
holds. The vcan suite and the Zenoh gateway test run their processes this way.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from canergy.testing.bus import Process
from canergy.testing.run import until

DUMP_S = 10
"""How long a process that would not stop has to write its stacks (SIGABRT) before SIGKILL."""


class Procs:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        """The pytest plugin's ``Process`` (stderr in ``NAME.stderr``, stdout discarded)."""
        proc = Process(name, argv, self.tmp).popen
        self.procs[name] = proc
        return proc

    def stderr(self, name: str) -> str:
        return (self.tmp / f"{name}.stderr").read_text(errors="replace")

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout: float = 60) -> int:
        """Signal it and wait; one that outlives ``timeout`` is killed before the test fails
        (left running, a supervisor bridging two buses doubled the next test's frames), by
        SIGABRT first: ``python`` runs it under faulthandler, which then writes every thread's
        stack to its stderr, and the failure shows it."""
        proc = self.procs.pop(name)
        proc.send_signal(sig)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)
            try:
                proc.wait(DUMP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(30)
        raise AssertionError(
            f"{name} did not end within {timeout} s of signal {sig}; its stderr (the stacks: "
            f"faulthandler on SIGABRT):\n{self.stderr(name)[-6000:]}"
        )

    def close(self) -> None:
        for proc in self.procs.values():
            proc.kill()
            proc.wait(30)


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Procs]:
    p = Procs(tmp_path)
    yield p
    p.close()


def python(*args: str) -> list[str]:
    """This interpreter, under faulthandler (a fatal signal, SIGABRT from ``Procs.stop`` too,
    writes every thread's stack to stderr)."""
    return [sys.executable, "-X", "faulthandler", *args]


def status(path: Path) -> dict[str, Any]:
    for _ in range(50):  # the writer replaces the file atomically; it may not exist yet
        try:
            data: dict[str, Any] = json.loads(path.read_text())
            return data
        except FileNotFoundError:
            time.sleep(0.1)
    raise AssertionError(f"{path} never appeared")


def wait(
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = 120,
    show: Callable[[], object] | None = None,
) -> None:
    """Poll ``condition`` (the pytest plugin's ``until``, every 0.2 s); on timeout fail naming
    ``what`` and what ``show`` returns then."""
    until(condition, what, timeout_s, show, period_s=0.2)
