"""A python-can bus wrapper that loses, duplicates, delays, reorders and corrupts what it sends.

For tests and soak runs on a bench: wrap a node's bus and its outgoing frames meet the same
seeded ``FaultInjector`` the demo uses, on the wall clock. Delayed copies are put on the real
bus by whichever of ``send``/``recv`` runs after they fall due.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from typing import Any

import can

from canergy.faults import FaultInjector


class FaultyBus(can.BusABC):
    def __init__(self, inner: can.BusABC, injector: FaultInjector, **kwargs: Any) -> None:
        self.inner = inner
        self.injector = injector
        self._held: list[tuple[float, int, can.Message]] = []
        self._seq = itertools.count()
        self._lock = threading.Lock()
        self.channel_info = f"faulty({inner.channel_info})"
        super().__init__(channel=inner.channel_info, can_filters=None, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        now = time.monotonic()
        with self._lock:
            for delay_us, data in self.injector.fate(bytes(msg.data)):
                copy = can.Message(
                    arbitration_id=msg.arbitration_id,
                    is_extended_id=msg.is_extended_id,
                    is_remote_frame=msg.is_remote_frame,
                    data=data,
                )
                heapq.heappush(self._held, (now + delay_us / 1e6, next(self._seq), copy))
        self._release(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._release(None)
        if self._held:  # wake up in time to release what is due
            wait = max(0.0, self._held[0][0] - time.monotonic())
            timeout = wait if timeout is None else min(timeout, wait)
        return self.inner.recv(timeout), False

    def _release(self, timeout: float | None) -> None:
        now = time.monotonic()
        while True:
            with self._lock:
                if not self._held or self._held[0][0] > now:
                    return
                _, _, frame = heapq.heappop(self._held)
            self.inner.send(frame, timeout)

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()
