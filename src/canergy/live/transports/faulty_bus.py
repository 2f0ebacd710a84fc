"""A python-can bus wrapper that loses, duplicates, delays, reorders and corrupts what it sends.

For tests and soak runs on a bench: wrap a node's bus and its outgoing frames meet the same
seeded ``FaultInjector`` the demo uses, on the wall clock. Delayed copies are put on the real
bus by whichever of ``send``/``recv`` runs after they fall due. (Between two buses, with
partitions and a capture: ``canergy.bridge``, whose hold queue and frame copy this uses.)
"""

from __future__ import annotations

import threading
from typing import Any

import can

from canergy.bridge.link import copy_frame
from canergy.bridge.schedule import Held
from canergy.faults import FaultInjector
from canergy.live.runtime import monotonic_us


class FaultyBus(can.BusABC):
    def __init__(self, inner: can.BusABC, injector: FaultInjector, **kwargs: Any) -> None:
        self.inner = inner
        self.injector = injector
        self._held: Held[can.Message] = Held()
        self._lock = threading.Lock()
        self.channel_info = f"faulty({inner.channel_info})"
        super().__init__(channel=inner.channel_info, can_filters=None, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        now = monotonic_us()
        with self._lock:
            for delay_us, data in self.injector.fate(bytes(msg.data)):
                self._held.push(now + delay_us, copy_frame(msg, data))
        self._release(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._release(None)
        with self._lock:
            due = self._held.next_due()
        if due is not None:  # wake up in time to release what is due
            wait = max(0.0, (due - monotonic_us()) / 1e6)
            timeout = wait if timeout is None else min(timeout, wait)
        return self.inner.recv(timeout), False

    def _release(self, timeout: float | None) -> None:
        with self._lock:
            due = self._held.pop_due(monotonic_us())
        for frame in due:
            self.inner.send(frame, timeout)

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()
