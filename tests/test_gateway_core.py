"""The gateway core: a client above and a supervisor below, energy crossing only as the rules say;
the chain checker over root → gateway → node, and its counterexample for a broken gateway."""

from __future__ import annotations

from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.check.chain import ChainBounds, Kind, check_chain
from canergy.core import Action, Client, Persist, Send, Supervisor
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import Gateway, link_gap
from canergy.ledger import TreeLedger, ledger
from canergy.messages import (
    Ack,
    Admit,
    Commit,
    Intention,
    Return,
    ReturnAck,
    ToClient,
    ToSupervisor,
)

GW = 20
J = 1_000_000


def _admitted_gateway() -> Gateway:
    gw = Gateway(GW, [1, 2])
    gw.books_lost(7, 0)
    gw.receive_upstream(Admit(GW, 7, 0, 0), 0)
    return gw


def test_energy_goes_below_only_when_committed_above() -> None:
    gw = _admitted_gateway()
    acts = gw.receive_upstream(Intention(GW, 1, 2000, 0), 0)
    assert Send(Ack(GW, 1)) in acts
    assert gw.down.state.usable == 0  # held, not yet granted: nothing to grant below
    acts = gw.receive_upstream(Commit(GW, 1, 2000), 0)
    assert acts[0] == Persist()  # one write covers both roles, before COMMITTED leaves
    assert gw.down.state.usable == 2 * J and gw.down.state.injected == 2 * J
    assert gw.up.state.usable == 0 and gw.up.state.spent == 2 * J
    assert link_gap(gw.up.state, gw.down.state) == 0


def test_give_back_withdraws_below_and_returns_above() -> None:
    gw = _admitted_gateway()
    gw.receive_upstream(Intention(GW, 1, 3000, 0), 0)
    gw.receive_upstream(Commit(GW, 1, 3000), 0)
    acts = gw.give_back(1000_000, 0)
    assert acts[0] == Persist() and Send(Return(GW, 1, 1000)) in acts
    assert gw.down.state.usable == 2 * J and gw.down.state.withdrawn == J
    assert gw.up.state.spent == 2 * J and gw.up.state.return_pending == J
    with pytest.raises(LocalProtocolError):  # one numbered return at a time
        gw.give_back(1000, 0)
    gw.receive_upstream(ReturnAck(GW, 1), 0)
    with pytest.raises(LocalProtocolError):  # never more than the budget below holds
        gw.give_back(3 * J, 0)
    assert gw.down.state.usable == 2 * J and link_gap(gw.up.state, gw.down.state) == 0


def test_a_write_off_paid_back_above_is_forwarded_below() -> None:
    """The root wrote off transaction 1 (the COMMITTED was lost); its next intention carries the
    delivered count, the gateway is paid back, and the pay-back goes below at once."""
    gw = _admitted_gateway()
    gw.receive_upstream(Intention(GW, 1, 2000, 0), 0)
    timer = gw.get_timer()
    assert timer is not None
    gw.handle_upstream_timer(timer)  # committed by timeout: 2 J below
    acts = gw.receive_upstream(Intention(GW, 2, 1000, 5000), timer)  # Gs says 5 J delivered
    assert acts[0] == Persist()
    assert gw.down.state.usable == 5 * J and gw.up.state.credited == 5 * J
    assert link_gap(gw.up.state, gw.down.state) == 0


def test_a_timeout_commit_is_forwarded_too() -> None:
    gw = _admitted_gateway()
    gw.receive_upstream(Intention(GW, 1, 1000, 0), 0)
    timer = gw.get_timer()
    assert timer is not None
    gw.handle_upstream_timer(timer)
    assert gw.down.state.usable == J and gw.up.state.usable == 0


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from(["grant", "below", "back", "node", "power"]), st.integers(1, 9)),
        max_size=30,
    )
)
def test_random_runs_keep_every_level_passive(ops: list[tuple[str, int]]) -> None:
    """Root, gateway and two nodes exchanging frames directly (no loss): the tree's ledger
    never shows energy created, and the gateway's roles stay linked."""
    root = Supervisor([GW], 50 * J)
    gw = _admitted_gateway()
    nodes = {n: Client(n) for n in (1, 2)}

    def pump(actions: Sequence[Action], above: bool) -> None:
        """Deliver every frame the actions send, and what the answers send, in order."""
        queue = [(a, above) for a in actions]
        while queue:
            action, up = queue.pop(0)
            if not isinstance(action, Send):
                continue
            msg = action.message
            if isinstance(msg, ToClient):
                target = gw.receive_upstream if up else nodes[msg.node].receive
                queue += [(a, up) for a in target(msg, 0)]
            elif isinstance(msg, ToSupervisor):
                queue += [(a, up) for a in (root if up else gw.down).receive(msg, 0)]

    for op, k in ops:
        if op == "grant" and root.is_quiescent() and root.state.usable >= k * 1000:
            acts = root.begin(GW, k * 1000, 0)
            pump(acts, True)
        elif op == "below" and gw.down.is_quiescent() and gw.down.state.usable >= k * 1000:
            node = 1 + k % 2
            acts = gw.down.begin(node, k * 1000, 0)
            pump(acts, False)
        elif op == "back" and gw.can_give_back() and gw.down.state.usable >= k * 1000:
            pump(gw.give_back(k * 1000, 0), True)
        elif op == "node":
            c = nodes[1 + k % 2]
            if c.state.usable >= 1000 and c.can_give_back():
                pump(c.give_back(1000, 0), False)
        elif op == "power":
            gw.power_loss(0)
        for deadline in (root.get_timer(), gw.get_timer()):
            if deadline is not None:
                pump(root.handle_timer(deadline), True)
                pump(gw.handle_upstream_timer(deadline), True)
                pump(gw.down.handle_timer(deadline), False)
        # acknowledged intentions are committed by both supervisors
        for s in root.state.sessions:
            if s.phase.name == "ACKED":
                pump(root.commit(s.node, 0), True)
        for s in gw.down.state.sessions:
            if s.phase.name == "ACKED":
                pump(gw.down.commit(s.node, 0), False)
        tree = TreeLedger(
            {
                "root": ledger(root.state, [gw.up.state]),
                "gateway": ledger(gw.down.state, [c.state for c in nodes.values()]),
            },
            {"gateway": link_gap(gw.up.state, gw.down.state)},
        )
        assert tree.passive, tree.as_json()
        assert link_gap(gw.up.state, gw.down.state) == 0


def test_chain_checker_finds_no_energy_created_within_its_bound() -> None:
    result = check_chain(bounds=ChainBounds(transactions=1, duplicates=0))
    assert result.complete and result.violations == 0
    assert result.states > 10_000  # it explored: loss and power loss on both legs


def test_chain_checker_catches_a_gateway_that_grants_before_the_upstream_commit() -> None:
    result = check_chain(
        bounds=ChainBounds(transactions=1), broken="early-grant", stop_at_first=True
    )
    assert result.violations > 0 and result.counterexample is not None
    steps = [step for step, _ in result.counterexample]
    assert steps[0].kind is Kind.ROOT_BEGIN
    last = result.counterexample[-1][1].ledger()
    assert not last.passive and last.link_gaps["gateway"] > 0
    # the same steps with the real rule: nothing
    honest = check_chain(bounds=ChainBounds(transactions=1, duplicates=0, power_losses=0))
    assert honest.complete and honest.violations == 0


def test_chain_checker_catches_roles_saved_in_two_files() -> None:
    """Two files written one after the other: a power loss between the writes restarts the
    upstream role from before a commit that was already forwarded below."""
    result = check_chain(
        bounds=ChainBounds(transactions=1), broken="split-save", stop_at_first=True
    )
    assert result.counterexample is not None
    kinds = [step.kind for step, _ in result.counterexample]
    assert kinds[-1] is Kind.GATEWAY_TORN_WRITE
    assert not result.counterexample[-1][1].ledger().passive


OLD_COPY = ChainBounds(transactions=1, duplicates=0, losses=0, power_losses=0, old_copies=1)
"""One transaction per supervisor and the gateway's record put back once to its copy before its
last write, at any step."""


def test_chain_checker_finds_a_restored_gateway_record_creating_energy_under_hardened() -> None:
    result = check_chain("hardened", OLD_COPY, stop_at_first=True)
    assert result.counterexample is not None
    kinds = [step.kind for step, _ in result.counterexample]
    assert Kind.GATEWAY_OLD_COPY in kinds and result.counterexample[-1][1].ledger().dissipated < 0


def test_chain_checker_finds_none_under_witnessed_in_its_first_states() -> None:
    """Not complete (the witnessed chain with a restore does not finish in minutes here): the
    first 40,000 states, breadth first. They held the hole this check found: Us below returned
    upstream while a start below waited for the nodes' books (``Gateway.can_give_back``)."""
    result = check_chain("witnessed", OLD_COPY, max_states=40_000)
    assert result.states >= 40_000 and result.violations == 0
    assert result.depth >= 12  # deep enough to restore after a give-back and start again
