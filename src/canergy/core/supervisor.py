"""The supervisor: one usable budget Us, one session per node, sans-IO.

Reservations never move between nodes. Every method takes ``now`` (µs) and returns the actions to
carry out, ``Persist`` first when the persistent record changed. Every change to a session and
every energy movement comes from the variant's transition table.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Protocol

from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.core import witnessed
from canergy.core.actions import Action, Persist
from canergy.core.common import check_counters
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import RESPONSE_TIMEOUT, Begin, Decide, PowerLoss
from canergy.core.state import SYNC_PHASES, Decision, Phase, Session, SupervisorState
from canergy.core.steps import SessionStep
from canergy.core.table import Event
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.frozen import evolve
from canergy.messages import MAX_NODE, MIN_NODE, ToSupervisor

if TYPE_CHECKING:  # the types of the service's parts a compiled core makes in C (names only)
    from canergy.ccore.calls import Answer
    from canergy.core.frame_answers import FrameAnswers
    from canergy.live.supervisor.grants import GrantCaps
    from canergy.live.supervisor.intrusions import Intrusions, Refusals
    from canergy.live.supervisor.policy import Limits, TopUp
    from canergy.live.supervisor.telemetry import TelemetryTable

BUS_SHIFT = 8
"""A supervisor over several buses keys its sessions ``bus << BUS_SHIFT | node``; bus 0's keys
are the plain node ids, so a single bus's books look as they always did."""


def is_session_key(key: int) -> bool:
    """A node id (1-127), or a node id above bus bits (``bus << BUS_SHIFT | node``)."""
    return key >= 0 and MIN_NODE <= key & ((1 << BUS_SHIFT) - 1) <= MAX_NODE


def apply_session(st: SupervisorState, i: int, step: SessionStep) -> SupervisorState:
    """Put session ``i`` back into the state and add the step's credit to Us (pure)."""
    sessions = list(st.sessions)
    sessions[i] = step.session
    return evolve(st, usable=st.usable + step.credit, sessions=tuple(sessions))


def unconfirmed(st: SupervisorState, without: Iterable[int] = ()) -> tuple[int, ...]:
    """The nodes whose books this start still waits for (witnessed rules), but those in
    ``without`` and those in a re-sync of their own (``Session.resync``): while any is left the
    supervisor grants nothing to anyone."""
    skip = frozenset(without)
    return tuple(
        s.node
        for s in st.sessions
        if s.phase in SYNC_PHASES and not s.resync and s.node not in skip
    )


def inject_into(st: SupervisorState, amount: int) -> SupervisorState:
    """Add energy from outside the system to Us, counted as injected (pure)."""
    if amount <= 0:
        raise LocalProtocolError("injected energy must be positive")
    return evolve(st, usable=st.usable + amount, injected=st.injected + amount)


def withdraw_from(st: SupervisorState, amount: int) -> SupervisorState:
    """Take energy out of Us to outside the system, counted as withdrawn (pure)."""
    if amount <= 0 or amount > st.usable:
        raise LocalProtocolError(f"cannot withdraw {amount} µJ of {st.usable} µJ usable")
    return evolve(st, usable=st.usable - amount, withdrawn=st.withdrawn + amount)


class SupervisorCore(Protocol):
    """What the service drives: ``Supervisor`` here, or the compiled one
    (``canergy.ccore.supervisor.CompiledSupervisor``, the C supervisor role)."""

    variant: Variant
    timing: Timing
    implementation: str
    """"python" or "c": what the status names."""

    @property
    def nodes(self) -> tuple[int, ...]: ...
    @property
    def state(self) -> SupervisorState: ...
    @property
    def usable(self) -> int:
        """Us, µJ (``state.usable`` without building the whole state)."""
        ...

    def session(self, node: int) -> Session: ...
    def idle(self, node: int) -> bool:
        """No transaction of ``node`` is open (``session(node).phase`` is IDLE, without the
        whole session: the grant policy asks it of every node it looks at)."""
        ...

    def begin(self, node: int, amount: int, now: int) -> list[Action]: ...
    def commit(self, node: int, now: int) -> list[Action]: ...
    def abort(self, node: int, now: int) -> list[Action]: ...
    def receive(self, msg: ToSupervisor, now: int) -> list[Action]: ...
    def get_timer(self) -> int | None: ...
    def handle_timer(self, now: int) -> list[Action]: ...
    def inject(self, amount: int) -> None: ...
    def power_loss(self, now: int, nonce: int = 0) -> None:
        """A start from the persistent record; ``nonce``: the SYNC's (witnessed rules)."""
        ...

    def resync(self, node: int, now: int, nonce: int) -> list[Action]:
        """Witnessed rules: re-sync one idle node (``witnessed.resync_session``)."""
        ...

    def is_quiescent(self) -> bool: ...

    # -- what the service asks of a core: declared by each (None: no version in C) -------------
    start_without: frozenset[int]
    """Nodes a start does not wait for (witnessed rules)."""

    def unconfirmed(self) -> tuple[int, ...]:
        """The nodes whose books this start waits for before any grant."""
        ...

    def heard_table(self, lost_after_us: int) -> TelemetryTable | None:
        """The TELEMETRY table in C, or None: the service keeps Python's
        (``canergy.live.supervisor.telemetry.HeardTable``)."""
        ...

    def return_gate(self, hold_us: int, block_us: int, hold: bool) -> Any | None:
        """The witness (``canergy.live.supervisor.witness.ReturnGate``'s interface) in C, or
        None: the service keeps Python's."""
        ...

    def join_hold(
        self,
        hold_us: int,
        local_nodes: frozenset[int],
        intrusions: Intrusions,
        refusals: Refusals,
        authenticated: Callable[[], bool],
    ) -> Any | None:
        """The held JOINs (``canergy.live.supervisor.joins.JoinHold``'s interface) in C, or
        None: the service keeps Python's."""
        ...

    def grant_caps(self, limits: Limits, policy: TopUp | None) -> GrantCaps | None:
        """The grant caps in C, or None: the service sizes grants in Python."""
        ...

    def answer_on(self, bus: int) -> Answer:
        """The frame path of bus ``bus`` (``canergy.live.supervisor.frame_path``): C's, or the
        Python core's (``canergy.core.frame_answers``)."""
        ...


class Supervisor:
    """Grants energy from its usable budget to client nodes."""

    implementation = "python"

    def __init__(
        self,
        nodes: Iterable[int],
        initial: int,
        *,
        variant: str | Variant = "hardened",
        timing: Timing | None = None,
        state: SupervisorState | None = None,
        start_without: Iterable[int] = (),
        id_base: int = DEFAULT_ID_BASE,
    ) -> None:
        """``id_base``: the identifier block of the frames ``answer_on`` takes.
        ``start_without``: nodes a start does not wait for (witnessed rules). The risk the
        operator takes: such a node may hold energy the restored books count in Us again (up
        to all it received after the copy was taken; nobody can know how much), and Us grants
        it to the other nodes. The node's own session still waits for its books."""
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        self.rules = self.variant.supervisor
        self.timing = timing or Timing()
        node_list = sorted(set(nodes))
        if not node_list or not all(is_session_key(n) for n in node_list):
            raise ValueError(
                f"nodes must be a non-empty set of ids {MIN_NODE}-{MAX_NODE} (each optionally "
                f"above bus bits: bus << {BUS_SHIFT} | node)"
            )
        if initial < 0:
            raise ValueError("initial budget must be >= 0")
        self.state = state or SupervisorState(
            initial, initial, 0, tuple(Session(n) for n in node_list)
        )
        for s in self.state.sessions:
            check_counters(s)
        self._index = {s.node: i for i, s in enumerate(self.state.sessions)}
        self.id_base = id_base
        self.start_without = frozenset(start_without)
        if not self.start_without <= set(self._index):
            raise ValueError("start_without names nodes this supervisor does not manage")
        self._deadlines: list[tuple[int, int]] = []
        """A heap of (deadline, session index): every session's deadline is in it, and entries
        a session has since left (a deadline changed or cleared) until they reach the top."""
        self._deadlines_of: SupervisorState | None = None
        """The state the heap was kept for: a state set from outside has it rebuilt."""

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(self._index)

    @property
    def usable(self) -> int:
        return self.state.usable

    def session(self, node: int) -> Session:
        return self.state.sessions[self._index[node]]

    def idle(self, node: int) -> bool:
        return self.state.sessions[self._index[node]].phase is Phase.IDLE

    def unconfirmed(self) -> tuple[int, ...]:
        """The nodes whose books this start waits for before any grant (witnessed rules; never
        any under the others): what a runtime prints while it waits."""
        return unconfirmed(self.state, self.start_without)

    # -- the service's parts: none in C here (``SupervisorCore``) ------------------------------
    def heard_table(self, lost_after_us: int) -> None:
        return None

    def return_gate(self, hold_us: int, block_us: int, hold: bool) -> None:
        return None

    def join_hold(self, *args: Any, **kwargs: Any) -> None:
        """None, as ``SupervisorCore.join_hold`` is asked (its arguments: the service's)."""
        return None

    def grant_caps(self, limits: Limits, policy: TopUp | None) -> None:
        return None

    def answer_on(self, bus: int) -> FrameAnswers:
        """Bus ``bus``'s frame path (``canergy.core.frame_answers``), on the identifier block
        ``id_base``."""
        from canergy.core.frame_answers import FrameAnswers  # it reads this module's sessions

        return FrameAnswers(self, Codec(self.id_base), bus)

    def begin(self, node: int, amount: int, now: int) -> list[Action]:
        """Reserve ``amount`` µJ from Us and send node ``node`` an intention; refused while a
        start waits for a node's books (``unconfirmed``)."""
        s = self._session_or_error(node)
        waiting = self.unconfirmed()
        if waiting:
            raise LocalProtocolError(
                "no grant before every node has confirmed its books after this start: waiting "
                f"for node(s) {', '.join(map(str, waiting))}"
            )
        step = self.rules.step(self.timing, s, Begin(amount), now)
        if -step.credit > self.state.usable:  # the one guard a session's rule cannot see
            raise LocalProtocolError(f"amount {amount} µJ exceeds usable {self.state.usable} µJ")
        return self._apply(s, step)

    def commit(self, node: int, now: int) -> list[Action]:
        return self._step(self._session_or_error(node), Decide(Decision.COMMIT), now)

    def abort(self, node: int, now: int) -> list[Action]:
        return self._step(self._session_or_error(node), Decide(Decision.ABORT), now)

    def receive(self, msg: ToSupervisor, now: int) -> list[Action]:
        """Feed a decoded client message; messages for unknown nodes are ignored."""
        i = self._index.get(msg.node)
        if i is None:
            return []
        return self._step(self.state.sessions[i], msg, now)

    def get_timer(self) -> int | None:
        """The earliest deadline of any session, or None (a heap kept up as sessions change:
        no scan of every session per frame)."""
        sessions = self.state.sessions
        heap = self._deadlines
        if self._deadlines_of is not self.state:
            heap = [(s.deadline, i) for i, s in enumerate(sessions) if s.deadline is not None]
            heapq.heapify(heap)
            self._deadlines, self._deadlines_of = heap, self.state
        while heap and sessions[heap[0][1]].deadline != heap[0][0]:
            heapq.heappop(heap)  # a deadline its session no longer has
        return heap[0][0] if heap else None

    def handle_timer(self, now: int) -> list[Action]:
        """Fire every session whose deadline is at or before ``now``."""
        actions: list[Action] = []
        for s in self.state.sessions:
            if s.deadline is not None and s.deadline <= now:
                actions += self.fire_timer(s.node, now)
        return actions

    def fire_timer(self, node: int, now: int) -> list[Action]:
        """Fire one node's timer (the model checker fires timers one at a time)."""
        return self._step(self.session(node), RESPONSE_TIMEOUT, now)

    def inject(self, amount: int) -> None:
        """Add energy from outside the system to Us (counted as injected)."""
        self.state = inject_into(self.state, amount)

    def withdraw(self, amount: int) -> None:
        """Take energy out of Us to outside the system (counted as withdrawn): a gateway's
        return upstream."""
        self.state = withdraw_from(self.state, amount)

    def power_loss(self, now: int, nonce: int = 0) -> None:
        """Lose volatile state and restart from the persistent record. ``nonce``: a fresh
        random number for rules that have every start confirmed (witnessed: the SYNC's)."""
        event = PowerLoss(nonce)
        for s in self.state.sessions:
            self._step(s, event, now)

    def resync(self, node: int, now: int, nonce: int) -> list[Action]:
        """Witnessed rules: re-sync node ``node`` alone (``witnessed.resync_session``:
        SYNC(``nonce``) sent, its books and counts taken as at a start; no other node waits for
        it), e.g. when a begin is refused as beyond its window (``WindowClosed``). ``nonce``:
        fresh, random. Refused (``LocalProtocolError``) under other rules and unless the
        session is IDLE."""
        s = self._session_or_error(node)
        if not self.variant.lifts_tx:  # rules without SYNC
            raise LocalProtocolError(f"the {self.variant.name} rules have no re-sync")
        return self._apply(s, witnessed.resync_session(self.timing, s, nonce, now))

    def is_quiescent(self) -> bool:
        return all(s.phase is Phase.IDLE for s in self.state.sessions)

    def _session_or_error(self, node: int) -> Session:
        if node not in self._index:
            raise LocalProtocolError(f"node {node} is not managed by this supervisor")
        return self.session(node)

    def _step(self, s: Session, event: Event, now: int) -> list[Action]:
        return self._apply(s, self.rules.step(self.timing, s, event, now))

    def _apply(self, s: Session, step: SessionStep) -> list[Action]:
        if step.session is s and not step.credit:  # nothing changed (an ignored frame)
            return list(step.actions)
        before, i = self.state, self._index[s.node]
        self.state = apply_session(before, i, step)
        if self._deadlines_of is before:  # keep the heap: one entry for a new deadline
            self._deadlines_of = self.state
            deadline = step.session.deadline
            if deadline is not None and deadline != s.deadline:
                heapq.heappush(self._deadlines, (deadline, i))
                if len(self._deadlines) > 2 * len(self.state.sessions) + 16:
                    self._deadlines_of = None  # mostly left entries: rebuilt when next read
        if step.credit or self.rules.persistent(s) != self.rules.persistent(step.session):
            return [Persist(), *step.actions]
        return list(step.actions)
