"""The C gateway's JOIN hold below (``canergy_joins_route`` and ``canergy_joins_due_join``,
firmware/src/joins.c, as ports/linux/gateway_below.c calls them) side by side with the Python
gateway's (``canergy gateway``: its supervisor service's ``JoinHold``, 500 ms).

With a key (both layouts): two Python emulated nodes behind their own ``FrameAuth`` speak to the
C gateway's supervisor side and the Python gateway's at once, as in
tests/test_c_gateway_down_auth.py, and now their JOINs and TELEMETRY go through each side's JOIN
hold. An earlier life's JOIN replayed with its JOINING TELEMETRY while a grant is in flight is
held on both, refused on both when the node reports its books, and writes nothing off; replayed
while the node stays silent it is admitted on both after the hold, with the same ADMIT.
Without a key (hypothesis): any sequence of JOINs, TELEMETRY with and without books, grants and
waits gives both sides the same frames, books and JOINs refused.
"""

from __future__ import annotations

from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.c_binding import OK, CGateway, SupervisorConfig, cbuf, library, ref, rx
from support.c_session import fields_of, timing_of
from test_c_gateway_down_auth import CODEC, INITIAL, NODES, Below, T, taken

from canergy.auth.frames import Layout, Verdict
from canergy.core import Acknowledged, Send, Supervisor
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.joins import JOIN_HOLD_US, JoinHold
from canergy.messages import QUANTUM_UJ, Join, Message, Telemetry


class JoinsBelow(Below):
    """``Below`` with each side's JOIN hold between the frame check and the rules."""

    def __init__(self, layout: Layout, rules: str = "hardened") -> None:
        super().__init__(layout, rules)
        lib = self.lib
        self.c_joins = lib.new("struct canergy_joins[2]")
        self.c_refuted = lib.new("struct canergy_joins_refuted *")
        self.to_rules = lib.new("struct canergy_msg *")
        self.c_refused = 0
        self.intrusions = Intrusions("gateway")
        self.refusals = Refusals("gateway")
        self.hold = JoinHold(
            NODES, JOIN_HOLD_US, frozenset(), self.intrusions, self.refusals, lambda: True
        )

    def _c_rules(self, msg: Any) -> list[tuple[int, bytes]]:
        out = self.out
        assert self.lib.canergy_supervisor_on_msg(ref(self.gw.down), msg, self.now, out) == OK
        return self._c_sent(out)

    def receive(self, frame: can.Message) -> Verdict:
        verdict = self._judged(frame)
        c_sent: list[tuple[int, bytes]] = []
        py_sent: list[can.Message] = []
        msg = verdict.message
        if msg is not None:
            v = self.verified
            plain, _pbuf = rx(v.id, bytes(v.data[0 : v.dlc]), lib=self.lib)
            to_sup = self.lib.CANERGY_TO_SUPERVISOR
            assert self.lib.canergy_decode(CODEC.id_base, ref(plain), to_sup, self.msg) == OK
            c_sent = self._c_route(NODES.index(msg.node))
            py_sent = self._py_route(msg)
        self._same(c_sent, py_sent)
        self.to_nodes(py_sent)
        return verdict

    def _c_route(self, i: int) -> list[tuple[int, bytes]]:
        lib = self.lib
        found = lib.canergy_joins_route(
            ref(self.c_joins[i]), self.msg, self.now, JOIN_HOLD_US, self.to_rules, self.c_refuted
        )
        self.c_refused += self.c_refuted.count
        if found & (lib.CANERGY_JOINS_PASS | lib.CANERGY_JOINS_ADMIT):
            return self._c_rules(self.to_rules)
        return []

    def _py_route(self, msg: Message) -> list[can.Message]:
        if isinstance(msg, Join):
            self.hold.on_join(msg)
            return []
        if isinstance(msg, Telemetry):
            return self._py_admit(self.hold.on_telemetry(msg, self.now))
        return self._py_sent(self.py.receive(msg, self.now))  # type: ignore[arg-type]

    def _py_admit(self, joins: list[Join]) -> list[can.Message]:
        """The JOINs the held JOINs confirmed, answered by the Python rules."""
        return [m for join in joins for m in self._py_sent(self.py.receive(join, self.now))]

    def advance(self, us: int) -> list[can.Message]:
        """Time goes on: the JOINs whose hold is over, admitted on both; their frames (to the
        nodes too)."""
        self.now += us
        c_sent: list[tuple[int, bytes]] = []
        for i, node in enumerate(NODES):
            if self.lib.canergy_joins_due_join(ref(self.c_joins[i]), node, self.now, self.msg):
                c_sent += self._c_rules(self.msg)
        py_sent = self._py_admit(self.hold.on_wakeup(self.now))
        self._same(c_sent, py_sent)
        self.to_nodes(py_sent)
        return py_sent

    def refused(self) -> int:
        """JOINs refused, the same count on both sides."""
        assert self.c_refused == self.refusals.total == self.intrusions.total
        return self.c_refused


def _admitted_at_start(below: JoinsBelow, node: int, nonce: int, high: int) -> list[can.Message]:
    """The node JOINs (its JOIN and JOINING TELEMETRY, returned as recorded) and is admitted
    once the hold is over, on both sides; then it reports its books."""
    join = below.join(node, nonce, high)
    below.deliver(join)
    telemetry = below.nodes[node].telemetry()
    below.deliver(telemetry)
    assert below.advance(JOIN_HOLD_US - 1) == []  # held: nobody admitted yet
    admit = below.advance(1)
    assert admit and below.nodes[node].client.state.phase.name == "IDLE"
    assert taken(below.deliver(below.nodes[node].telemetry()))
    return join + telemetry


@pytest.mark.parametrize("layout", list(Layout))
def test_an_earlier_lifes_join_replayed_while_the_node_is_on_writes_nothing_off(
    layout: Layout,
) -> None:
    """Issue 40, item 10: node 3's JOIN and JOINING TELEMETRY from its start, replayed while a
    grant is in flight (its INTENTION sent, not yet taken), verify and are held on both sides;
    the node's own TELEMETRY with its books refuses the JOIN on both (a refusal and an
    intrusion each), nothing is written off, and the grant completes. Before, the C gateway
    handed the JOIN to its rules at once: the node re-admitted, the grant written off."""
    below = JoinsBelow(layout)
    old = _admitted_at_start(below, 3, 0x0042, 0x5A5A)
    _admitted_at_start(below, 5, 0x0101, 0x1234)
    below.grant(3, 500)
    below.deliver(below.nodes[3].telemetry())
    in_flight = below.begin(3, 700)  # the INTENTION on its way
    reserved = below.py.session(3).reserved
    assert reserved == 700 * QUANTUM_UJ
    below.deliver(old)  # the replay: JOIN, then its TELEMETRY without books
    assert below.hold.holding(3) and below.c_joins[0].held_count == 1
    assert below.advance(JOIN_HOLD_US // 2) == []  # not admitted within the hold
    assert below.py.session(3).reserved == reserved and below.refused() == 0
    assert taken(below.deliver(below.nodes[3].telemetry()))  # the node: "I have my books"
    assert below.refused() == 1
    assert below.advance(10 * JOIN_HOLD_US) == []  # refused: never admitted
    below.to_nodes(in_flight)  # the grant completes
    s3 = below.py.session(3)
    assert s3.delivered == 1_200 * QUANTUM_UJ and s3.reserved == 0
    assert below.gw.down.usable_uj == INITIAL - 1_200_000 - 0  # nothing written off
    assert below.nodes[3].client.state.usable == 1_200 * QUANTUM_UJ


@pytest.mark.parametrize("layout", list(Layout))
def test_a_replay_while_the_node_stays_silent_is_admitted_alike_after_the_hold(
    layout: Layout,
) -> None:
    """The residual: replayed while the node does not report (off, or its TELEMETRY lost for
    the whole hold), the JOIN is admitted on both sides after 500 ms with the same ADMIT, and
    what was open is written off on both (never created)."""
    below = JoinsBelow(layout)
    old = _admitted_at_start(below, 3, 0x0077, 0x0F0F)
    below.grant(3, 400)
    below.deliver(below.nodes[3].telemetry())
    below.begin(3, 300)  # in flight, never delivered
    below.deliver(old)
    assert below.advance(JOIN_HOLD_US - 1) == []
    admit = below.now + 1
    sent = below.advance(1)
    assert len(sent) == (1 if layout is Layout.FD else 2) and below.now == admit
    assert below.py.session(3).reserved == 0 and below.refused() == 0


# -- without a key: any sequence, side by side -----------------------------------------------
class Keyless:
    """The C gateway's rules below and its JOIN hold next to the Python gateway's (no key):
    messages in, frames out compared byte for byte."""

    def __init__(self) -> None:
        self.lib = lib = library()
        self.now = 0
        self.py = Supervisor(NODES, INITIAL, timing=T)
        self.gw = CGateway(lib=lib)
        cfg = SupervisorConfig(CODEC.id_base, timing_of(T, "hardened", lib=lib), lib=lib)
        nodes = cbuf(bytes(NODES), lib=lib)
        assert lib.canergy_supervisor_init(ref(self.gw.down), ref(cfg), nodes, 2, INITIAL) == OK
        self.joins = lib.new("struct canergy_joins[2]")
        self.refuted = lib.new("struct canergy_joins_refuted *")
        self.msg = lib.new("struct canergy_msg *")
        self.to_rules = lib.new("struct canergy_msg *")
        self.out = lib.new("struct canergy_supervisor_out *")
        self.c_refused = 0
        self.intrusions = Intrusions("gateway")
        self.hold = JoinHold(
            NODES, JOIN_HOLD_US, frozenset(), self.intrusions, Refusals("gateway"), lambda: False
        )

    def _py(self, actions: list[Any]) -> list[tuple[int, bytes]]:
        sent: list[tuple[int, bytes]] = []
        for a in actions:
            if isinstance(a, Acknowledged):
                sent += self._py(self.py.commit(a.node, self.now))
            elif isinstance(a, Send):
                sent.append(CODEC.encode(a.message))
        return sent

    def _c(self, out: Any) -> list[tuple[int, bytes]]:
        sent = [(f.id, bytes(f.data[0 : f.dlc])) for f in out.frames[0 : out.frame_count]]
        for e in out.events[0 : out.event_count]:
            if e.flags & self.lib.CANERGY_SUP_ACKNOWLEDGED:
                decided = self.lib.new("struct canergy_supervisor_out *")
                code = self.lib.canergy_supervisor_decide(
                    ref(self.gw.down), e.node, True, self.now, decided
                )
                assert code == OK
                sent += self._c(decided)
        return sent

    def _c_rules(self, msg: Any) -> list[tuple[int, bytes]]:
        assert self.lib.canergy_supervisor_on_msg(ref(self.gw.down), msg, self.now, self.out) == OK
        return self._c(self.out)

    def same(self, c_sent: list[tuple[int, bytes]], py_sent: list[tuple[int, bytes]]) -> None:
        assert c_sent == py_sent
        for i, node in enumerate(NODES):
            assert fields_of(self.gw.down.sessions[i]) == fields_of(self.py.session(node))
        assert self.gw.down.usable_uj == self.py.usable
        assert self.c_refused == self.intrusions.total

    def message(self, msg: Join | Telemetry) -> None:
        arbitration_id, data = CODEC.encode(msg)
        r, _buf = rx(arbitration_id, data, lib=self.lib)
        to_sup = self.lib.CANERGY_TO_SUPERVISOR
        assert self.lib.canergy_decode(CODEC.id_base, ref(r), to_sup, self.msg) == OK
        i = NODES.index(msg.node)
        found = self.lib.canergy_joins_route(
            ref(self.joins[i]), self.msg, self.now, JOIN_HOLD_US, self.to_rules, self.refuted
        )
        self.c_refused += self.refuted.count
        to_rules = found & (self.lib.CANERGY_JOINS_PASS | self.lib.CANERGY_JOINS_ADMIT)
        c_sent = self._c_rules(self.to_rules) if to_rules else []
        if isinstance(msg, Join):
            self.hold.on_join(msg)
            py_sent: list[tuple[int, bytes]] = []
        else:
            py_sent = self._admit(self.hold.on_telemetry(msg, self.now))
        self.same(c_sent, py_sent)

    def wait(self, us: int) -> None:
        self.now += us
        c_sent: list[tuple[int, bytes]] = []
        for i, node in enumerate(NODES):
            if self.lib.canergy_joins_due_join(ref(self.joins[i]), node, self.now, self.msg):
                c_sent += self._c_rules(self.msg)
        self.same(c_sent, self._admit(self.hold.on_wakeup(self.now)))

    def _admit(self, joins: list[Join]) -> list[tuple[int, bytes]]:
        """The JOINs the held JOINs confirmed, answered by the Python rules."""
        return [f for join in joins for f in self._py(self.py.receive(join, self.now))]

    def begin(self, node: int, amount_mj: int) -> None:
        if self.py.session(node).phase.name != "IDLE":
            return
        code = self.lib.canergy_supervisor_begin(
            ref(self.gw.down), node, amount_mj * QUANTUM_UJ, self.now, self.out
        )
        assert code == OK
        self.same(
            self._c(self.out), self._py(self.py.begin(node, amount_mj * QUANTUM_UJ, self.now))
        )


_node = st.sampled_from(NODES)
_step = st.one_of(
    st.tuples(st.just("join"), _node, st.sampled_from([0x0001, 0x0002, 0x0003, 0xFFFF])),
    st.tuples(st.just("telemetry"), _node, st.sampled_from([0, Telemetry.JOINING])),
    st.tuples(st.just("wait"), _node, st.sampled_from([1_000, JOIN_HOLD_US - 1, JOIN_HOLD_US])),
    st.tuples(st.just("begin"), _node, st.integers(1, 900)),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(_step, max_size=40))
def test_without_a_key_any_sequence_gives_both_holds_the_same_frames_and_books(
    steps: list[tuple[str, int, int]],
) -> None:
    k = Keyless()
    for kind, node, value in steps:
        if kind == "join":
            k.message(Join(node, value))
        elif kind == "telemetry":
            k.message(Telemetry(node, 0, value, 0))
        elif kind == "wait":
            k.wait(value)
        else:
            k.begin(node, value)


def test_a_forged_join_while_the_node_reports_its_books_is_refused_keyless() -> None:
    """Without a key: a JOIN forged during a grant, then the node's TELEMETRY with its books:
    refused on both (an intrusion each), the grant still open, nobody admitted."""
    k = Keyless()
    k.message(Join(3, 9))
    k.message(Telemetry(3, 0, Telemetry.JOINING, 0))
    k.wait(JOIN_HOLD_US)  # admitted
    k.message(Telemetry(3, 0, 0, 0))
    k.begin(3, 250)
    reserved = k.py.session(3).reserved
    k.message(Join(3, 10))  # forged
    k.message(Telemetry(3, 0, Telemetry.JOINING, 0))  # forged too
    k.message(Telemetry(3, 0, 0, 0))  # the node's own, at once
    k.wait(10 * JOIN_HOLD_US)
    assert k.py.session(3).reserved == reserved == 250 * QUANTUM_UJ
    assert k.c_refused == 1 and k.intrusions.total == 1


def test_the_nodes_own_join_resent_before_its_admit_arrived_is_no_intrusion_keyless() -> None:
    """The node's JOIN re-sent while its ADMIT was on the way (the same nonce), then its
    TELEMETRY with books: dropped on both as a re-send (``resent``), not refused; an earlier
    life's JOIN held beside it still is."""
    k = Keyless()
    k.message(Join(3, 9))
    k.message(Telemetry(3, 0, Telemetry.JOINING, 0))
    k.wait(JOIN_HOLD_US)  # admitted
    k.message(Join(3, 4))  # an earlier life's
    k.message(Join(3, 9))  # its own re-send
    k.message(Telemetry(3, 0, 0, 0))
    assert k.hold.resent(3) == k.joins[0].resent == 1
    assert k.c_refused == k.intrusions.total == 1
