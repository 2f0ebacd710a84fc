"""Transition tables: ``(phase, event) -> named handler`` for each role of each variant.

A table is total over its phases and events. The cells a variant lists carry its rules; every
other cell ignores the event (messages, timers) or refuses it with ``LocalProtocolError`` (local
requests). Guards on ids and energy stay inside the named handlers; ``to`` declares the phases a
handler may leave its state in, which the diagrams in ``docs/`` are drawn from and tests check.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any, ClassVar, Generic, Self, TypeVar, get_args

from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import (
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    Input,
    LocalInput,
    PowerLoss,
    ResponseTimeout,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import ClientState, Phase, Session
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.timing import Timing
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    FinalAck,
    Intention,
    Join,
    Return,
    ReturnAck,
    StatusRequest,
    ToClient,
    ToSupervisor,
)

S = TypeVar("S", Session, ClientState)
R = TypeVar("R", SessionStep, ClientStep)
Handler = Callable[[Timing, Any, Any, int], Any]
"""``handler(timing, state, event, now) -> SessionStep | ClientStep``."""


class Role(Enum):
    SUPERVISOR = "supervisor"
    CLIENT = "client"


Event = Input | ToClient | ToSupervisor
"""What a table dispatches on: a wire message or another input."""
LOCAL_EVENTS: tuple[type, ...] = get_args(LocalInput)
EVENTS: dict[Role, tuple[type, ...]] = {
    Role.SUPERVISOR: (
        Begin,
        Decide,
        Ack,
        Committed,
        Aborted,
        Return,
        Join,
        Debit,
        ResponseTimeout,
        PowerLoss,
    ),
    Role.CLIENT: (
        Intention,
        Commit,
        Abort,
        ReturnAck,
        StatusRequest,
        FinalAck,
        Admit,
        CommandTimeout,
        ReturnTimeout,
        Spend,
        GiveBack,
        PowerLoss,
        BooksLost,
    ),
}

STAY: None = None
"""In ``to``: the handler may leave the phase unchanged (a guard failed, or nothing to do)."""
ANY: None = None
"""In a cell's phases: every phase of the table."""


def event_name(event: type) -> str:
    """``INTENTION``, ``ACK``... for messages, ``begin``, ``power loss``... for other inputs."""
    msg_type = getattr(event, "TYPE", None)
    return msg_type.name if msg_type is not None else str(getattr(event, "NAME"))  # noqa: B009


@dataclass(frozen=True, slots=True)
class Transition:
    """One cell: the handler and the phases it may leave the state in."""

    handler: Handler
    to: frozenset[Phase]

    @property
    def name(self) -> str:
        return self.handler.__name__

    @property
    def summary(self) -> str:
        return (self.handler.__doc__ or "").strip().splitlines()[0]


@dataclass(frozen=True, slots=True)
class Cell:
    """What a variant lists: ``handler`` for ``event`` in ``phases``, ending in ``to``."""

    phases: tuple[Phase, ...] | None
    event: type
    handler: Handler
    to: tuple[Phase | None, ...]


def cell(
    phases: Phase | Iterable[Phase] | None,
    event: type,
    handler: Handler,
    to: Phase | Iterable[Phase | None] | None = STAY,
) -> Cell:
    """A listed cell; ``phases`` ``ANY`` is every phase, ``to`` may name ``STAY``."""
    ps = (phases,) if isinstance(phases, Phase) else None if phases is None else tuple(phases)
    ts = (to,) if to is None or isinstance(to, Phase) else tuple(to)
    return Cell(ps, event, handler, ts)


def ignore_session(t: Timing, s: Session, event: object, now: int) -> SessionStep:
    """Ignore: nothing changes."""
    return SessionStep(s)


def ignore_client(t: Timing, c: ClientState, event: object, now: int) -> ClientStep:
    """Ignore: nothing changes."""
    return ClientStep(c)


def refuse(t: Timing, state: Session | ClientState, event: object, now: int) -> Any:
    """Refuse: the local application may not ask for this now."""
    raise LocalProtocolError(
        f"node {state.node}: {getattr(event, 'NAME', event)} is not allowed in phase "
        f"{state.phase.name}"
    )


class RuleTable(Generic[S, R]):
    """One role's rules in one variant, total over ``phases`` x the role's events."""

    role: ClassVar[Role]

    def __init__(
        self,
        variant: str,
        phases: Iterable[Phase],
        cells: Iterable[Cell],
        persistent: Callable[[S], tuple[object, ...]],
    ) -> None:
        self.variant = variant
        self.phases = tuple(phases)
        self.events = EVENTS[self.role]
        self.persistent: Callable[[S], tuple[object, ...]] = persistent
        """What is written to non-volatile memory; ``()`` when there is no record to write."""
        self._build(cells)

    def _build(self, cells: Iterable[Cell]) -> None:
        listed: dict[tuple[Phase, type], Transition] = {}
        for c in cells:
            for phase in c.phases or self.phases:
                key = (phase, c.event)
                if phase not in self.phases or c.event not in self.events or key in listed:
                    raise ValueError(
                        f"{self.variant} {self.role.value}: bad or repeated cell {key}"
                    )
                listed[key] = Transition(
                    c.handler, frozenset(phase if p is None else p for p in c.to)
                )
        self.listed: Mapping[tuple[Phase, type], Transition] = listed
        ignore = ignore_session if self.role is Role.SUPERVISOR else ignore_client
        self.cells: Mapping[tuple[Phase, type], Transition] = {
            (p, e): listed.get((p, e))
            or Transition(refuse if e in LOCAL_EVENTS else ignore, frozenset({p}))
            for p in self.phases
            for e in self.events
        }

    def step(self, t: Timing, state: S, event: Event, now: int) -> R:
        """Run the cell of ``state.phase`` and ``type(event)``."""
        transition = self.cells.get((state.phase, type(event)))
        if transition is None:
            raise LocalProtocolError(
                f"{self.variant} {self.role.value}: no rule for {type(event).__name__} "
                f"in phase {state.phase.name}"
            )
        step: R = transition.handler(t, state, event, now)
        return step

    def with_cells(self, *cells: Cell) -> Self:
        """A copy with some listed cells replaced or added (tests break rules on purpose)."""
        replaced = {(p, c.event) for c in cells for p in (c.phases or self.phases)}
        kept: list[Cell] = [
            Cell((p,), e, tr.handler, tuple(tr.to))
            for (p, e), tr in self.listed.items()
            if (p, e) not in replaced
        ]
        return self._with_cells([*kept, *cells])

    def _with_cells(self, cells: list[Cell]) -> Self:
        """The same table built from ``cells`` (no ``copy``: compiled classes have none)."""
        return type(self)(self.variant, self.phases, cells, self.persistent)


class SupervisorTable(RuleTable[Session, SessionStep]):
    """A supervisor's rules for one node's session."""

    role = Role.SUPERVISOR


def always(c: ClientState) -> bool:
    """No guard: the actuator may spend whenever the budget holds it."""
    return True


class ClientTable(RuleTable[ClientState, ClientStep]):
    """A client's rules, plus the guards the application asks before it gives energy back and
    before it spends."""

    role = Role.CLIENT

    def __init__(
        self,
        variant: str,
        phases: Iterable[Phase],
        cells: Iterable[Cell],
        persistent: Callable[[ClientState], tuple[object, ...]],
        can_give_back: Callable[[ClientState], bool],
        can_spend: Callable[[ClientState], bool] = always,
    ) -> None:
        super().__init__(variant, phases, cells, persistent)
        self.can_give_back = can_give_back
        self.can_spend = can_spend

    def _with_cells(self, cells: list[Cell]) -> Self:
        return type(self)(
            self.variant, self.phases, cells, self.persistent, self.can_give_back, self.can_spend
        )
