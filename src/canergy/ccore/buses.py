"""The compiled supervisor core over several buses: one C supervisor per bus, one budget.

The C library is one supervisor per bus, as on a microcontroller: its sessions are keyed by
the node id a frame carries. ``CompiledBuses`` holds one ``CompiledSupervisor`` per bus and
takes the service's session keys (``bus << 8 | node``, ``canergy.bus_keys``), handing each call
to the bus's supervisor with the plain node id and keying what comes back. A frame is only ever
handed to the supervisor of the bus it arrived on (``answer_on``; with a key ``auth_answer_on``,
``auth_pair_on``, each bus's supervisor holding its bus's node keys, ``use_keys``): node 5 on
bus A never reaches bus B's session of node 5.

The usable budget Us is one pool. The supervisors' Us summed is Us: the state file stores the
sum (``state``), a start loads it into the first bus's supervisor, and a grant on a bus first
gathers the whole pool into that bus's supervisor (``begin``): plain moves in memory, between
two calls on the loop's thread, which neither create nor lose a µJ (the sum is the same before
and after, and the books are written as one record, of the sum). Each supervisor's own
identity (Us + reserved + delivered - returned = initial + injected - withdrawn) holds for the
sum only; each C call checks only what it debits against the Us it holds, which is the pool.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Any, ParamSpec, TypeVar, cast

from canergy.bus_keys import bus_of, node_of, session_key
from canergy.ccore.calls import Answer, AuthAnswer, AuthPair
from canergy.ccore.grants import CompiledGrantCaps
from canergy.ccore.joins import CompiledJoinHold
from canergy.ccore.supervisor import CompiledHeard, CompiledSupervisor
from canergy.ccore.witness import CompiledReturnGate
from canergy.core.actions import (
    Acknowledged,
    Action,
    Admitted,
    AheadOfImage,
    Resolved,
    ReturnCredited,
    Send,
)
from canergy.core.errors import LocalProtocolError
from canergy.core.state import Session, SupervisorState
from canergy.core.timing import Timing
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.messages import Debit, Join, Message, Return, Telemetry, ToSupervisor

M = TypeVar("M", bound=Message)
_P = ParamSpec("_P")

NODE_ACTIONS = (Acknowledged, Resolved, ReturnCredited, Admitted, AheadOfImage)
"""A supervisor's actions that name a node (re-keyed per bus)."""


class CompiledBuses:
    """``core.Supervisor`` over session keys of several buses, each bus's rules in C."""

    implementation = "c"

    def __init__(
        self,
        keys: Iterable[int],
        initial: int,
        *,
        timing: Timing | None = None,
        state: SupervisorState | None = None,
        id_base: int | None = None,
        variant: str = "hardened",
        start_without: Iterable[int] = (),
        module: Any = None,
    ) -> None:
        """As ``CompiledSupervisor``'s, over session keys: every bus index from 0 up to the
        highest one has nodes. ``initial`` (and a ``state``'s Us, injected and withdrawn) go to
        the first bus's supervisor."""
        key_list = sorted(set(keys))
        count = bus_of(key_list[-1]) + 1 if key_list else 0
        by_bus: list[list[int]] = [[] for _ in range(count)]
        for key in key_list:
            by_bus[bus_of(key)].append(node_of(key))
        if not count or not all(by_bus):
            raise ValueError("the C core over several buses takes nodes on every bus")
        self.start_without = frozenset(start_without)
        if not self.start_without <= set(key_list):
            raise ValueError("start_without names nodes this supervisor does not manage")
        states = _split(state, key_list, count) if state is not None else [None] * count
        self._parts = [
            CompiledSupervisor(
                nodes,
                initial if bus == 0 else 0,
                timing=timing,
                state=states[bus],
                id_base=id_base,
                variant=variant,
                start_without=[node_of(k) for k in self.start_without if bus_of(k) == bus],
                module=module,
            )
            for bus, nodes in enumerate(by_bus)
        ]
        first = self._parts[0]
        self.variant = first.variant
        self.timing = first.timing
        self.codec = first.codec
        self._keys = tuple(key_list)
        self._managed = frozenset(key_list)
        self._keyed: dict[int, tuple[Session, Session]] = {}
        """Each key's session as last asked for: the bus's (plain node) and its keyed copy."""

    # -- state -----------------------------------------------------------------------------
    @property
    def parts(self) -> tuple[CompiledSupervisor, ...]:
        """The supervisors, one per bus, in bus order."""
        return tuple(self._parts)

    @property
    def nodes(self) -> tuple[int, ...]:
        return self._keys

    @property
    def state(self) -> SupervisorState:
        """One record for every bus: Us, injected and withdrawn summed, sessions keyed."""
        initial = usable = injected = withdrawn = 0
        sessions: list[Session] = []
        for bus, part in enumerate(self._parts):
            st = part.state
            initial += st.initial
            usable += st.usable
            injected += st.injected
            withdrawn += st.withdrawn
            sessions += [replace(s, node=session_key(bus, s.node)) for s in st.sessions]
        return SupervisorState(initial, usable, injected, tuple(sessions), withdrawn)

    @property
    def usable(self) -> int:
        return sum(part.usable for part in self._parts)

    def idle(self, node: int) -> bool:
        return self._parts[bus_of(node)].idle(node_of(node))

    def session(self, node: int) -> Session:
        inner = self._parts[bus_of(node)].session(node_of(node))
        known = self._keyed.get(node)
        if known is not None and known[0] is inner:
            return known[1]
        keyed = replace(inner, node=node)
        self._keyed[node] = (inner, keyed)
        return keyed

    def is_quiescent(self) -> bool:
        return all(part.is_quiescent() for part in self._parts)

    def unconfirmed(self) -> tuple[int, ...]:
        """The nodes of every bus whose books this start waits for before any grant."""
        return tuple(
            session_key(bus, n) for bus, part in enumerate(self._parts) for n in part.unconfirmed()
        )

    # -- requests --------------------------------------------------------------------------
    def begin(self, node: int, amount: int, now: int) -> list[Action]:
        """Reserve ``amount`` µJ from Us (the whole pool) and send node ``node`` an intention;
        refused while a start waits for any bus's node's books."""
        part = self._granting(node)
        return self._keyed_actions(bus_of(node), part.begin(node_of(node), amount, now))

    def begin_encoded(
        self, node: int, amount: int, now: int
    ) -> tuple[list[Action], list[tuple[int, bytes]]]:
        """``begin`` with its INTENTION as C encoded it, to send on the node's bus."""
        part = self._granting(node)
        actions, frames = part.begin_encoded(node_of(node), amount, now)
        return self._keyed_actions(bus_of(node), actions), frames

    def begin_protected(
        self, node: int, amount: int, now: int
    ) -> tuple[list[Action], list[tuple[int, bytes]]]:
        """``begin`` with its INTENTION protected in C under the node's key (``use_keys``),
        to send on the node's bus (``CompiledSupervisor.begin_protected``)."""
        part = self._granting(node)
        actions, frames = part.begin_protected(node_of(node), amount, now)
        return self._keyed_actions(bus_of(node), actions), frames

    def _granting(self, node: int) -> CompiledSupervisor:
        """The supervisor of ``node``'s bus, holding the whole pool, once every bus's nodes
        have confirmed their books (``LocalProtocolError`` otherwise)."""
        self._check(node)
        if waiting := self.unconfirmed():
            raise LocalProtocolError(
                "no grant before every node has confirmed its books after this start: waiting "
                f"for node(s) {', '.join(map(str, waiting))}"
            )
        part = self._parts[bus_of(node)]
        for other in self._parts:
            if other is not part:
                other.hand_usable(part)
        return part

    def commit(self, node: int, now: int) -> list[Action]:
        self._check(node)
        return self._keyed_actions(
            bus_of(node), self._parts[bus_of(node)].commit(node_of(node), now)
        )

    def abort(self, node: int, now: int) -> list[Action]:
        self._check(node)
        return self._keyed_actions(
            bus_of(node), self._parts[bus_of(node)].abort(node_of(node), now)
        )

    def resync(self, node: int, now: int, nonce: int) -> list[Action]:
        """Re-sync one node (its session key) on its bus's supervisor."""
        self._check(node)
        return self._keyed_actions(
            bus_of(node), self._parts[bus_of(node)].resync(node_of(node), now, nonce)
        )

    def receive(self, msg: ToSupervisor, now: int) -> list[Action]:
        """Feed a decoded client message (node: its session key); unknown nodes are ignored."""
        if msg.node not in self._managed:
            return []
        bus = bus_of(msg.node)
        plain = replace(msg, node=node_of(msg.node))
        return self._keyed_actions(bus, self._parts[bus].receive(plain, now))

    @property
    def verdicts(self) -> tuple[int, int]:
        """``CompiledSupervisor.verdicts``: every bus's supervisor is of one library."""
        return self._parts[0].verdicts

    def answer_on(self, bus: int) -> Answer:
        """Bus ``bus``'s frame path into its own supervisor (``CompiledSupervisor.on_answer``,
        what it decodes and does keyed): a frame from that bus reaches no other bus's
        sessions."""
        part = self._parts[bus]
        answer = part.on_answer

        def on_bus(
            arbitration_id: int,
            data: bytes | bytearray,
            extended: bool,
            remote: bool,
            now: int,
            abort: bool,
        ) -> tuple[int, list[Action], list[tuple[int, bytes]], Message | None, int]:
            status, actions, frames, msg, verdict = answer(
                arbitration_id, data, extended, remote, now, abort
            )
            if actions:
                actions = self._keyed_actions(bus, actions)
            if msg is not None:
                msg = replace(msg, node=session_key(bus, msg.node))
            return status, actions, frames, msg, verdict

        return on_bus

    def use_keys(
        self, key_for: Callable[[int], bytes], *, classic: bool = False, bus: int | None = None
    ) -> None:
        """Authenticated mode (``CompiledSupervisor.use_keys``): the keys of bus ``bus``'s
        nodes (None: every bus's) set up in its supervisor, ``key_for`` taking the plain node
        id as that bus's ``FrameAuth`` does."""
        for part in self._parts if bus is None else [self._parts[bus]]:
            part.use_keys(key_for, classic=classic)

    def auth_answer_on(self, bus: int) -> AuthAnswer:
        """Bus ``bus``'s frame path with a key, FD layout, into its own supervisor
        (``CompiledSupervisor.on_auth_answer``, what it does keyed): verified under that bus's
        keys against that bus's sessions' counters."""
        return self._keyed_path(bus, self._parts[bus].on_auth_answer)

    def auth_pair_on(self, bus: int) -> AuthPair:
        """``auth_answer_on`` in the classic layout (``CompiledSupervisor.on_auth_pair``)."""
        return self._keyed_path(bus, self._parts[bus].on_auth_pair)

    def _keyed_path(
        self, bus: int, call: Callable[_P, tuple[int, list[Action], list[tuple[int, bytes]], int]]
    ) -> Callable[_P, tuple[int, list[Action], list[tuple[int, bytes]], int]]:
        """``call``, one bus's keyed frame path, with its actions keyed by session."""

        def on_bus(
            *args: _P.args, **kwargs: _P.kwargs
        ) -> tuple[int, list[Action], list[tuple[int, bytes]], int]:
            status, actions, frames, fv = call(*args, **kwargs)
            return status, self._keyed_actions(bus, actions) if actions else actions, frames, fv

        return on_bus

    def heard_table(self, lost_after_us: int) -> BusesHeard:
        """The TELEMETRY table in C (``CompiledSupervisor.heard_table``), one per bus's
        supervisor: each bus's frame path takes a TELEMETRY into its own."""
        return BusesHeard([part.heard_table(lost_after_us) for part in self._parts])

    def return_gate(self, hold_us: int, block_us: int, hold: bool) -> BusesReturnGate:
        """The witness in C (``CompiledSupervisor.return_gate``), one per bus's supervisor."""
        return BusesReturnGate([part.return_gate(hold_us, block_us, hold) for part in self._parts])

    def join_hold(
        self,
        hold_us: int,
        local_nodes: frozenset[int],
        intrusions: Intrusions,
        refusals: Refusals,
        authenticated: Callable[[], bool],
    ) -> BusesJoinHold:
        """The held JOINs in C (``CompiledSupervisor.join_hold``), one per bus's supervisor;
        what each reports and returns to admit is keyed by its bus."""
        holds = []
        for bus, part in enumerate(self._parts):
            local = frozenset(node_of(k) for k in local_nodes if bus_of(k) == bus)
            holds.append(
                part.join_hold(
                    hold_us,
                    local,
                    cast(Intrusions, _Keyed(intrusions, bus)),
                    cast(Refusals, _Keyed(refusals, bus)),
                    authenticated,
                )
            )
        return BusesJoinHold(holds)

    def grant_caps(self, limits: Limits, policy: TopUp | None) -> CompiledGrantCaps | None:
        """The grant caps in C (they hold no node's record): the first bus's supervisor's."""
        return self._parts[0].grant_caps(limits, policy)

    def get_timer(self) -> int | None:
        timers = [t for part in self._parts if (t := part.get_timer()) is not None]
        return min(timers) if timers else None

    def handle_timer(self, now: int) -> list[Action]:
        """Fire every session due, bus by bus (the keys' order)."""
        actions: list[Action] = []
        for bus, part in enumerate(self._parts):
            timer = part.get_timer()
            if timer is not None and timer <= now:
                actions += self._keyed_actions(bus, part.handle_timer(now))
        return actions

    def inject(self, amount: int) -> None:
        self._parts[0].inject(amount)

    def power_loss(self, now: int, nonce: int = 0) -> None:
        """Every bus's supervisor restarts from the record, with the same nonce."""
        for part in self._parts:
            part.power_loss(now, nonce)

    # -- internals -------------------------------------------------------------------------
    def _check(self, node: int) -> None:
        if node not in self._managed:
            raise LocalProtocolError(f"node {node} is not managed by this supervisor")

    @staticmethod
    def _keyed_actions(bus: int, actions: list[Action]) -> list[Action]:
        """A bus's supervisor's actions, its node ids replaced by their session keys."""
        if not bus:
            return actions  # bus 0's keys are its node ids
        keyed: list[Action] = []
        for action in actions:
            if isinstance(action, Send):
                message = action.message
                keyed.append(Send(replace(message, node=session_key(bus, message.node))))
            elif isinstance(action, NODE_ACTIONS):
                keyed.append(replace(action, node=session_key(bus, action.node)))
            else:
                keyed.append(action)
        return keyed


def _split(state: SupervisorState, keys: list[int], count: int) -> list[SupervisorState | None]:
    """A saved record of every bus as one per bus: the first holds Us, injected and
    withdrawn, each its sessions with plain node ids."""
    if tuple(s.node for s in state.sessions) != tuple(keys):
        raise ValueError("the state's nodes are not this supervisor's")
    sessions: list[list[Session]] = [[] for _ in range(count)]
    for s in state.sessions:
        sessions[bus_of(s.node)].append(replace(s, node=node_of(s.node)))
    return [
        SupervisorState(
            state.initial, state.usable, state.injected, tuple(sessions[0]), state.withdrawn
        )
        if bus == 0
        else SupervisorState(0, 0, 0, tuple(sessions[bus]), 0)
        for bus in range(count)
    ]


def _plain(msg: M) -> tuple[int, M]:
    """A message keyed by session key as its bus's supervisor takes it: the bus, and the
    message with the plain node id."""
    return bus_of(msg.node), replace(msg, node=node_of(msg.node))


def _keyed(bus: int, msg: M) -> M:
    return replace(msg, node=session_key(bus, msg.node)) if bus else msg


class _Keyed:
    """``Intrusions`` or ``Refusals`` as a bus's held JOINs record into them: by session key."""

    def __init__(self, inner: Intrusions | Refusals, bus: int) -> None:
        self._inner = inner
        self._bus = bus

    def record(self, node: int, *args: Any, **kwargs: Any) -> None:
        self._inner.record(session_key(self._bus, node), *args, **kwargs)


class BusesHeard:
    """The TELEMETRY tables of every bus (``CompiledHeard``), by session key."""

    implementation = "c"

    def __init__(self, tables: list[CompiledHeard]) -> None:
        self.tables = tables

    def of(self, node: int) -> Any:
        return self.tables[bus_of(node)].of(node_of(node))

    def telemetry(self, node: int, s: Session, level_mj: int, flags: int, now: int) -> int:
        return self.tables[bus_of(node)].telemetry(node_of(node), s, level_mj, flags, now)

    def credited(self, node: int, amount_uj: int, now: int) -> None:
        self.tables[bus_of(node)].credited(node_of(node), amount_uj, now)


class BusesReturnGate:
    """The witnesses of every bus (``CompiledReturnGate``), by session key."""

    implementation = "c"

    def __init__(self, gates: list[CompiledReturnGate]) -> None:
        self.gates = gates
        self.hold_us = gates[0].hold_us
        self.block_us = gates[0].block_us

    def telemetry(self, msg: Telemetry, credited: int, now: int) -> tuple[list[str], list[str]]:
        bus, plain = _plain(msg)
        return self.gates[bus].telemetry(plain, credited, now)

    def telemetry_words(
        self, msg: Telemetry, credited: Callable[[], int], found: int
    ) -> tuple[list[str], list[str]]:
        bus, plain = _plain(msg)
        return self.gates[bus].telemetry_words(plain, credited, found)

    def old(self, msg: Return, credited: int) -> bool:
        bus, plain = _plain(msg)
        return self.gates[bus].old(plain, credited)

    def hold(self, msg: Return, credited: int, now: int) -> str | None:
        bus, plain = _plain(msg)
        return self.gates[bus].hold(plain, credited, now)

    def hold_words(self, msg: Return, credited: int, verdict: int) -> str | None:
        bus, plain = _plain(msg)
        return self.gates[bus].hold_words(plain, credited, verdict)

    def hold_resume(self, msg: Debit, credited: int, now: int, hold: bool) -> bool:
        bus, plain = _plain(msg)
        return self.gates[bus].hold_resume(plain, credited, now, hold)

    def holds(self, node: int) -> bool:
        return self.gates[bus_of(node)].holds(node_of(node))

    def release(self, node: int, credited: int, now: int) -> list[Return | Debit]:
        bus = bus_of(node)
        return [_keyed(bus, m) for m in self.gates[bus].release(node_of(node), credited, now)]

    def holding(self) -> list[int]:
        return [session_key(b, n) for b, gate in enumerate(self.gates) for n in gate.holding()]

    def next_release(self) -> int | None:
        times = [t for gate in self.gates if (t := gate.next_release()) is not None]
        return min(times, default=None)

    def blocked(self, node: int, now: int) -> bool:
        return self.gates[bus_of(node)].blocked(node_of(node), now)

    def resume_held(self, node: int) -> bool:
        return self.gates[bus_of(node)].resume_held(node_of(node))

    def readmitted(self, node: int) -> None:
        self.gates[bus_of(node)].readmitted(node_of(node))

    def status(self, node: int) -> dict[str, int]:
        return self.gates[bus_of(node)].status(node_of(node))


class BusesJoinHold:
    """The held JOINs of every bus (``CompiledJoinHold``), by session key."""

    implementation = "c"

    def __init__(self, holds: list[CompiledJoinHold]) -> None:
        self.holds = holds

    def on_join(self, join: Join) -> None:
        bus, plain = _plain(join)
        self.holds[bus].on_join(plain)

    def holding(self, node: int) -> bool:
        return self.holds[bus_of(node)].holding(node_of(node))

    def resent(self, node: int) -> int:
        return self.holds[bus_of(node)].resent(node_of(node))

    def on_telemetry(self, msg: Telemetry, now: int) -> list[Join]:
        bus, plain = _plain(msg)
        return [_keyed(bus, join) for join in self.holds[bus].on_telemetry(plain, now)]

    def telemetry_taken(
        self, msg: Telemetry, now: int, found: int, nonce: int | None = None
    ) -> list[Join]:
        bus, plain = _plain(msg)
        taken = self.holds[bus].telemetry_taken(plain, now, found, nonce)
        return [_keyed(bus, join) for join in taken]

    def on_wakeup(self, now: int) -> list[Join]:
        out: list[Join] = []
        for bus, hold in enumerate(self.holds):
            out += [_keyed(bus, join) for join in hold.on_wakeup(now)]
        return out

    def next_wakeup(self) -> int | None:
        times = [t for hold in self.holds if (t := hold.next_wakeup()) is not None]
        return min(times, default=None)
