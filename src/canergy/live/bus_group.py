"""Several buses, one loop: a reader thread per bus queues frames; the loop owns every handler.

Each bus keeps its own ``BusRuntime`` (codec, acceptance filters, counters, handler); only the
waiting is shared, so handlers that share a core (a gateway's two roles, a supervisor over
several buses) are only ever called from the loop's thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Sequence

import can

from canergy.live.runtime import BusRuntime

log = logging.getLogger(__name__)

QUEUE_FRAMES = 8192
"""Frames waiting for the loop, all buses; beyond, a frame is dropped and counted (lost, for the
protocol) rather than memory and every deadline growing while the loop is held up."""


class BusGroup:
    """Drive ``runtimes`` from one thread; ``close`` stops the readers (not the buses)."""

    def __init__(self, runtimes: Sequence[BusRuntime], max_batch: int = 512) -> None:
        self.runtimes = tuple(runtimes)
        self.max_batch = max_batch
        self._frames: queue.Queue[tuple[int, can.Message]] = queue.Queue(QUEUE_FRAMES)
        self.dropped = 0
        self._running = True
        self._readers = [
            threading.Thread(target=self._read, args=(i,), name=f"canergy-bus-{i}", daemon=True)
            for i in range(len(self.runtimes))
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, i: int) -> None:
        runtime = self.runtimes[i]
        while self._running:
            try:
                frame = runtime.bus.recv(timeout=0.1)
            except can.CanError:  # the interface went down: counted by the loop, retried
                runtime.counters.receive_failed()
                time.sleep(0.1)
                continue
            except Exception:  # a bus closed under us at shutdown, or a driver's own error
                if self._running:
                    log.exception("bus %d: receive failed; retrying", i)
                    runtime.counters.receive_failed()
                    time.sleep(0.1)
                continue
            if frame is None:
                continue
            try:
                self._frames.put_nowait((i, frame))
            except queue.Full:
                self.dropped += 1
                runtime.counters.receive_errors += 1

    def poll(self, max_wait_s: float = 0.1) -> None:
        """Wait for a frame on any bus (at most until the earliest deadline), hand over what is
        queued, then run every deadline that is due."""
        now = min(rt.clock() for rt in self.runtimes)
        wakeups = [w for rt in self.runtimes if (w := rt.handler.next_wakeup()) is not None]
        wait = max_wait_s if not wakeups else min(max_wait_s, max(0, min(wakeups) - now) / 1e6)
        try:
            item: tuple[int, can.Message] | None = self._frames.get(timeout=wait)
        except queue.Empty:
            item = None
        for runtime in self.runtimes:
            runtime.begin_pass()
        try:
            batch = 0
            while item is not None:
                self.runtimes[item[0]].receive(item[1])
                batch += 1
                try:
                    item = self._frames.get_nowait() if batch < self.max_batch else None
                except queue.Empty:
                    item = None
            for runtime in self.runtimes:
                runtime.run_due()
        finally:
            for runtime in self.runtimes:
                runtime.end_pass()

    def close(self) -> None:
        self._running = False
        for reader in self._readers:
            reader.join(timeout=1.0)
