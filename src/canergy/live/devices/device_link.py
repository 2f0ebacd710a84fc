"""What the supervisor's loop needs of a guarded device's link (``OdriveLink``, ``MoteusLink``):
feed what arrived to the guard, take its commands, report, close; ``GuardLink``, what they
share."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, Protocol

import can

from canergy.devices.guard import DeviceGuard
from canergy.devices.profile import L, ReadLimits, Stop, WriteLimits
from canergy.messages import Message


class DeviceLink(Protocol):
    """Also a ``can.Listener`` (the builder adds it to the bus's Notifier)."""

    def start(self) -> None: ...

    def on_message_received(self, msg: Any) -> None: ...

    def pump(self, guard: Any, now: int) -> list[Message]: ...

    def command(self, cmd: Any) -> None: ...

    def pending(self) -> bool: ...

    def next_wakeup(self) -> int | None:
        """When the link has work of its own (None: only when frames arrive)."""
        ...

    def status(self) -> dict[str, object]: ...

    def close(self) -> None: ...


Device = tuple[DeviceGuard[Any], DeviceLink]
"""A guarded device and its link."""


class GuardLink(Generic[L]):
    """What the links share: frames heard on the Notifier's thread become events for the loop
    (``pump`` feeds them to the guard), the guard's commands go to a worker thread that talks
    to the device (``_work``, the subclass's), counts for the status. ``clock`` gives host µs."""

    def __init__(
        self, bus: can.BusABC, node: int, limits: L | None, clock: Callable[[], int], kind: str
    ) -> None:
        self.bus = bus
        self.node = node
        self.limits = limits
        self.clock = clock
        self.lock = threading.Lock()
        self.events: list[Callable[[DeviceGuard[L], int], list[Message]]] = []
        self.work: queue.Queue[WriteLimits[L] | ReadLimits | Stop | None] = queue.Queue()
        self.voltage: float | None = None
        self.reaction_max_us = 0
        self.latency_max_us = 0
        self.send_failures = 0
        self.frames_in = 0
        self.bad_frames = 0
        self.closing = threading.Event()
        self.worker = threading.Thread(target=self._work, daemon=True, name=f"{kind}-{node}")

    def start(self) -> None:
        """Set up the device and carry out commands (once the listener hears the bus)."""
        self.worker.start()

    def _work(self) -> None:
        raise NotImplementedError

    # -- the listener (Notifier thread) ---------------------------------------------------
    def __call__(self, frame: can.Message) -> None:
        self.on_message_received(frame)

    def on_message_received(self, frame: can.Message) -> None:
        raise NotImplementedError

    def _event(self, event: Callable[[DeviceGuard[L], int], list[Message]]) -> None:
        with self.lock:
            self.frames_in += 1
            self.events.append(event)

    def received_at(self, frame: can.Message) -> int:
        """Host µs when ``frame`` arrived (it may have waited for the Notifier's thread)."""
        at = self.clock()
        if frame.timestamp > 0:
            at -= max(0, min(round((time.time() - frame.timestamp) * 1e6), 1_000_000))
        return at

    # -- the loop's side ------------------------------------------------------------------
    def pump(self, guard: DeviceGuard[L], now: int) -> list[Message]:
        """Feed what arrived to ``guard``."""
        with self.lock:
            events, self.events = self.events, []
        guard.watch(self.reaction_max_us, self.latency_max_us)
        out: list[Message] = []
        for event in events:
            out += event(guard, now)
        return out

    def command(self, cmd: WriteLimits[L] | ReadLimits | Stop) -> None:
        self.work.put(cmd)

    def pending(self) -> bool:
        with self.lock:
            return bool(self.events)

    def next_wakeup(self) -> int | None:
        return None

    def status(self) -> dict[str, object]:
        return {
            "reaction_max_us": self.reaction_max_us,
            "latency_max_us": self.latency_max_us,
            "bus_voltage_v": self.voltage,
            "send_failures": self.send_failures,
            "frames_in": self.frames_in,
            "bad_frames": self.bad_frames,
        }

    def close(self) -> None:
        """Carry out what is queued (a halt's stop), then end the worker."""
        self.work.put(None)
        if self.worker.is_alive():
            self.worker.join(timeout=2)
        self.closing.set()


def limits_event(
    wrote: L, read: L | None, at: int, guard: DeviceGuard[L], now: int
) -> list[Message]:
    """A write's read-back for the guard (``functools.partial`` of the first three)."""
    return guard.on_limits(now, wrote, read, at)


def read_event(read: L | None, guard: DeviceGuard[L], now: int) -> list[Message]:
    """A periodic read-back for the guard (``functools.partial`` of the first)."""
    return guard.on_read(now, read)


def ready_event(
    guard: DeviceGuard[L], now: int, started: int, full: L | None, closed: L | None
) -> list[Message]:
    """Set-up done, for the guard (``functools.partial`` of the last three)."""
    guard.on_ready(now, started, full, closed)
    return []
