"""The joint state of supervisor, clients and channel, and every step that can change it.

Time is abstract: the rules run with zero timeouts and ``now = 0``, so an armed deadline is 0 and
a timer fires only when a step says so. Energies are whole wire quanta ("units").
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from canergy.core.actions import Send
from canergy.core.common import Actions
from canergy.core.frozen import evolve
from canergy.core.state import ClientState, Decision, Phase, Session, SupervisorState
from canergy.core.supervisor import apply_session
from canergy.core.timing import Timing
from canergy.core.variants import Variant
from canergy.ledger import Ledger, ledger
from canergy.messages import QUANTUM_UJ, Direction, Message, ToClient, ToSupervisor

UNIT = QUANTUM_UJ
Flight = frozenset[tuple[Message, int]]
"""The multiset of frames in flight as (message, copies): canonical without sorting."""


@dataclass(frozen=True, slots=True)
class Bounds:
    """What the exploration may spend. Energies in units (1 unit = 1 mJ)."""

    clients: int = 1
    transactions: int = 2
    losses: int = 1
    duplicates: int = 1
    power_losses: int = 1
    in_flight: int = 3
    units: int = 1
    retries: int = 1
    timeouts: int | None = None
    """Timer expiries (either side) in one run; None: unbounded (and not counted)."""
    returns: bool = True
    spending: bool = True
    extra_ids: int = 2
    """Paper variant: intentions it may re-define beyond ``transactions`` (ids are unbounded)."""

    def timing(self) -> Timing:
        return Timing(
            response_timeout_us=0, retries=self.retries, command_timeout_us=0, return_retry_us=0
        )


@dataclass(frozen=True, slots=True)
class World:
    sup: SupervisorState
    clients: tuple[ClientState, ...]
    flight: Flight
    started: int = 0
    lost: int = 0
    duplicated: int = 0
    power_lost: int = 0
    timed_out: int = 0

    def frames(self) -> int:
        return sum(n for _, n in self.flight)

    def ledger(self) -> Ledger:
        return ledger(self.sup, self.clients)

    def quiescent(self) -> bool:
        """No transaction open, nothing in flight, no return waiting."""
        return (
            not self.flight
            and all(s.phase is Phase.IDLE for s in self.sup.sessions)
            and all(
                c.return_pending == 0 or c.return_seq <= s.returns_credited
                for s, c in zip(self.sup.sessions, self.clients, strict=True)
            )
        )


StepKind = Literal[
    "begin",
    "decide",
    "deliver",
    "lose",
    "duplicate",
    "supervisor_timer",
    "command_timer",
    "return_timer",
    "spend",
    "give_back",
    "client_power_loss",
    "supervisor_power_loss",
]


@dataclass(frozen=True, slots=True)
class Step:
    """One nondeterministic choice. ``node`` is the node concerned, when there is one."""

    kind: StepKind
    node: int = 0
    units: int = 0
    commit: bool = False
    message: Message | None = None

    def describe(self) -> str:
        if self.message is not None:
            return f"{self.kind} {self.message}"
        extra = {
            "begin": f" {self.units} unit(s)",
            "decide": " commit" if self.commit else " abort",
        }
        where = f" node {self.node}" if self.node else ""
        return f"{self.kind}{where}{extra.get(self.kind, '')}"


def initial_world(bounds: Bounds) -> World:
    nodes = range(1, bounds.clients + 1)
    total = bounds.units * UNIT
    sup = SupervisorState(total, total, 0, tuple(Session(n) for n in nodes))
    return World(sup, tuple(ClientState(n) for n in nodes), frozenset())


class Model:
    """Steps of one variant under one set of bounds."""

    def __init__(self, variant: Variant, bounds: Bounds) -> None:
        self.variant = variant
        self.bounds = bounds
        self.timing = bounds.timing()
        self.sup_rules = variant.supervisor
        self.client_rules = variant.client

    # -- enumeration -----------------------------------------------------------------
    def steps(self, w: World) -> Iterator[Step]:
        b = self.bounds
        for s in w.sup.sessions:
            if s.phase is Phase.IDLE and w.started < b.transactions:
                for units in range(1, min(w.sup.usable // UNIT, b.units) + 1):
                    yield Step("begin", s.node, units=units)
            if s.phase is Phase.ACKED:
                yield Step("decide", s.node, commit=True)
                yield Step("decide", s.node, commit=False)
            if s.deadline is not None and (b.timeouts is None or w.timed_out < b.timeouts):
                yield Step("supervisor_timer", s.node)
        for msg, _ in sorted(w.flight, key=_flight_key):
            yield Step("deliver", message=msg)
            if w.lost < b.losses:
                yield Step("lose", message=msg)
            if w.duplicated < b.duplicates and w.frames() < b.in_flight:
                yield Step("duplicate", message=msg)
        for c in w.clients:
            if c.deadline is not None and (b.timeouts is None or w.timed_out < b.timeouts):
                yield Step("command_timer", c.node)
            if c.return_deadline is not None and (b.timeouts is None or w.timed_out < b.timeouts):
                yield Step("return_timer", c.node)
            if b.spending and c.usable >= UNIT:
                yield Step("spend", c.node)
            if b.returns and c.usable >= UNIT and self.client_rules.can_give_back(c):
                yield Step("give_back", c.node)
            if w.power_lost < b.power_losses:
                yield Step("client_power_loss", c.node)
        if w.power_lost < b.power_losses:
            yield Step("supervisor_power_loss")

    # -- application -----------------------------------------------------------------
    def apply(self, w: World, step: Step) -> World | None:
        """The world after ``step``, or None when it leaves the bounds."""
        new = self._apply(w, step)
        if new is None or new.frames() > self.bounds.in_flight:
            return None
        limit = self.bounds.transactions + self.bounds.extra_ids
        if any(s.tx > limit for s in new.sup.sessions):
            return None
        return new

    def _apply(self, w: World, step: Step) -> World | None:
        t, kind, i = self.timing, step.kind, step.node - 1
        if kind.endswith("_timer") and self.bounds.timeouts is not None:
            w = evolve(w, timed_out=w.timed_out + 1)
        if kind == "begin":
            s, actions = self.sup_rules.begin(t, w.sup.sessions[i], step.units * UNIT, 0)
            sup = apply_session(w.sup, i, s, -step.units * UNIT)
            return self._out(evolve(w, sup=sup, started=w.started + 1), actions)
        if kind == "decide":
            decision = Decision.COMMIT if step.commit else Decision.ABORT
            return self._session(w, i, self.sup_rules.decide(t, w.sup.sessions[i], decision, 0))
        if kind == "supervisor_timer":
            return self._session(w, i, self.sup_rules.timer(t, w.sup.sessions[i], 0))
        if kind in ("deliver", "lose", "duplicate"):
            return self._channel(w, step)
        if kind == "supervisor_power_loss":
            sessions = tuple(self.sup_rules.power_loss(s, 0) for s in w.sup.sessions)
            return evolve(w, sup=evolve(w.sup, sessions=sessions), power_lost=w.power_lost + 1)
        c = w.clients[i]
        if kind == "command_timer":
            return self._client(w, i, *self.client_rules.command_timer(t, c, 0))
        if kind == "return_timer":
            return self._client(w, i, *self.client_rules.return_timer(t, c, 0))
        if kind == "spend":
            spent = evolve(c, usable=c.usable - UNIT, spent=c.spent + UNIT)
            return self._client(w, i, spent, ())
        if kind == "give_back":
            return self._client(w, i, *self.client_rules.give_back(t, c, UNIT, 0))
        if kind == "client_power_loss":
            w = evolve(w, power_lost=w.power_lost + 1)
            return self._client(w, i, self.client_rules.power_loss(c, 0), ())
        raise ValueError(f"unknown step {step}")

    def _channel(self, w: World, step: Step) -> World | None:
        msg = step.message
        assert msg is not None
        counts = dict(w.flight)
        if msg not in counts:
            return None
        if step.kind == "duplicate":
            counts[msg] += 1
            return evolve(w, flight=frozenset(counts.items()), duplicated=w.duplicated + 1)
        counts[msg] -= 1
        if not counts[msg]:
            del counts[msg]
        w = evolve(w, flight=frozenset(counts.items()))
        if step.kind == "lose":
            return evolve(w, lost=w.lost + 1)
        i = msg.node - 1
        if msg.TYPE.direction is Direction.TO_CLIENT:
            assert isinstance(msg, ToClient)
            return self._client(w, i, *self.client_rules.receive(self.timing, w.clients[i], msg, 0))
        assert isinstance(msg, ToSupervisor)
        return self._session(w, i, self.sup_rules.receive(self.timing, w.sup.sessions[i], msg, 0))

    def _session(self, w: World, i: int, step: tuple[Session, Actions, int]) -> World:
        s, actions, credit = step
        return self._out(evolve(w, sup=apply_session(w.sup, i, s, credit)), actions)

    def _client(self, w: World, i: int, c: ClientState, actions: Actions) -> World:
        clients = (*w.clients[:i], c, *w.clients[i + 1 :])
        return self._out(evolve(w, clients=clients), actions)

    @staticmethod
    def _out(w: World, actions: Actions) -> World:
        sends = [a.message for a in actions if isinstance(a, Send)]
        if not sends:
            return w
        counts = dict(w.flight)
        for msg in sends:
            counts[msg] = counts.get(msg, 0) + 1
        return evolve(w, flight=frozenset(counts.items()))


def _flight_key(item: tuple[Message, int]) -> tuple[int, str]:
    return (int(item[0].TYPE), repr(item[0]))


def replay(model: Model, steps: list[Step]) -> list[World]:
    """Re-run ``steps`` from the initial world through the core; the worlds after each step."""
    worlds = [initial_world(model.bounds)]
    for step in steps:
        nxt = model.apply(worlds[-1], step)
        if nxt is None:
            raise ValueError(f"step not applicable: {step.describe()}")
        worlds.append(nxt)
    return worlds[1:]
