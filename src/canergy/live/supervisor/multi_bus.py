"""One supervisor over several buses: one usable budget, one core, one ``BusRuntime`` per bus.

The core keys each node's session ``bus index << 8 | node`` (``canergy.bus_keys``), so node 5
on two buses are two sessions. A ``BusPort`` per bus stands between its runtime and the shared
``SupervisorService``: what arrives on bus i is handed over with its node replaced by the key,
and every message the service returns is sent on the bus its key names, as a plain node id.
Only the first port runs the service's deadlines (``BusGroup`` asks every runtime). On the
compiled core (``canergy.ccore.buses``) each bus's runtime has that bus's frame path
(``SupervisorService.frame_path(bus=)``; with a key, verified and protected in that bus's
supervisor in C under the keys of that bus's ``FrameAuth``), and the frames C encoded name
their bus (``RawFrame.bus``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import can

from canergy.auth.frames import Verdict
from canergy.bus_keys import bus_of, node_of, session_key
from canergy.codec import DecodeError
from canergy.live.runtime import BusRuntime, Outgoing, RawFrame
from canergy.live.supervisor.service import SupervisorService
from canergy.messages import Message


@dataclass(frozen=True, slots=True)
class BusSpec:
    """One ``--bus``: its name (default: the channel), where it is, the nodes on it."""

    name: str
    interface: str
    channel: str
    nodes: tuple[int, ...]


def session_keys(specs: Sequence[BusSpec]) -> tuple[int, ...]:
    """The core's session keys of every node on every bus, in bus order."""
    return tuple(session_key(i, n) for i, spec in enumerate(specs) for n in spec.nodes)


class BusRouter:
    """Sends each message the service addresses by session key on its own bus."""

    def __init__(self) -> None:
        self.runtimes: list[BusRuntime] = []
        """One per bus, in bus order: filled in once the runtimes exist."""

    def send(self, messages: Sequence[Outgoing]) -> Sequence[Message]:
        """Send ``messages``; returns nothing left for the caller's own bus to send. A frame
        the compiled core encoded (``RawFrame``) goes to the bus it names, as it is. Each run
        of messages for one bus goes to its runtime in one call, in order: a classic frame C
        protected and the MAC frame after it are sent (and noted as this side's) together."""
        run: list[Outgoing] = []
        run_bus = 0
        for msg in messages:
            out: Outgoing
            if isinstance(msg, RawFrame):
                bus, out = msg.bus, msg
            else:
                bus, out = bus_of(msg.node), replace(msg, node=node_of(msg.node))
            if run and bus != run_bus:
                self.runtimes[run_bus].send_messages(run)
                run = []
            run_bus = bus
            run.append(out)
        if run:
            self.runtimes[run_bus].send_messages(run)
        return ()


class BusPort:
    """Bus ``bus``'s side of a service shared by several buses: a ``Handler`` for its runtime.

    Returns nothing itself: everything the service answers goes out through the router, on the
    bus of each message's node (a frame on one bus may start grants on another)."""

    def __init__(
        self, service: SupervisorService, bus: int, router: BusRouter, *, deadlines: bool
    ) -> None:
        self.service = service
        self._freshness = service.freshness  # per frame: the service's part's, called directly
        self.bus = bus
        self.router = router
        self.deadlines = deadlines
        """Whether this port runs the service's deadlines (exactly one port does)."""

    def key(self, node: int) -> int:
        return session_key(self.bus, node)

    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        keyed = replace(msg, node=self.key(msg.node))
        return self.router.send(self.service.on_message(keyed, now))

    def on_decode_error(self, error: DecodeError, frame: can.Message) -> None:
        self.service.on_decode_error(error, frame, self.key(frame.arbitration_id & 0xFF))

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        if verdict.node is not None:
            verdict = replace(verdict, node=self.key(verdict.node))
        self.service.on_auth_failure(verdict, frame, now)

    def on_foreign_direction(self, frame: can.Message, now: int) -> Sequence[Message]:
        node = self.key(frame.arbitration_id & 0xFF)
        return self.router.send(self.service.on_foreign_direction(frame, now, node))

    def freshness(self, msg: Message) -> int | None:
        """Authenticated mode: the service's freshness for this bus's node ``msg.node``."""
        return self._freshness(replace(msg, node=self.key(msg.node)))

    def begin_pass(self) -> None:
        self.service.begin_pass()

    def end_pass(self) -> Sequence[Message]:
        """What the service held through the pass (all buses' frames, once the outermost pass
        ends), each sent on its own bus (the compiled core's encoded frames on the bus they
        name)."""
        return self.router.send(self.service.end_pass())

    def next_wakeup(self) -> int | None:
        return self.service.next_wakeup() if self.deadlines else None

    def on_wakeup(self, now: int) -> Sequence[Message]:
        return self.router.send(self.service.on_wakeup(now)) if self.deadlines else ()
