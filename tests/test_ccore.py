"""The compiled supervisor core (``canergy.ccore``, the C supervisor through cffi) side by side
with ``canergy.core.Supervisor``: the same grants, decisions, client messages, timers, restarts
and injections give the same actions (every ``Send``, ``Acknowledged``, ``Resolved``,
``ReturnCredited`` and ``Admitted``, in order; ``Persist`` alike) and the same state, field for
field. The service drives both through this interface, so these are what it sees."""

from __future__ import annotations

import os
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import can
import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule
from support.c_binding import DECODE_OK, RX_NOT_CAN, compiled_core, library
from support.ccore_built import release
from support.strategies import client_answer
from support.wire import Wire

from canergy.auth.frames import FrameAuth, Layout, expected_freshness, freshness
from canergy.ccore.supervisor import CompiledSupervisor, CoreMissing, make_supervisor
from canergy.codec import Codec
from canergy.core.actions import Acknowledged, Action, Persist
from canergy.core.errors import LocalProtocolError
from canergy.core.supervisor import Supervisor
from canergy.core.timing import Timing
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import (
    QUANTUM_UJ,
    Ack,
    Commit,
    Committed,
    Debit,
    Direction,
    Intention,
    Return,
    Telemetry,
)

"""For the tests of the release module (``canergy supervisor --core c``'s, 127 sessions); the
others run the core on the tests' sanitizer build of the same builder (``compiled_core``)."""

NODES = (3, 5, 9, 127)
SYNC_ANSWER = (Debit.BOOKS, Debit.START | Debit.SYNC, Debit.START | Debit.SYNC | Debit.RC_UNKNOWN)
CODEC = Codec()
T = Timing(response_timeout_us=1_000, retries=2)
amounts = st.one_of(
    st.integers(1, 3_000).map(lambda mj: mj * QUANTUM_UJ),
    st.sampled_from([0, 500, 65_536_000, 2**40]),
)


def steps(actions: list[Action]) -> tuple[bool, list[Action]]:
    """Whether a persist was asked, and every other action in order (the Python core puts one
    Persist before each session's step; the C core asks once per call)."""
    return any(isinstance(a, Persist) for a in actions), [
        a for a in actions if not isinstance(a, Persist)
    ]


class SideBySide(RuleBasedStateMachine):
    variant = "hardened"
    timing = T
    build = ""
    """The build of the library the compiled core runs (``compiled_core``)."""

    def __init__(self) -> None:
        super().__init__()
        self.py = Supervisor(NODES, 10_000_000, timing=self.timing, variant=self.variant)
        self.c = compiled_core(
            NODES, 10_000_000, timing=self.timing, variant=self.variant, build=self.build
        )
        self.now = 0

    def _same(self, py: Any, c: Any) -> None:
        try:
            expected = py()
        except LocalProtocolError:
            with pytest.raises(LocalProtocolError):
                c()
            return
        got = c()
        assert (got is None) == (expected is None)
        if expected is not None:
            assert steps(got) == steps(expected)

    @rule(node=st.sampled_from([*NODES, 4]), amount=amounts)
    def begin(self, node: int, amount: int) -> None:
        self._same(
            lambda: self.py.begin(node, amount, self.now),
            lambda: self.c.begin(node, amount, self.now),
        )

    @rule(node=st.sampled_from([*NODES, 4]), commit=st.booleans())
    def decide(self, node: int, commit: bool) -> None:
        self._same(
            lambda: (self.py.commit if commit else self.py.abort)(node, self.now),
            lambda: (self.c.commit if commit else self.c.abort)(node, self.now),
        )

    @rule(data=st.data())
    def receive(self, data: st.DataObject) -> None:
        node = data.draw(st.sampled_from([*NODES, 4]))
        s = self.py.session(node) if node in NODES else None
        tx, credited = (0, 0) if s is None else (s.tx, s.returns_credited)
        msg = client_answer(data, node, tx, credited, telemetry=True)
        self._same(lambda: self.py.receive(msg, self.now), lambda: self.c.receive(msg, self.now))

    @rule(data=st.data(), fast=st.booleans())
    def debit(self, data: st.DataObject, fast: bool) -> None:
        """A DRAW, a RESUME, or a SYNC's books or counts near the session's counts (the hardened
        rules ignore them all), by ``receive`` or as the fast path hands it back to the
        caller."""
        node = data.draw(st.sampled_from([*NODES, 4]))
        s = self.py.session(node) if node in NODES else None
        credited, tx, sync = (0, 0, 0) if s is None else (s.returns_credited, s.tx, s.sync_nonce)
        seq = (credited + data.draw(st.integers(-2, 3))) & 0xFFFF
        nonce = data.draw(st.sampled_from([0, 7, sync, sync ^ 1]))
        kinds = [Debit.DRAW, Debit.START, Debit.START | Debit.DRAW, *SYNC_ANSWER]
        flags = data.draw(st.sampled_from(kinds))
        amount = data.draw(st.sampled_from([0, 1, 2_000]))
        if flags == Debit.DRAW:
            nonce, amount = 0, max(amount, 1)
        if flags == Debit.BOOKS:  # Rc near Gs, or far
            rc = s.delivered // QUANTUM_UJ if s is not None else 0
            rc = (rc + data.draw(st.integers(-3, 3_000) | st.just(0x7FFFFF))) & 0xFFFFFF
            seq, amount = rc & 0xFFFF, rc >> 16
        elif flags & ~Debit.RC_UNKNOWN == Debit.START | Debit.SYNC:  # counts, afresh or not:
            # ltx near tx, a window ahead, or behind
            amount = (tx + data.draw(st.integers(-3, 3) | st.sampled_from([64, 0x7FFF]))) & 0xFFFF
        msg = Debit(node, nonce, flags, seq, amount)
        if fast:
            _, actions, _, decoded, _ = self.c.on_answer(
                *CODEC.encode(msg), True, False, self.now, False
            )
            assert actions == [] and (decoded == msg or node not in NODES)
        self._same(lambda: self.py.receive(msg, self.now), lambda: self.c.receive(msg, self.now))

    @rule(data=st.data(), stopping=st.booleans(), dt=st.integers(0, 1_500))
    def fast_answer(self, data: st.DataObject, stopping: bool, dt: int) -> None:
        """The fast path (``on_answer``: one frame, decoded, judged and an ACK decided in C)
        against the Python core given the same message and then the service's decision, ``dt``
        after the last event (an answer moves deadlines). A frame the fast path leaves to the
        caller goes the usual way, as the service sends it."""
        self.now += dt
        node = data.draw(st.sampled_from([*NODES, 4]))
        s = self.py.session(node) if node in NODES else None
        tx, credited = (0, 0) if s is None else (s.tx, s.returns_credited)
        msg = client_answer(data, node, tx, credited, telemetry=True)
        ident, payload = CODEC.encode(msg)
        status, _, _, decoded, _ = self.c.on_answer(ident, payload, True, False, self.now, stopping)
        if status != DECODE_OK and not isinstance(decoded or msg, Telemetry):
            self.c.receive(decoded or msg, self.now)
        if isinstance(msg, Telemetry):
            return  # the service's: no rule of either core takes it
        for action in self.py.receive(msg, self.now):
            if isinstance(action, Acknowledged):
                (self.py.abort if stopping else self.py.commit)(action.node, self.now)

    @rule(nonce=st.integers(0, 0xFFFF))
    def start(self, nonce: int) -> None:
        """A start with a fresh nonce (witnessed: every session SYNCs, no grant until the books
        are in)."""
        self.py.power_loss(self.now, nonce=nonce)
        self.c.power_loss(self.now, nonce=nonce)

    @rule()
    def waiting(self) -> None:
        """Both cores wait for the same nodes."""
        assert self.c.unconfirmed() == self.py.unconfirmed()

    @rule(dt=st.integers(0, 3_000))
    def timer(self, dt: int) -> None:
        self.now += dt
        self._same(lambda: self.py.handle_timer(self.now), lambda: self.c.handle_timer(self.now))

    @rule()
    def restart(self) -> None:
        """A reset from the saved state, as ``canergy supervisor`` restarts from its file."""
        self.py.power_loss(self.now)
        self.c = compiled_core(
            NODES, 1, timing=self.timing, state=self.c.state, variant=self.variant, build=self.build
        )
        self.c.power_loss(self.now)

    @rule(amount=st.integers(0, 5_000_000))
    def inject(self, amount: int) -> None:
        self._same(lambda: self.py.inject(amount), lambda: self.c.inject(amount))

    @invariant()
    def same_state(self) -> None:
        assert self.c.state == self.py.state
        assert self.c.get_timer() == self.py.get_timer()
        assert self.c.is_quiescent() == self.py.is_quiescent()


def test_the_fast_path_moves_deadlines_as_the_python_core_does() -> None:
    """The compiled core keeps its deadline between calls; an answer on the fast path moves it
    (the ACK's COMMIT starts a wait, COMMITTED ends one), as the Python core's does."""
    py, c = Supervisor(NODES, 10_000_000, timing=T), compiled_core(NODES, 10_000_000, timing=T)
    for node, now in ((3, 0), (5, 200)):
        py.begin(node, 5 * QUANTUM_UJ, now)
        c.begin(node, 5 * QUANTUM_UJ, now)
    deadlines = [c.get_timer()]
    for now, msg in ((300, Ack(3, 1)), (400, Committed(3, 1)), (500, Ack(5, 1))):
        ident, payload = CODEC.encode(msg)
        assert c.on_answer(ident, payload, True, False, now, False)[0] == DECODE_OK  # taken
        for action in py.receive(msg, now):
            if isinstance(action, Acknowledged):
                py.commit(action.node, now)
        deadlines.append(c.get_timer())
        assert deadlines[-1] == py.get_timer() and c.state == py.state
    assert deadlines == [1_000, 1_200, 1_200, 1_500]


MACHINE = settings(
    max_examples=int(os.environ.get("CANERGY_SIDE_BY_SIDE_EXAMPLES", "200")),
    stateful_step_count=60,
    deadline=None,
)
"""200 examples; fewer under ASan (tests/test_c_asan.py's child)."""
TestSideBySide = SideBySide.TestCase
TestSideBySide.settings = MACHINE


class WitnessedSideBySide(SideBySide):
    """The same under the witnessed rules (``--core c --rules witnessed``'s supervisor), with a
    window small enough that grants reach its end."""

    variant = "witnessed"
    timing = replace(T, window=3)


TestWitnessedSideBySide = WitnessedSideBySide.TestCase
TestWitnessedSideBySide.settings = MACHINE


def test_refuses_what_the_c_core_cannot_hold() -> None:
    with pytest.raises(ValueError, match="node ids"):
        compiled_core([1, 1 << 8 | 1], 0)
    with pytest.raises(ValueError, match="response timeout"):
        compiled_core([1], 0, timing=Timing(response_timeout_us=2**32))
    with pytest.raises(LocalProtocolError, match="not managed"):
        compiled_core([1], 0).begin(2, 1_000, 0)
    with pytest.raises(ValueError, match="it holds 16"):
        compiled_core(range(1, 18), 0)


def test_a_build_from_other_headers_is_refused_by_name() -> None:
    """A module whose headers lack a value the core reads (here CANERGY_RX_NOT_CAN) is refused
    with the rebuild to do, before any call into it."""
    built = library().module

    class OtherLib:
        def __getattr__(self, name: str) -> Any:
            if name == "CANERGY_RX_NOT_CAN":
                raise AttributeError(name)
            return getattr(built.lib, name)

    other = SimpleNamespace(__name__="other", ffi=built.ffi, lib=OtherLib())
    with pytest.raises(CoreMissing, match=r"other does not match .*RX_NOT_CAN.*rebuild"):
        CompiledSupervisor([1], 0, module=other)


def test_a_refused_grant_names_its_reason() -> None:
    """The C core's refusals read through the binding's status codes, in the Python core's
    words where it has them."""
    c = compiled_core([1], 10_000)
    with pytest.raises(LocalProtocolError, match="exceeds usable 10000"):
        c.begin(1, 11_000, 0)
    with pytest.raises(LocalProtocolError, match="not a whole mJ"):
        c.begin(1, 1_500, 0)
    c.begin(1, 1_000, 0)
    with pytest.raises(LocalProtocolError, match=r"cannot begin node 1 in WAIT_ACK \(phase\)"):
        c.begin(1, 1_000, 0)


def _run_script(
    core: str, id_base: int | None = None
) -> tuple[list[tuple[int, bytes]], dict[str, Any], int]:
    """The same frames to a service on each core through the bus loop: a grant, a forged ACK
    naming a transaction never begun, damaged bytes, the real ACK twice, COMMITTED, the node's
    level, a RETURN and the level after it."""
    codec = Codec() if id_base is None else Codec(id_base)
    wire = Wire()
    now = [0]
    service = build_service(
        make_supervisor(core, [3], 10_000_000, timing=T, id_base=id_base), ServiceConfig(), 0
    )
    path = service.frame_path()
    loop = BusRuntime(
        wire,
        service,
        codec=codec,
        receives=Direction.TO_SUPERVISOR,
        frame_path=path,
        clock=lambda: now[0],
    )
    service.on_message(Telemetry(3, 0), 0)  # heard: a one-shot grant may begin
    service.request_grant(3, 2_000_000, lambda reply: None)
    loop.poll(0)

    def frame(msg: Any, damage: bool = False) -> can.Message:
        arbitration_id, data = codec.encode(msg)
        data = bytes([data[0] ^ 0x5A, *data[1:]]) if damage else data
        return can.Message(arbitration_id=arbitration_id, is_extended_id=True, data=data)

    for msg, damage in (
        (Ack(3, 9), False),
        (Ack(3, 1), True),
        (Ack(3, 1), False),
        (Ack(3, 1), False),
        (Committed(3, 1), False),
        (Telemetry(3, 2_000), False),
        (Return(3, 1, 500), False),
        (Telemetry(3, 1_500, return_seq=1), False),
    ):
        now[0] += 100
        wire.inbox.append(frame(msg, damage))
        loop.poll(0)
    wire.shutdown()
    status = service.status()
    return wire.sent, status, status["frame_path_frames"]


@pytest.mark.parametrize("id_base", [None, 0x0CF00000])
@release
def test_the_fast_path_answers_as_the_python_core_does(id_base: int | None) -> None:
    """The compiled core's fast path sends the same frames and keeps the same books as the
    Python core's frame path, in the bus's identifier block; the forged ACK is still an
    intrusion and the damaged frame a decode error (both left to the usual path), and each
    core's path took the genuine answers (C's also decoded the TELEMETRY and RETURN, then
    handled as usual)."""
    py_sent, py_status, py_taken = _run_script("python", id_base)
    c_sent, c_status, c_taken = _run_script("c", id_base)
    assert c_sent == py_sent and len(c_sent) >= 2  # INTENTION, COMMIT
    for key in ("usable_uj", "delivered_uj", "intrusions"):
        assert c_status[key] == py_status[key], key
    node, py_node = c_status["nodes"]["3"], py_status["nodes"]["3"]
    assert c_status["intrusions"] == 1 and node["decode_errors"] == py_node["decode_errors"] == 1
    assert node == py_node and node["committed"] == 1 and node["returns_credited"] == 1
    assert node["level_uj"] == 1_500_000  # the TELEMETRY after the RETURN, decoded in C
    assert len(c_sent) == 3  # INTENTION, COMMIT, RETURN_ACK
    # both ACKs and COMMITTED on either core's frame path; both TELEMETRY and the RETURN
    # decoded in C's too (Python's leaves them to the bus loop, which decodes them as ever)
    assert (py_taken, c_taken) == (3, 6)
    assert (py_status["frame_path"], c_status["frame_path"]) == ("python", "c")


@release
@pytest.mark.parametrize("layout", list(Layout))
def test_with_a_key_every_frame_of_the_c_core_leaves_with_its_mac(layout: Layout) -> None:
    """The fast path sends C's bytes as they are, without a MAC: with a key the bus loop must
    not take it. The INTENTION and the COMMIT that answers an authenticated ACK (whose classic
    data frame alone would decode on the fast path) both verify at the node."""
    key = bytes(range(16))
    codec, fd = Codec(), layout is Layout.FD
    wire = Wire()
    service = build_service(make_supervisor("c", [3], 10_000_000, timing=T), ServiceConfig(), 0)
    auth = FrameAuth(codec, layout, lambda n: key, Direction.TO_SUPERVISOR, service.freshness)
    loop = BusRuntime(
        wire, service, codec=codec, receives=Direction.TO_SUPERVISOR, auth=auth, clock=lambda: 0
    )
    service.on_message(Telemetry(3, 0), 0)
    service.request_grant(3, 2_000_000, lambda reply: None)
    loop.poll(0)
    node = FrameAuth(
        codec, layout, lambda n: key, Direction.TO_CLIENT, lambda m: expected_freshness(m, 0, 0)
    )
    node_sends = FrameAuth(
        codec, layout, lambda n: key, Direction.TO_CLIENT, lambda m: freshness(m, 1, 0)
    )

    def heard(sent: list[tuple[int, bytes]]) -> list[Any]:
        frames = [can.Message(arbitration_id=i, data=d, is_fd=fd) for i, d in sent]
        return [v.message for v in map(node.accept, frames) if v.failure is None and v.message]

    assert heard(wire.sent) == [Intention(3, 1, 2_000, 0)]
    wire.sent.clear()
    wire.inbox += node_sends.frames(Ack(3, 1))
    loop.poll(0)
    node = FrameAuth(
        codec, layout, lambda n: key, Direction.TO_CLIENT, lambda m: expected_freshness(m, 1, 0)
    )
    assert heard(wire.sent) == [Commit(3, 1, 2_000)]
    assert service.core.session(3).phase.name == "WAIT_CONFIRM"
    wire.shutdown()


@pytest.mark.parametrize("arbitration_id", [-1, 1 << 29, (1 << 32) | 0x0CE00903])
def test_an_identifier_no_can_frame_carries_takes_the_usual_path(arbitration_id: int) -> None:
    """Transports that are not CAN (zenoh, UDP) can hand over any integer: the fast path
    leaves it to the usual path (which counts it) instead of failing in the C call."""
    core = compiled_core([3], 10_000_000, timing=T)
    _, data = Codec().encode(Ack(3, 1))
    status, actions, frames, decoded, verdict = core.on_answer(
        arbitration_id, data, True, False, 0, False
    )
    assert status == RX_NOT_CAN and (actions, frames, decoded, verdict) == ([], [], None, 0)
