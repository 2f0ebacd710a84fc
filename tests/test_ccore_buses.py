"""The compiled core over several buses (``canergy.ccore.buses``: one C supervisor per bus, one
budget) side by side with ``canergy.core.Supervisor`` over the same session keys: the same
grants, decisions, client messages, timers, starts, restarts and injections give the same
actions and the same state, field for field, whichever bus's supervisor holds Us. A frame is
handed to the supervisor of the bus it arrived on only: in the name of a node of another bus
it changes nothing."""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Any, cast

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule
from support.c_binding import DECODE_OK, library
from support.strategies import client_answer

from canergy.bus_keys import bus_of, node_of, session_key
from canergy.ccore.buses import CompiledBuses
from canergy.ccore.supervisor import make_supervisor, missing
from canergy.codec import Codec
from canergy.core.actions import Acknowledged, Action, Persist
from canergy.core.errors import LocalProtocolError
from canergy.core.state import Phase
from canergy.core.supervisor import Supervisor
from canergy.core.timing import Timing
from canergy.messages import QUANTUM_UJ, Ack, Debit, Message, Telemetry, ToSupervisor

A, B = 0, 1
KEYS = (session_key(A, 3), session_key(A, 5), session_key(B, 3), session_key(B, 9))
"""Node 3 on both buses, node 5 on bus A only, node 9 on bus B only."""
STRAYS = (session_key(A, 9), session_key(B, 5), session_key(A, 4))
"""Nodes a frame may name on a bus that does not have them."""
CODEC = Codec()
T = Timing(response_timeout_us=1_000, retries=2)
SYNC_ANSWER = (Debit.BOOKS, Debit.START | Debit.SYNC, Debit.START | Debit.SYNC | Debit.RC_UNKNOWN)
amounts = st.one_of(
    st.integers(1, 3_000).map(lambda mj: mj * QUANTUM_UJ),
    st.sampled_from([0, 500, 65_536_000]),
)
nodes = st.sampled_from([*KEYS, *STRAYS])


def compiled(initial: int, **kwargs: Any) -> CompiledBuses:
    """The composite on the tests' build of the library (UBSan; ASan in its child run)."""
    return CompiledBuses(KEYS, initial, module=library().module, **kwargs)


def steps(actions: list[Action]) -> tuple[bool, list[Action]]:
    """Whether a persist was asked, and every other action in order (the Python core asks
    before each session's step, a C supervisor once per call)."""
    return any(isinstance(a, Persist) for a in actions), [
        a for a in actions if not isinstance(a, Persist)
    ]


def on_bus(msg: Message) -> tuple[int, int, bytes]:
    """A message keyed by session key as its bus carries it: the bus index, the identifier
    and the data (the frame names the plain node id)."""
    ident, data = CODEC.encode(replace(msg, node=node_of(msg.node)))
    return bus_of(msg.node), ident, data


class BusesSideBySide(RuleBasedStateMachine):
    variant = "hardened"
    timing = T

    def __init__(self) -> None:
        super().__init__()
        self.py = Supervisor(KEYS, 10_000_000, timing=self.timing, variant=self.variant)
        self.c = compiled(10_000_000, timing=self.timing, variant=self.variant)
        self.now = 0

    def _same(self, py: Any, c: Any) -> None:
        try:
            expected = py()
        except LocalProtocolError as exc:
            with pytest.raises(LocalProtocolError) as got:
                c()
            if "waiting" in str(exc) or "exceeds usable" in str(exc):
                assert str(got.value) == str(exc)  # every bus's nodes, the whole pool
            return
        got = c()
        assert (got is None) == (expected is None)
        if expected is not None:
            assert steps(got) == steps(expected)

    @rule(node=nodes, amount=amounts)
    def begin(self, node: int, amount: int) -> None:
        self._same(
            lambda: self.py.begin(node, amount, self.now),
            lambda: self.c.begin(node, amount, self.now),
        )

    @rule(node=nodes, commit=st.booleans())
    def decide(self, node: int, commit: bool) -> None:
        self._same(
            lambda: (self.py.commit if commit else self.py.abort)(node, self.now),
            lambda: (self.c.commit if commit else self.c.abort)(node, self.now),
        )

    @rule(data=st.data())
    def receive(self, data: st.DataObject) -> None:
        node = data.draw(nodes)
        s = self.py.session(node) if node in KEYS else None
        tx, credited = (0, 0) if s is None else (s.tx, s.returns_credited)
        msg = cast(ToSupervisor, client_answer(data, node, tx, credited))
        self._same(lambda: self.py.receive(msg, self.now), lambda: self.c.receive(msg, self.now))

    @rule(data=st.data())
    def debit(self, data: st.DataObject) -> None:
        """A RESUME or a SYNC's books or counts near the session's (witnessed rules)."""
        node = data.draw(st.sampled_from(KEYS))
        s = self.py.session(node)
        seq = (s.returns_credited + data.draw(st.integers(-2, 3))) & 0xFFFF
        nonce = data.draw(st.sampled_from([0, 7, s.sync_nonce]))
        flags = data.draw(st.sampled_from([Debit.START, *SYNC_ANSWER]))
        amount = data.draw(st.sampled_from([0, 1, 2_000]))
        if flags == Debit.BOOKS:
            rc = (s.delivered // QUANTUM_UJ + data.draw(st.integers(-3, 3))) & 0xFFFFFF
            seq, amount = rc & 0xFFFF, rc >> 16
        elif flags & ~Debit.RC_UNKNOWN == Debit.START | Debit.SYNC:
            amount = (s.tx + data.draw(st.integers(-3, 3))) & 0xFFFF
        msg = Debit(node, nonce, flags, seq, amount)
        self._same(lambda: self.py.receive(msg, self.now), lambda: self.c.receive(msg, self.now))

    @rule(data=st.data(), stopping=st.booleans(), dt=st.integers(0, 1_500))
    def fast_answer(self, data: st.DataObject, stopping: bool, dt: int) -> None:
        """A frame on its bus's fast path (``answer_on``), against the Python core given the
        same message (and the decision on an ACK). A frame in the name of a node its bus lacks
        (a stray) changes nothing on either."""
        self.now += dt
        node = data.draw(nodes)
        s = self.py.session(node) if node in KEYS else None
        tx, credited = (0, 0) if s is None else (s.tx, s.returns_credited)
        msg = client_answer(data, node, tx, credited, telemetry=True)
        bus, ident, payload = on_bus(msg)
        answer = self.c.answer_on(bus)
        status, _, _, decoded, _ = answer(ident, payload, True, False, self.now, stopping)
        if node not in KEYS:
            assert status != DECODE_OK and decoded is None
        if decoded is not None:
            assert decoded == msg  # keyed by its bus
        if status != DECODE_OK and not isinstance(decoded or msg, Telemetry):
            self.c.receive(cast(ToSupervisor, decoded or msg), self.now)
        if isinstance(msg, Telemetry):
            return
        for action in self.py.receive(cast(ToSupervisor, msg), self.now):
            if isinstance(action, Acknowledged):
                (self.py.abort if stopping else self.py.commit)(action.node, self.now)

    @rule(nonce=st.integers(0, 0xFFFF))
    def start(self, nonce: int) -> None:
        self.py.power_loss(self.now, nonce=nonce)
        self.c.power_loss(self.now, nonce=nonce)

    @rule(dt=st.integers(0, 3_000))
    def timer(self, dt: int) -> None:
        self.now += dt
        self._same(lambda: self.py.handle_timer(self.now), lambda: self.c.handle_timer(self.now))

    @rule()
    def restart(self) -> None:
        """A reset from the saved record, as ``canergy supervisor`` restarts from its file:
        one record of every bus, Us summed."""
        self.py.power_loss(self.now)
        self.c = compiled(1, timing=self.timing, state=self.c.state, variant=self.variant)
        self.c.power_loss(self.now)

    @rule(amount=st.integers(1, 5_000_000))
    def inject(self, amount: int) -> None:
        self.py.inject(amount)
        self.c.inject(amount)

    @invariant()
    def same_state(self) -> None:
        assert self.c.state == self.py.state
        assert self.c.unconfirmed() == self.py.unconfirmed()
        assert self.c.get_timer() == self.py.get_timer()
        assert self.c.is_quiescent() == self.py.is_quiescent()
        assert sum(part.usable for part in self.c.parts) == self.py.usable


MACHINE = settings(
    max_examples=int(os.environ.get("CANERGY_SIDE_BY_SIDE_EXAMPLES", "100")),
    stateful_step_count=60,
    deadline=None,
)
TestBusesSideBySide = BusesSideBySide.TestCase
TestBusesSideBySide.settings = MACHINE


class WitnessedBusesSideBySide(BusesSideBySide):
    variant = "witnessed"
    timing = replace(T, window=3)


TestWitnessedBusesSideBySide = WitnessedBusesSideBySide.TestCase
TestWitnessedBusesSideBySide.settings = MACHINE


def _answer(c: CompiledBuses, msg: Message, bus: int, now: int) -> int:
    """``msg`` (its plain node id) as a frame arriving on bus ``bus``: the fast path's status."""
    ident, data = CODEC.encode(msg)
    return c.answer_on(bus)(ident, data, True, False, now, False)[0]


def test_a_frame_settles_only_the_session_of_its_own_bus() -> None:
    """Node 3 is on both buses; only bus A's has a grant open. Its ACK arriving on bus B is not
    taken by bus A's session, nor is one on bus A in the name of node 9 (bus B's only)."""
    c = compiled(10_000_000)
    c.begin(session_key(A, 3), 2_000_000, 0)
    c.begin(session_key(B, 9), 1_000_000, 0)
    before = c.state
    assert _answer(c, Ack(3, 1), B, 10) != DECODE_OK
    assert _answer(c, Ack(9, 1), A, 10) != DECODE_OK
    assert c.state == before
    assert c.session(session_key(A, 3)).phase is Phase.WAIT_ACK
    assert c.session(session_key(B, 9)).phase is Phase.WAIT_ACK
    assert _answer(c, Ack(3, 1), A, 20) == DECODE_OK  # on its own bus: taken, committed
    assert c.session(session_key(A, 3)).phase is Phase.WAIT_CONFIRM
    assert c.session(session_key(B, 3)).phase is Phase.IDLE


def test_the_pool_moves_whole_to_the_bus_granting_and_is_saved_summed() -> None:
    """Us is one pool: a grant on bus B takes it from bus A's supervisor (where the start put
    it), a return on bus A lands there, and the next grant on bus B gathers it again; at every
    step the supervisors' Us summed is what the record holds, and the identity holds."""
    c = compiled(3_000_000)
    assert [p.usable for p in c.parts] == [3_000_000, 0]
    c.begin(session_key(B, 9), 2_000_000, 0)
    assert [p.usable for p in c.parts] == [0, 1_000_000]
    assert c.state.usable == 1_000_000
    c.begin(session_key(A, 5), 1_000_000, 0)
    assert [p.usable for p in c.parts] == [0, 0]
    with pytest.raises(LocalProtocolError, match="exceeds usable 0"):
        c.begin(session_key(B, 3), 1_000, 0)
    st = c.state
    reserved = sum(s.reserved for s in st.sessions)
    assert st.usable + reserved == st.initial + st.injected - st.withdrawn
    again = compiled(1, state=st)  # the record round-trips, Us summed into the first bus's
    assert again.state == st and [p.usable for p in again.parts] == [0, 0]


def test_a_witnessed_start_waits_for_every_bus() -> None:
    """After a start from the record, no grant on bus A while a node of bus B has not
    confirmed its books, in the Python core's words (session keys)."""
    py = Supervisor(KEYS, 10_000_000, variant="witnessed")
    c = compiled(10_000_000, variant="witnessed")
    py.power_loss(0, nonce=5)
    c.power_loss(0, nonce=5)
    assert c.unconfirmed() == py.unconfirmed() == KEYS
    with pytest.raises(LocalProtocolError) as got:
        c.begin(session_key(A, 3), 1_000, 0)
    assert "waiting for node(s) 3, 5, 259, 265" in str(got.value)


def test_make_supervisor_over_buses_runs_one_c_supervisor_per_bus() -> None:
    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    core = make_supervisor("c", KEYS, 1_000, buses=True)
    assert isinstance(core, CompiledBuses) and core.implementation == "c"
    assert [part.nodes for part in core.parts] == [(3, 5), (3, 9)]
    assert core.nodes == KEYS
    with pytest.raises(ValueError, match="nodes on every bus"):
        CompiledBuses((session_key(1, 3),), 0, module=library().module)
