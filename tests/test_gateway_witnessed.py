"""The gateway's upstream role under the witnessed rules (``Gateway(up_variant="witnessed")``):
forwarding is a draw the supervisor above acknowledges before anything goes below, every start is
a RESUME it confirms before anything is granted below, and a record restored from an older copy
creates nothing (the hardened upstream rules create what the gateway returned after the copy)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.core import Action, Client, ClientState, Persist, Send, Supervisor
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import Gateway, GatewayState, link_gap
from canergy.core.witnessed import CLIENT
from canergy.ledger import TreeLedger, ledger
from canergy.live.gateway.state import load_gateway, save_gateway
from canergy.live.supervisor.state_file import StateFileError
from canergy.messages import Debit, ReturnAck, ToClient, ToSupervisor

GW = 20
J = 1_000_000
INITIAL = 50 * J


class Pair:
    """A root supervisor and a gateway under ``variant`` above, frames delivered at once."""

    def __init__(self, variant: str) -> None:
        self.variant = variant
        self.root = Supervisor([GW], 10 * J, variant=variant)
        self.gw = self.gateway()
        self.pump(self.gw.books_lost(7, 0))

    def gateway(self, state: object = None) -> Gateway:
        return Gateway(GW, [1], up_variant=self.variant, state=state)  # type: ignore[arg-type]

    def pump(self, actions: Sequence[Action]) -> None:
        queue = [a.message for a in actions if isinstance(a, Send)]
        while queue:
            msg = queue.pop(0)
            if isinstance(msg, ToClient):
                answers = self.gw.receive_upstream(msg, 0)
            else:
                answers = self.root.receive(msg, 0)  # type: ignore[arg-type]
            queue += [a.message for a in answers if isinstance(a, Send)]

    def grant(self, uj: int) -> None:
        self.pump(self.root.begin(GW, uj, 0))
        self.pump(self.root.commit(GW, 0))

    def tree(self) -> TreeLedger:
        return TreeLedger(
            {
                "root": ledger(self.root.state, [self.gw.up.state]),
                "gateway": ledger(self.gw.down.state, [ClientState(1)]),
            },
            {"gateway": link_gap(self.gw.up.state, self.gw.down.state)},
        )


def test_forwarding_is_a_draw_acknowledged_above_before_anything_goes_below() -> None:
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, 2 * J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    acts = p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    draws = [a.message for a in acts if isinstance(a, Send) and isinstance(a.message, Debit)]
    assert acts[0] == Persist() and len(draws) == 1 and draws[0].amount_mj == 2000
    up = p.gw.up.state
    assert up.pending_draw and up.return_pending == 2 * J and up.usable == 0
    assert p.gw.down.state.usable == 0  # nothing below before the acknowledgement
    assert link_gap(up, p.gw.down.state) == 0
    acts = p.gw.receive_upstream(ReturnAck(GW, draws[0].seq), 0)
    assert acts[0] == Persist()
    assert p.gw.down.state.usable == 2 * J == p.gw.down.state.injected == p.gw.up.state.spent
    assert link_gap(p.gw.up.state, p.gw.down.state) == 0


@pytest.mark.parametrize("variant", ["hardened", "witnessed"])
def test_an_older_copy_of_the_gateway_creates_energy_only_under_hardened(variant: str) -> None:
    """3 J forwarded, the record copied, 2 J returned upstream, the copy started again."""
    p = Pair(variant)
    p.grant(3 * J)
    copy = p.gw.state
    p.pump(p.gw.give_back(2 * J, 0))
    assert p.root.session(GW).returned == 2 * J
    p.gw = p.gateway(copy)
    resumed = p.gw.power_loss(0, 0x1234, 0x77)
    if variant == "hardened":
        assert p.gw.upstream_waiting() is None and p.gw.down.state.usable == 3 * J
        assert not p.tree().passive  # 2 J created: below again, and credited above
        return
    assert p.gw.upstream_waiting() is not None
    with pytest.raises(LocalProtocolError, match="no grant below until the supervisor above"):
        p.gw.down.begin(1, J, 0)
    with pytest.raises(LocalProtocolError):  # nor a return upstream
        p.gw.give_back(J, 0)
    p.pump(resumed)  # RESUME: the root holds a later debit: behind
    assert p.gw.upstream_waiting() is None and p.gw.behind == 1 and p.gw.dropped == 3 * J
    assert p.gw.down.state.usable == 0 and p.gw.up.state.usable == 0
    assert p.tree().passive, p.tree().as_json()


def test_a_confirmed_start_keeps_the_books_and_forwards_what_was_waiting() -> None:
    """A restart from the current record: confirmed, nothing dropped; a credit that was waiting
    for its draw is drawn once confirmed."""
    p = Pair("witnessed")
    p.grant(J)
    p.gw = p.gateway(p.gw.state)
    p.pump(p.gw.power_loss(0, 0x4321))
    assert p.gw.behind == 0 and p.gw.down.state.usable == J and p.gw.upstream_waiting() is None
    p.pump(p.gw.down.begin(1, J // 2, 0))  # grants below go on
    assert p.gw.down.state.usable == J // 2 and p.tree().passive


def test_a_restored_copy_with_its_draw_pending_is_confirmed_and_the_draw_dropped() -> None:
    """Copied between the DRAW's write and its acknowledgement: the root holds that debit, so the
    copy is current; the draw, released once already, is dropped unreleased."""
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    acts = p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    copy = p.gw.state
    assert copy.up.pending_draw
    p.pump(acts)  # the draw goes above, is acknowledged, and J goes below
    assert p.gw.down.state.usable == J
    p.gw = p.gateway(copy)
    p.pump(p.gw.power_loss(0, 0x999))
    assert p.gw.behind == 0 and p.gw.up.state.return_pending == 0
    assert p.gw.down.state.usable == 0 and p.tree().passive


def test_the_state_file_keeps_a_pending_draw_and_the_upstream_rules(tmp_path: Path) -> None:
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    path = tmp_path / "gw.json"
    save_gateway(path, p.gw.state, "hardened", fsync=False, up_variant="witnessed")
    loaded = load_gateway(path, "hardened", GW, (1,), up_variant="witnessed")
    assert loaded.up.pending_draw and CLIENT.persistent(loaded.up) == CLIENT.persistent(
        p.gw.up.state
    )
    with pytest.raises(StateFileError, match="upstream variant 'witnessed', not 'hardened'"):
        load_gateway(path, "hardened", GW, (1,))
    text = path.read_text().replace('"pending_draw":1', '"pending_draw":2')
    path.write_text(text)
    with pytest.raises(StateFileError, match="pending_draw"):
        load_gateway(path, "hardened", GW, (1,), up_variant="witnessed", accept_edited=True)


def test_both_legs_witnessed_a_start_waits_above_and_below() -> None:
    """``variant="witnessed"`` below too: a start sends RESUME above and SYNC below; nothing is
    granted below until both are answered (the reason names the wait above first)."""
    p = Pair("witnessed")
    p.grant(J)
    gw = Gateway(GW, [1], variant="witnessed", up_variant="witnessed", state=p.gw.state)
    p.gw = gw
    resumed = gw.power_loss(0, 0x55, 0x66)
    assert gw.down.unconfirmed() == (1,) and gw.upstream_waiting() is not None
    with pytest.raises(LocalProtocolError, match="supervisor above"):
        gw.down.begin(1, J // 2, 0)
    p.pump(resumed)  # confirmed above; below still waits for node 1's books
    assert gw.upstream_waiting() is None and gw.behind == 0 and gw.down.state.usable == J
    with pytest.raises(LocalProtocolError, match="waiting for node"):
        gw.down.begin(1, J // 2, 0)
    # nor returned above: Us may be an older copy's, holding what node 1 was granted since
    # (found by canergy check --topology chain --variant witnessed --gateway-old-copies 1)
    assert not gw.can_give_back()
    with pytest.raises(LocalProtocolError, match=r"no return upstream .* node.s. 1"):
        gw.give_back(J // 2, 0)


# -- a whole tree, the gateway's record restored at any step ---------------------------------


def total(root: Supervisor, gw: Gateway, nodes: dict[int, Client]) -> int:
    """The energy anywhere in the tree (a debit counts where it is not yet credited)."""
    s = root.session(GW)
    up, down = gw.up.state, gw.down.state
    pend_up = up.return_pending if (up.pending_draw or s.returns_credited < up.return_seq) else 0
    t = root.state.usable + sum(x.reserved for x in root.state.sessions)
    us = 0 if gw.down.unconfirmed() else max(down.usable, 0)  # counted once its books are in
    t += up.usable + pend_up + us + sum(x.reserved for x in down.sessions)
    for c in nodes.values():
        st_ = c.state
        ds = gw.down.session(c.node)
        pend = (
            st_.return_pending if (st_.pending_draw or ds.returns_credited < st_.return_seq) else 0
        )
        t += st_.usable + pend + st_.spent
    return t


OPS = st.lists(
    st.tuples(
        st.sampled_from(
            ["grant", "below", "back", "spend", "nodeback", "copy", "restore", "timers"]
        ),
        st.integers(1, 9),
    ),
    max_size=40,
)


def tree_run(ops: list[tuple[str, int]], above: str) -> None:
    """Root, gateway (witnessed below, ``above`` upstream) and two witnessed nodes, frames
    delivered at once, the gateway's record put back to any earlier copy: the energy anywhere
    (the root, the gateway, the nodes and what their actuators used; Us below only once its
    nodes' books are in) never exceeds the root's initial budget."""
    root = Supervisor([GW], INITIAL, variant=above)
    gws = [Gateway(GW, [1, 2], variant="witnessed", up_variant=above)]
    nodes = {n: Client(n, variant="witnessed") for n in (1, 2)}
    nonce = [100]
    now = [0]

    def fresh() -> int:
        nonce[0] += 1
        return nonce[0]

    def pump(actions: Sequence[Action], above: bool) -> None:
        gw = gws[0]
        queue = [(a, above) for a in actions]
        n = 0
        while queue and n < 200:
            n += 1
            action, up = queue.pop(0)
            if not isinstance(action, Send):
                continue
            msg = action.message
            if isinstance(msg, ToClient):
                target = gw.receive_upstream if up else nodes[msg.node].receive
                queue += [(a, up) for a in target(msg, now[0])]
            elif isinstance(msg, ToSupervisor):
                queue += [(a, up) for a in (root if up else gw.down).receive(msg, now[0])]

    # join the gateway and the nodes
    pump(gws[0].books_lost(7, 0), True)
    for c in nodes.values():
        pump(c.books_lost(fresh(), 0), False)
    copies: list[GatewayState] = []
    for op, k in ops:
        gw = gws[0]
        try:
            if op == "grant" and root.is_quiescent():
                pump(root.begin(GW, k * 100_000, now[0]), True)
            elif op == "below" and gw.down.is_quiescent() and gw.down.state.usable >= k * 1000:
                pump(gw.down.begin(1 + k % 2, k * 1000, now[0]), False)
            elif op == "back" and gw.can_give_back() and gw.down.state.usable >= k * 1000:
                pump(gw.give_back(k * 1000, now[0]), True)
            elif op == "spend":
                c = nodes[1 + k % 2]
                if c.can_spend() and c.state.usable >= 1000:
                    pump(c.spend(1000, now[0]), False)
            elif op == "nodeback":
                c = nodes[1 + k % 2]
                if c.can_give_back() and c.state.usable >= 1000:
                    pump(c.give_back(1000, now[0]), False)
            elif op == "copy":
                copies.append(gw.state)
            elif op == "restore" and copies:
                state = copies[k % len(copies)]
                gws[0] = Gateway(GW, [1, 2], variant="witnessed", up_variant=above, state=state)
                acts = gws[0].power_loss(now[0], fresh(), fresh())
                pump(acts, True)
                # the SYNC below goes out at its timer
            elif op == "timers":
                now[0] += 500_000
                pump(root.handle_timer(now[0]), True)
                pump(gw.handle_upstream_timer(now[0]), True)
                pump(gw.down.handle_timer(now[0]), False)
                for c in nodes.values():
                    pump(c.handle_timer(now[0]), False)
        except LocalProtocolError:
            pass
        gw = gws[0]
        for s in root.state.sessions:
            if s.phase.name == "ACKED":
                pump(root.commit(s.node, now[0]), True)
        for s in gw.down.state.sessions:
            if s.phase.name == "ACKED":
                pump(gw.down.commit(s.node, now[0]), False)
        t = total(root, gw, nodes)
        assert t <= INITIAL, (t - INITIAL, op, k)


@settings(max_examples=300, deadline=None)
@given(OPS)
def test_a_tree_with_the_gateways_record_restored_creates_nothing(
    ops: list[tuple[str, int]],
) -> None:
    tree_run(ops, "witnessed")


RESTORED_AFTER_A_GIVE_BACK = [
    ("grant", 3),
    ("copy", 1),
    ("back", 3),
    ("timers", 1),
    ("restore", 1),
    ("timers", 1),
    ("below", 3),
    ("spend", 3),
]
"""Granted, copied, given back (credited above), the copy started again, granted below, spent."""


def test_the_same_tree_finds_energy_created_with_the_hardened_rules_above() -> None:
    """The teeth of the property above, scripted (a random search needs about 1,000 examples to
    find it and sometimes does not): under the hardened rules above, the restored gateway grants
    below what it already gave back; under the witnessed rules it is found behind first."""
    with pytest.raises(AssertionError):
        tree_run(RESTORED_AFTER_A_GIVE_BACK, "hardened")
    tree_run(RESTORED_AFTER_A_GIVE_BACK, "witnessed")
