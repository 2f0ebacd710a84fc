"""The stateful Supervisor/Client wrappers: argument checks, Persist ordering, timers."""

from __future__ import annotations

import pytest
from support.harness import Harness, J

from canergy.core import Client, LocalProtocolError, Persist, Send, Supervisor
from canergy.messages import Ack, Intention


def test_begin_refuses_what_the_protocol_cannot_carry() -> None:
    sup = Supervisor([1, 2], 5 * J)
    for node, amount in [(3, J), (1, 0), (1, 1500), (1, 66 * J), (1, 6 * J)]:
        with pytest.raises(LocalProtocolError):
            sup.begin(node, amount, 0)
    sup.begin(1, J, 0)
    with pytest.raises(LocalProtocolError):
        sup.begin(1, J, 0)  # already open
    with pytest.raises(LocalProtocolError):
        sup.commit(1, 0)  # nothing acknowledged yet
    assert sup.state.usable == 4 * J


def test_constructor_checks() -> None:
    for nodes in ([], [0], [128]):
        with pytest.raises(ValueError):
            Supervisor(nodes, J)
    with pytest.raises(ValueError):
        Supervisor([1], -1)
    with pytest.raises(ValueError):
        Supervisor([1], J, variant="optimistic-typo")
    with pytest.raises(ValueError):
        Client(0)


def test_persist_comes_before_the_reply_that_reports_it() -> None:
    sup, client = Supervisor([1], 2 * J), Client(1)
    first = sup.begin(1, J, 0)
    assert isinstance(first[0], Persist) and isinstance(first[1], Send)
    intention = first[1].message
    assert client.receive(intention, 1) == [Send(Ack(1, 1))]  # hold only: nothing persisted
    sup.receive(Ack(1, 1), 2)
    commit = sup.commit(1, 3)
    reply = client.receive(commit[-1].message, 4)
    assert isinstance(reply[0], Persist) and isinstance(reply[-1], Send)
    resend = sup.fire_timer(1, 10**9)
    assert resend and not any(isinstance(a, Persist) for a in resend)  # a re-send changes nothing


def test_timers_and_quiescence() -> None:
    sup = Supervisor([1, 2], 2 * J)
    assert sup.get_timer() is None and sup.is_quiescent()
    sup.begin(2, J, 100)
    deadline = sup.get_timer()
    assert deadline == 100 + sup.timing.response_timeout_us
    assert sup.handle_timer(deadline - 1) == []
    assert [a for a in sup.handle_timer(deadline) if isinstance(a, Send)] == [
        Send(Intention(2, 1, 1000, 0))
    ]
    assert not sup.is_quiescent()


def test_messages_for_other_nodes_are_ignored() -> None:
    sup, client = Supervisor([1], J), Client(1)
    assert sup.receive(Ack(9, 1), 0) == []
    assert client.receive(Intention(2, 1, 5, 0), 0) == []
    assert client.state.held_tx == 0


def test_spend_and_return_checks() -> None:
    h = Harness("hardened")
    h.begin(2 * J)
    h.settle()
    c = h.client()
    for amount in (0, 3 * J):
        with pytest.raises(LocalProtocolError):
            c.spend(amount)
    with pytest.raises(LocalProtocolError):
        c.give_back(1500, 0)  # not a whole quantum
    h.give_back(J)
    with pytest.raises(LocalProtocolError):
        c.give_back(J // 2, 0)  # one return at a time
    h.settle()
    assert c.can_give_back() and h.sup.state.usable == 9 * J


def test_inject_counts_as_injected() -> None:
    sup = Supervisor([1], J)
    sup.inject(2 * J)
    assert (sup.state.usable, sup.state.injected) == (3 * J, 2 * J)
    with pytest.raises(LocalProtocolError):
        sup.inject(0)


def test_write_off_is_paid_back_with_the_next_intention() -> None:
    h = Harness("hardened")
    h.begin(J)
    h.drop_to_client()
    for _ in range(h.timing.retries):  # N identical re-sends, all lost
        h.sup_timer()
        h.drop_to_client()
    h.sup_timer()  # gives up: written off
    assert h.sup.is_quiescent() and h.ledger.dissipated == J
    h.begin(J)
    h.settle()
    assert h.ledger.dissipated == 0 and h.client().state.usable == 2 * J
