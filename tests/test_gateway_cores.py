"""The gateway's downstream role on either core (``Gateway(below=...)``, ``canergy gateway
--core``): the same tree run twice, side by side, once with the Python supervisor role
(``core.gateway.Below``) and once with the compiled one (``ccore.supervisor.CompiledBelow``).

A root supervisor grants to the gateway, the gateway tops up its two nodes, they spend and
return, the gateway returns upward; frames are delivered at once or one of a step is lost; the
gateway restarts from its state file, each tree from the file the other wrote. After every step
both trees hold the same books (both roles, the root, the nodes), sent the same frames byte for
byte in the same order with the same writes, refused alike, and their state files are the same
text; the link between the gateway's roles stays closed.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.c_binding import library
from support.ccore_built import release

from canergy.ccore.supervisor import CompiledBelow
from canergy.codec import Codec
from canergy.core import Action, Client, Persist, Send, Supervisor
from canergy.core.errors import LocalProtocolError, WindowClosed
from canergy.core.gateway import Below, Gateway, GatewayState, MakeDown, link_gap
from canergy.core.state import ClientState, Session, SupervisorState
from canergy.ledger import TreeLedger, ledger
from canergy.live.gateway.state import gateway_json, load_gateway, save_gateway
from canergy.messages import Admit, Debit, Intention, Join, ToClient, ToSupervisor

pytestmark = release

GW = 20
NODES = (1, 2)
J = 1_000_000
INITIAL = 40 * J
CODEC = Codec()
RULES = [("hardened", "hardened"), ("witnessed", "witnessed"), ("witnessed", "hardened")]
"""(below, above): the gateway's downstream rules and the rules of the bus above."""


def c_below() -> MakeDown:
    """The compiled role on the tests' build of the library (``support.c_binding.library``:
    UBSan in-process, ASan+UBSan in tests/test_c_asan.py's child)."""
    return partial(CompiledBelow, module=library().module)


class Tree:
    """Root, gateway (its supervisor role made by ``below``) and two nodes, frames delivered
    at once; ``log`` records what each step did, for the other tree's to be compared with."""

    def __init__(self, below: MakeDown | None, down: str, up: str) -> None:
        self.below, self.down, self.up = below, down, up
        self.root = Supervisor([GW], INITIAL, variant=up)
        self.gw = Gateway(GW, NODES, variant=down, up_variant=up, below=below)
        self.nodes = {n: Client(n, variant=down) for n in NODES}
        self.now = 0
        self.nonce = 100
        self.log: list[Any] = []
        self.lose = -1
        """The frame of the next exchange to lose (counted from 0; -1: none)."""

    def fresh(self) -> int:
        self.nonce += 1
        return self.nonce

    def pump(self, actions: Sequence[Action], above: bool) -> None:
        """Carry out ``actions`` (the gateway's, the root's or a node's) and every answer."""
        queue = [(a, above) for a in actions]
        sent = 0
        while queue and sent < 400:
            action, up = queue.pop(0)
            if not isinstance(action, Send):
                self.log.append(action)  # Persist, Resolved, Acknowledged...: in their order
                continue
            msg = action.message
            self.log.append(("frame", up, *CODEC.encode(msg)))
            sent += 1
            if sent - 1 == self.lose:
                self.log.append("lost")
                continue
            if isinstance(msg, ToClient):
                target = self.gw.receive_upstream if up else self.nodes[msg.node].receive
                queue += [(a, up) for a in target(msg, self.now)]
            elif isinstance(msg, ToSupervisor):
                sup = self.root if up else self.gw.down
                queue += [(a, up) for a in sup.receive(msg, self.now)]
        self.lose = -1

    def step(self, op: str, k: int) -> None:
        """One step of the scenario; a refusal is logged, not raised."""
        gw = self.gw
        try:
            if op == "grant" and self.root.is_quiescent():
                self.pump(self.root.begin(GW, k * 500_000, self.now), True)
            elif op == "below" and gw.down.session(1 + k % 2).phase.name == "IDLE":
                self.pump(gw.down.begin(1 + k % 2, k * 100_000, self.now), False)
            elif op == "back" and gw.can_give_back():
                self.pump(gw.give_back(k * 100_000, self.now), True)
            elif op == "spend":
                c = self.nodes[1 + k % 2]
                if c.can_spend() and c.state.usable >= 100_000:
                    self.pump(c.spend(100_000, self.now), False)
            elif op == "nodeback":
                c = self.nodes[1 + k % 2]
                if c.can_give_back() and c.state.usable >= 100_000:
                    self.pump(c.give_back(100_000, self.now), False)
            elif op == "lose":
                self.lose = k % 3
            elif op == "timers":
                self.timers(k * 100_000)
        except LocalProtocolError as exc:
            self.log.append(("refused", str(exc)))
        for s in self.root.state.sessions:  # decide what was acknowledged
            if s.phase.name == "ACKED":
                self.pump(self.root.commit(s.node, self.now), True)
        for s in self.gw.down.state.sessions:
            if s.phase.name == "ACKED":
                self.pump(self.gw.down.commit(s.node, self.now), False)

    def timers(self, us: int) -> None:
        self.now += us
        self.pump(self.root.handle_timer(self.now), True)
        self.pump(self.gw.handle_upstream_timer(self.now), True)
        self.pump(self.gw.down.handle_timer(self.now), False)
        for c in self.nodes.values():
            self.pump(c.handle_timer(self.now), False)

    def save(self, path: Path) -> None:
        save_gateway(path, self.gw.state, self.down, fsync=False, up_variant=self.up)

    def restart(self, path: Path) -> None:
        """Power lost: the gateway starts again from ``path`` on its own core."""
        state = load_gateway(path, self.down, GW, NODES, up_variant=self.up)
        self.gw = Gateway(
            GW, NODES, variant=self.down, up_variant=self.up, state=state, below=self.below
        )
        self.pump(self.gw.power_loss(self.now, self.fresh(), self.fresh()), True)

    def books(self) -> tuple[Any, ...]:
        gw = self.gw
        return (
            gw.state,
            gateway_json(gw.state, self.down, self.up),
            gw.upstream_waiting(),
            gw.down.unconfirmed(),
            gw.get_timer(),
            (gw.behind, gw.dropped),
            self.root.state,
            tuple(c.state for c in self.nodes.values()),
        )

    def ledger(self) -> TreeLedger:
        gw = self.gw
        return TreeLedger(
            {
                "root": ledger(self.root.state, [gw.up.state]),
                "gateway": ledger(gw.down.state, [c.state for c in self.nodes.values()]),
            },
            {"gateway": link_gap(gw.up.state, gw.down.state)},
        )


def twins(down: str, up: str) -> tuple[Tree, Tree]:
    """The same tree on the Python core and on the compiled one, both joined."""
    py, c = Tree(None, down, up), Tree(c_below(), down, up)
    assert isinstance(py.gw.down, Below) and isinstance(c.gw.down, CompiledBelow)
    assert (py.gw.down.implementation, c.gw.down.implementation) == ("python", "c")
    for t in (py, c):
        t.pump(t.gw.books_lost(7, 0), True)
        for n in t.nodes.values():
            t.pump(n.books_lost(t.fresh(), 0), False)
    return py, c


def run_side_by_side(ops: Sequence[tuple[str, int]], down: str, up: str) -> tuple[Tree, Tree]:
    py, c = twins(down, up)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for i, (op, k) in enumerate(ops):
            if op == "restart":  # each restarts from the file the other core wrote
                py.save(folder / "py.json")
                c.save(folder / "c.json")
                text = (folder / "py.json").read_text()
                assert text == (folder / "c.json").read_text(), (i, op)
                (folder / "c.json").replace(folder / "for-py.json")
                (folder / "py.json").replace(folder / "for-c.json")
                py.restart(folder / "for-py.json")
                c.restart(folder / "for-c.json")
            else:
                py.step(op, k)
                c.step(op, k)
            assert py.log == c.log, (i, op, k)
            assert py.books() == c.books(), (i, op, k)
            assert link_gap(c.gw.up.state, c.gw.down.state) == 0
    return py, c


SCENARIO = [
    ("grant", 8),  # 4 J from above, forwarded below (drawn first under witnessed rules above)
    ("below", 5),  # top-ups below
    ("below", 4),
    ("spend", 1),
    ("spend", 2),
    ("nodeback", 1),  # a node returns to the gateway
    ("timers", 6),
    ("back", 9),  # a RETURN upward
    ("timers", 6),
    ("restart", 0),  # from the state file, each from the other core's
    ("timers", 6),
    ("lose", 1),
    ("grant", 4),
    ("timers", 9),
    ("below", 3),
    ("back", 5),
    ("timers", 9),
    ("timers", 9),
    ("restart", 0),
    ("timers", 9),
    ("timers", 9),
]


@pytest.mark.parametrize(("down", "up"), RULES)
def test_a_gateway_scenario_is_the_same_on_both_cores(down: str, up: str) -> None:
    """Grant from above, top-ups below, a RETURN upward, restarts from the state file: the same
    books, frames, writes and state file on both cores, and the tree creates nothing."""
    py, c = run_side_by_side(SCENARIO, down, up)
    frames = [e for e in c.log if isinstance(e, tuple) and e[0] == "frame"]
    assert c.log.count(Persist()) >= 8 and len(frames) >= 30
    up_state, below = c.gw.up.state, c.gw.down.state
    assert up_state.return_seq >= 2 and below.withdrawn >= J  # returned upward, twice
    assert below.injected >= 4 * J and sum(s.delivered for s in below.sessions) > 0
    assert c.root.session(GW).returns_credited == up_state.return_seq  # credited above
    for t in (py, c):
        assert t.ledger().passive, t.ledger().as_json()


OPS = st.lists(
    st.tuples(
        st.sampled_from(
            ["grant", "below", "back", "spend", "nodeback", "lose", "timers", "restart"]
        ),
        st.integers(1, 9),
    ),
    max_size=40,
)


@settings(max_examples=int(os.environ.get("CANERGY_SIDE_BY_SIDE_EXAMPLES", "200")), deadline=None)
@given(ops=OPS, rules=st.sampled_from(RULES))
def test_any_gateway_run_is_the_same_on_both_cores(
    ops: list[tuple[str, int]], rules: tuple[str, str]
) -> None:
    run_side_by_side(ops, *rules)


def test_the_compiled_role_holds_grants_while_the_start_waits_above() -> None:
    """Witnessed above, a restart grants nothing below until the supervisor above confirms the
    record, on every path the compiled role begins a grant (the service's too)."""
    _, c = twins("hardened", "witnessed")
    c.step("grant", 4)
    path = Path(tempfile.mkdtemp()) / "gw.json"
    c.save(path)
    state = load_gateway(path, "hardened", GW, NODES, up_variant="witnessed")
    gw = Gateway(GW, NODES, up_variant="witnessed", state=state, below=c_below())
    resume = gw.power_loss(0, 0x55)
    down = gw.down
    assert isinstance(down, CompiledBelow) and gw.upstream_waiting() is not None
    for begin in (down.begin, down.begin_encoded):
        with pytest.raises(LocalProtocolError, match="RESUME sent upstream"):
            begin(1, J, 0)
    assert down.usable == 2 * J and down.session(1).phase.name == "IDLE"
    c.gw = gw
    c.pump(resume, True)
    assert gw.upstream_waiting() is None
    assert any(isinstance(a, Send) for a in down.begin(1, J, 0))


@pytest.mark.parametrize("core", ["python", "c"])
def test_either_role_withdraws_only_what_it_holds(core: str) -> None:
    """``withdraw`` (a return upward) takes energy out of Us counted as withdrawn, and refuses
    what Us does not hold in the same words on both cores, changing nothing."""
    make = c_below() if core == "c" else Below
    sup = make([1, 2], 0, variant="hardened", timing=None, state=None, start_without=())
    sup.inject(2 * J)
    for amount in (3 * J, 0, -1):
        with pytest.raises(LocalProtocolError, match=f"cannot withdraw {amount} µJ of 2000000"):
            sup.withdraw(amount)
    sup.withdraw(J // 2)
    assert (sup.usable, sup.state.injected, sup.state.withdrawn) == (3 * J // 2, 2 * J, J // 2)


@pytest.mark.parametrize("core", ["python", "c"])
def test_a_gateways_node_admitted_into_cs_higher_block_gets_its_next_grant(core: str) -> None:
    """The gateway's supervisor role runs the same session rules: tx 10, W 10, C 70,000, a
    JOIN lifts tx to 10 + 2^16 and leaves W at 10, so the next grant below is refused as beyond
    the window; one re-sync of the node (its books and counts taken under the re-sync's nonce)
    and the next grant begins, on either core."""
    lifted = Session(1, tx=10, witness=10, returns_credited=70_000)
    down = SupervisorState(5 * J, 5 * J, sessions=(lifted,))
    gw = Gateway(
        GW,
        [1],
        variant="witnessed",
        state=GatewayState(ClientState(GW), down),
        below=c_below() if core == "c" else None,
    )
    gw.down.receive(Join(1, 0x33), 0)
    with pytest.raises(WindowClosed):
        gw.down.begin(1, J, 1)
    q = 70_001 & 0xFFFF  # the JOIN voided C + 1: the node's q
    sync = [a.message for a in gw.down.resync(1, 1, 0x0707) if isinstance(a, Send)]
    assert sync == [Admit(1, 0x0707, 10, q)]  # SYNC(n, tx, C): tx 10 + 2^16 on the wire
    ltx = 10 + (1 << 16) + 64  # the node settled B past the ADMIT's k
    gw.down.receive(Debit.books(1, 0x0707, None), 1)
    gw.down.receive(Debit.counts(1, 0x0707, q, ltx & 0xFFFF), 1)
    sent = [a.message for a in gw.down.begin(1, J, 2) if isinstance(a, Send)]
    assert sent == [Intention(1, (ltx + 1) & 0xFFFF, 1000, 0)]
