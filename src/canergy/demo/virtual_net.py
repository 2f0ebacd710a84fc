"""A python-can ``virtual`` bus driven in virtual time through a fault injector.

Each node owns one endpoint of the same virtual channel. A frame sent by a node is handed to the
``FaultInjector``, which decides its copies and delays; at its delivery time the frame is put on
the bus from the sender's endpoint, so every other endpoint (and the ``on_frame`` callback, if any)
sees it, and receivers apply their acceptance filters. Nothing sleeps: the caller advances the
clock. Use the network as a context manager: every bus it opened is shut down on the way out.
"""

from __future__ import annotations

import heapq
import itertools
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import TracebackType

import can

from canergy.codec import Codec
from canergy.faults import FaultInjector
from canergy.messages import Message

Filters = list[dict[str, int | bool]]


@dataclass(slots=True)
class Endpoint:
    """One node's connection to the bus, with its acceptance filters."""

    name: str
    bus: can.BusABC
    filters: Filters
    frames_sent: int = 0


@dataclass(order=True, slots=True)
class _InFlight:
    due: int
    seq: int
    sender: Endpoint = field(compare=False)
    arbitration_id: int = field(compare=False)
    data: bytes = field(compare=False)


class VirtualNetwork:
    """Endpoints on one private virtual channel and the frames in flight.

    ``on_frame`` is called with every frame put on the bus, as a monitoring bus received it.
    """

    def __init__(
        self,
        codec: Codec,
        injector: FaultInjector,
        *,
        on_frame: Callable[[can.Message], None] | None = None,
        epoch: float = 0.0,
    ) -> None:
        self.codec = codec
        self.injector = injector
        self.epoch = epoch
        self._channel = f"canergy-{uuid.uuid4().hex}"
        self._endpoints: list[Endpoint] = []
        self._on_frame = on_frame
        self._monitor = self._bus()
        self._in_flight: list[_InFlight] = []
        self._seq = itertools.count()

    def __enter__(self) -> VirtualNetwork:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _bus(self) -> can.BusABC:
        return can.Bus(interface="virtual", channel=self._channel, preserve_timestamps=True)

    def endpoint(self, name: str, filters: Filters) -> Endpoint:
        ep = Endpoint(name, self._bus(), filters)
        self._endpoints.append(ep)
        return ep

    def send(self, sender: Endpoint, msg: Message, now: int) -> None:
        """Encode ``msg`` and let the injector decide when (and if) its copies arrive."""
        arbitration_id, data = self.codec.encode(msg)
        sender.frames_sent += 1
        for delay, payload in self.injector.fate(data):
            item = _InFlight(now + delay, next(self._seq), sender, arbitration_id, payload)
            heapq.heappush(self._in_flight, item)

    def next_due(self) -> int | None:
        return self._in_flight[0].due if self._in_flight else None

    def in_flight(self) -> int:
        return len(self._in_flight)

    def deliver_next(self, now: int) -> Iterator[tuple[Endpoint, can.Message]]:
        """Put the next due frame on the bus; yield ``(receiver, frame)`` for each acceptor."""
        if not self._in_flight or self._in_flight[0].due > now:
            return
        item = heapq.heappop(self._in_flight)
        frame = can.Message(
            timestamp=self.epoch + item.due / 1e6,
            arbitration_id=item.arbitration_id,
            is_extended_id=True,
            data=item.data,
        )
        item.sender.bus.send(frame)
        self._drain_monitor()
        for ep in self._endpoints:
            if ep is item.sender:
                continue
            received = ep.bus.recv(timeout=0)
            if received is not None and self.codec.accepts(
                ep.filters, received.arbitration_id, received.is_extended_id
            ):
                yield ep, received

    def _drain_monitor(self) -> None:
        while (frame := self._monitor.recv(timeout=0)) is not None:
            if self._on_frame is not None:
                self._on_frame(frame)

    def close(self) -> None:
        """Shut down every bus this network opened."""
        for bus in [self._monitor, *(ep.bus for ep in self._endpoints)]:
            bus.shutdown()
