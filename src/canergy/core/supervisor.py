"""The supervisor: one usable budget Us, one session per node, sans-IO.

Reservations never move between nodes. Every method takes ``now`` (µs) and returns the actions to
carry out, ``Persist`` first when the persistent record changed.
"""

from __future__ import annotations

from collections.abc import Iterable

from canergy.core.actions import Action, Persist
from canergy.core.common import Actions
from canergy.core.errors import LocalProtocolError
from canergy.core.frozen import evolve
from canergy.core.state import Decision, Phase, Session, SupervisorState
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.messages import AMOUNT_MAX_MJ, MAX_NODE, MIN_NODE, QUANTUM_UJ, ToSupervisor


def check_amount(amount: int) -> None:
    """A transferable amount: a positive whole number of wire quanta that fits one frame."""
    if amount <= 0 or amount % QUANTUM_UJ or amount > AMOUNT_MAX_MJ * QUANTUM_UJ:
        raise LocalProtocolError(
            f"amount {amount} µJ must be a positive multiple of {QUANTUM_UJ} µJ "
            f"and at most {AMOUNT_MAX_MJ * QUANTUM_UJ} µJ"
        )


def apply_session(st: SupervisorState, i: int, new: Session, credit: int) -> SupervisorState:
    """Put session ``i`` back into the state and credit ``credit`` µJ to Us (pure)."""
    sessions = (*st.sessions[:i], new, *st.sessions[i + 1 :])
    return evolve(st, usable=st.usable + credit, sessions=sessions)


class Supervisor:
    """Grants energy from its usable budget to client nodes."""

    def __init__(
        self,
        nodes: Iterable[int],
        initial: int,
        *,
        variant: str | Variant = "hardened",
        timing: Timing | None = None,
        state: SupervisorState | None = None,
    ) -> None:
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        self.rules = self.variant.supervisor
        self.timing = timing or Timing()
        node_list = sorted(set(nodes))
        if not node_list or not all(MIN_NODE <= n <= MAX_NODE for n in node_list):
            raise ValueError(f"nodes must be a non-empty set of ids {MIN_NODE}-{MAX_NODE}")
        if initial < 0:
            raise ValueError("initial budget must be >= 0")
        self.state = state or SupervisorState(
            initial, initial, 0, tuple(Session(n) for n in node_list)
        )
        self._index = {s.node: i for i, s in enumerate(self.state.sessions)}

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(self._index)

    def session(self, node: int) -> Session:
        return self.state.sessions[self._index[node]]

    def begin(self, node: int, amount: int, now: int) -> list[Action]:
        """Reserve ``amount`` µJ from Us and send node ``node`` an intention."""
        check_amount(amount)
        s = self._session_or_error(node)
        if s.phase is not Phase.IDLE:
            raise LocalProtocolError(f"node {node} already has transaction {s.tx} open")
        if amount > self.state.usable:
            raise LocalProtocolError(f"amount {amount} µJ exceeds usable {self.state.usable} µJ")
        s, actions = self.rules.begin(self.timing, s, amount, now)
        return self._apply(s, actions, -amount)

    def commit(self, node: int, now: int) -> list[Action]:
        return self._decide(node, Decision.COMMIT, now)

    def abort(self, node: int, now: int) -> list[Action]:
        return self._decide(node, Decision.ABORT, now)

    def receive(self, msg: ToSupervisor, now: int) -> list[Action]:
        """Feed a decoded client message; messages for unknown nodes are ignored."""
        i = self._index.get(msg.node)
        if i is None:
            return []
        return self._apply(*self.rules.receive(self.timing, self.state.sessions[i], msg, now))

    def get_timer(self) -> int | None:
        """The earliest deadline of any session, or None."""
        deadlines = [s.deadline for s in self.state.sessions if s.deadline is not None]
        return min(deadlines) if deadlines else None

    def handle_timer(self, now: int) -> list[Action]:
        """Fire every session whose deadline is at or before ``now``."""
        actions: list[Action] = []
        for s in self.state.sessions:
            if s.deadline is not None and s.deadline <= now:
                actions += self.fire_timer(s.node, now)
        return actions

    def fire_timer(self, node: int, now: int) -> list[Action]:
        """Fire one node's timer (the model checker fires timers one at a time)."""
        return self._apply(*self.rules.timer(self.timing, self.session(node), now))

    def inject(self, amount: int) -> None:
        """Add energy from outside the system to Us (counted as injected)."""
        if amount <= 0:
            raise LocalProtocolError("injected energy must be positive")
        st = self.state
        self.state = evolve(st, usable=st.usable + amount, injected=st.injected + amount)

    def power_loss(self, now: int) -> None:
        """Lose volatile state and restart from the persistent record."""
        sessions = tuple(self.rules.power_loss(s, now) for s in self.state.sessions)
        self.state = evolve(self.state, sessions=sessions)

    def is_quiescent(self) -> bool:
        return all(s.phase is Phase.IDLE for s in self.state.sessions)

    def _decide(self, node: int, decision: Decision, now: int) -> list[Action]:
        s = self._session_or_error(node)
        if s.phase is not Phase.ACKED:
            raise LocalProtocolError(f"node {node}: nothing acknowledged to decide on")
        return self._apply(*self.rules.decide(self.timing, s, decision, now))

    def _session_or_error(self, node: int) -> Session:
        if node not in self._index:
            raise LocalProtocolError(f"node {node} is not managed by this supervisor")
        return self.session(node)

    def _apply(self, new: Session, actions: Actions, credit: int) -> list[Action]:
        i = self._index[new.node]
        old = self.state.sessions[i]
        self.state = apply_session(self.state, i, new, credit)
        if credit or self.rules.persistent(old) != self.rules.persistent(new):
            return [Persist(), *actions]
        return list(actions)
