"""The parts of a node's content, interned, and the core's rules memoized on them.

Sessions, client records and frames are kept with node id 1 and numbered; a multiset of frames
is a sorted tuple of (frame, copies) and the frames seen a sorted tuple of frames, both numbered
too. A rule runs once per (part, position, event): on the part renamed to the node at that
position, through ``variant.supervisor.step`` / ``variant.client.step`` exactly as
``Model`` calls them (no time: ``now = 0``, zero timeouts).
"""

from __future__ import annotations

from typing import Any, TypeVar, cast

from canergy.check.model import Model, Resync, session_step
from canergy.core.actions import Send
from canergy.core.state import ClientState, Session
from canergy.core.table import Event
from canergy.frozen import evolve
from canergy.messages import Direction, Message

T = TypeVar("T")
Flight = tuple[tuple[int, int], ...]
"""Frames in flight to or from one node: (frame, copies), sorted."""
Seen = tuple[int, ...]
SessionResult = tuple[int, int, tuple[int, ...]]
"""(session after, credit to Us, frames sent)."""
ClientResult = tuple[int, tuple[int, ...], bool]
"""(client record after, frames sent, whether the persistent record changed)."""


class Parts:
    """Numbered sessions, client records, frames, multisets of frames and sets of frames."""

    def __init__(self, model: Model) -> None:
        self.variant, self.timing = model.variant, model.timing
        self.objects: list[Any] = []
        self._ids: dict[Any, int] = {}
        self.flights: list[Flight] = []
        self._flight_ids: dict[Flight, int] = {}
        self.seens: list[Seen] = []
        self._seen_ids: dict[Seen, int] = {}
        self._renamed: dict[tuple[int, int], Any] = {}
        self._session_steps: dict[tuple[int, int, object], SessionResult] = {}
        self._client_steps: dict[tuple[int, int, object], ClientResult] = {}
        self._added: dict[tuple[int, tuple[int, ...]], int] = {}
        self._removed: dict[tuple[int, int], int] = {}
        self._seen_added: dict[tuple[int, tuple[int, ...]], int] = {}
        self.empty_flight = self.flight(())
        self.empty_seen = self.seen(())

    # -- numbering ---------------------------------------------------------------------
    def part(self, obj: object) -> int:
        """The number of a session, client record or frame, whatever its node id."""
        if getattr(obj, "node") != 1:  # noqa: B009 (every part has one)
            obj = evolve(obj, node=1)
        i = self._ids.get(obj)
        if i is None:
            i = self._ids[obj] = len(self.objects)
            self.objects.append(obj)
        return i

    def named(self, i: int, node: int) -> Any:
        """Part ``i`` as node ``node``'s; memoized."""
        if node == 1:
            return self.objects[i]
        out = self._renamed.get((i, node))
        if out is None:
            out = self._renamed[(i, node)] = evolve(self.objects[i], node=node)
        return out

    def flight(self, items: Flight) -> int:
        items = tuple(sorted(items))
        i = self._flight_ids.get(items)
        if i is None:
            i = self._flight_ids[items] = len(self.flights)
            self.flights.append(items)
        return i

    def seen(self, frames: Seen) -> int:
        frames = tuple(sorted(set(frames)))
        i = self._seen_ids.get(frames)
        if i is None:
            i = self._seen_ids[frames] = len(self.seens)
            self.seens.append(frames)
        return i

    # -- multisets -----------------------------------------------------------------------
    def add(self, flight: int, frames: tuple[int, ...]) -> int:
        """``flight`` with one more copy of each of ``frames``."""
        key = (flight, frames)
        out = self._added.get(key)
        if out is None:
            counts = dict(self.flights[flight])
            for f in frames:
                counts[f] = counts.get(f, 0) + 1
            out = self._added[key] = self.flight(tuple(counts.items()))
        return out

    def remove(self, flight: int, frame: int) -> int:
        """``flight`` with one copy of ``frame`` fewer (it must hold one)."""
        key = (flight, frame)
        out = self._removed.get(key)
        if out is None:
            counts = dict(self.flights[flight])
            counts[frame] -= 1
            if not counts[frame]:
                del counts[frame]
            out = self._removed[key] = self.flight(tuple(counts.items()))
        return out

    def seen_with(self, seen: int, frames: tuple[int, ...]) -> int:
        key = (seen, frames)
        out = self._seen_added.get(key)
        if out is None:
            out = self._seen_added[key] = self.seen(self.seens[seen] + frames)
        return out

    # -- the rules ---------------------------------------------------------------------
    def event(self, event: Event | int, node: int) -> Event:
        """An event as node ``node``'s (a number stands for a frame)."""
        return cast(Event, self.named(event, node)) if isinstance(event, int) else event

    def session_step(self, session: int, node: int, event: Event | Resync | int) -> SessionResult:
        key = (session, node, event)
        out = self._session_steps.get(key)
        if out is None:
            s = cast(Session, self.named(session, node))
            if not isinstance(event, Resync):
                event = self.event(event, node)
            step = session_step(self.variant, self.timing, s, event)
            sends = self._sent(step.actions, node)
            out = self._session_steps[key] = (self.part(step.session), step.credit, sends)
        return out

    def client_step(self, client: int, node: int, event: Event | int) -> ClientResult:
        key = (client, node, event)
        out = self._client_steps.get(key)
        if out is None:
            rules = self.variant.client
            old = cast(ClientState, self.named(client, node))
            new, actions = rules.step(self.timing, old, self.event(event, node), 0)
            persisted = rules.persistent(old) != rules.persistent(new)
            out = self._client_steps[key] = (self.part(new), self._sent(actions, node), persisted)
        return out

    def _sent(self, actions: tuple[object, ...], node: int) -> tuple[int, ...]:
        sends = [a.message for a in actions if isinstance(a, Send)]
        if any(m.node != node for m in sends):
            raise RuntimeError(f"node {node}'s rule sent a frame for another node: {sends}")
        return tuple(self.part(m) for m in sends)

    def to_client(self, frame: int) -> bool:
        """Whether frame ``frame`` goes to a client (else to the supervisor)."""
        msg: Message = self.objects[frame]
        return msg.TYPE.direction is Direction.TO_CLIENT
