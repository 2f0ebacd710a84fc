"""Watching python-can's ``virtual`` bus from a test: what a master sees, and waiting for it.

``Frames`` is a listener that keeps every frame with its arrival time; ``wait_for`` polls a
condition (the pytest plugin's ``until``) until it holds or fails after a generous timeout (no
test depends on tight timing).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can

from canergy.testing.run import until


def wait_for(
    condition: Callable[[], bool], timeout: float = 60.0, show: Callable[[], object] | None = None
) -> None:
    until(condition, timeout_s=timeout, show=show, period_s=0.005)


class Frames(can.Listener):
    """Every frame the master sees, with its arrival time."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, int, bytes]] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.seen.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def of(self, cob_id: int) -> list[tuple[float, bytes]]:
        with self.lock:
            return [(t, d) for t, c, d in self.seen if c == cob_id]
