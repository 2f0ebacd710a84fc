"""Table-driven transitions of the hardened client rules."""

from __future__ import annotations

from dataclasses import replace

import pytest

from canergy.core import ClientAborted, ClientCommitted, Credited, ReturnAcknowledged, Send, Timing
from canergy.core.hardened import HardenedClient as R
from canergy.core.state import ClientState, Outcome
from canergy.messages import Abort, Aborted, Ack, Commit, Committed, Intention, Return, ReturnAck

T = Timing(command_timeout_us=1000, return_retry_us=300)
A = 4000  # 4 mJ
FRESH = ClientState(
    node=2, usable=10_000, credited=50_000, spent=40_000, last_tx=5, outcome=Outcome.COMMITTED
)
HOLDING = replace(FRESH, held_tx=6, held_amount=A, deadline=1000)
COMMITTED_6 = replace(FRESH, usable=14_000, credited=54_000, last_tx=6)
ABORTED_6 = replace(FRESH, last_tx=6, outcome=Outcome.ABORTED)
RETURNING = replace(FRESH, return_seq=3, return_pending=2000, return_deadline=300)


def intention(tx: int, delivered_mj: int = 50) -> Intention:
    return Intention(2, tx, A // 1000, delivered_mj)


@pytest.mark.parametrize(
    ("name", "start", "msg", "end", "actions"),
    [
        ("new intention is held and acked", FRESH, intention(6), HOLDING, (Send(Ack(2, 6)),)),
        (
            "duplicate intention re-acked, timer kept",
            HOLDING,
            intention(6),
            HOLDING,
            (Send(Ack(2, 6)),),
        ),
        (
            "intention already committed gets the recorded reply",
            COMMITTED_6,
            intention(6),
            COMMITTED_6,
            (Send(Committed(2, 6)),),
        ),
        (
            "intention already aborted gets the recorded reply",
            ABORTED_6,
            intention(6),
            ABORTED_6,
            (Send(Aborted(2, 6)),),
        ),
        ("stale intention ignored", COMMITTED_6, intention(5), COMMITTED_6, ()),
        (
            "skipped transactions are settled",
            FRESH,
            intention(8),
            replace(
                FRESH, last_tx=7, outcome=Outcome.SETTLED, held_tx=8, held_amount=A, deadline=1000
            ),
            (Send(Ack(2, 8)),),
        ),
        (
            "a newer intention drops a stale hold",
            HOLDING,
            intention(9),
            replace(HOLDING, last_tx=8, outcome=Outcome.SETTLED, held_tx=9),
            (Send(Ack(2, 9)),),
        ),
        (
            "write-off paid back through Gs",
            FRESH,
            intention(6, delivered_mj=53),
            replace(HOLDING, usable=13_000, credited=53_000),
            (Credited(2, 3000), Send(Ack(2, 6))),
        ),
        (
            "older Gs pays nothing",
            FRESH,
            intention(6, delivered_mj=40),
            HOLDING,
            (Send(Ack(2, 6)),),
        ),
        (
            "commit",
            HOLDING,
            Commit(2, 6, 4),
            COMMITTED_6,
            (ClientCommitted(2, 6, A, False), Send(Committed(2, 6))),
        ),
        (
            "commit after a reset lost the hold uses the message amount",
            FRESH,
            Commit(2, 6, 4),
            COMMITTED_6,
            (ClientCommitted(2, 6, A, False), Send(Committed(2, 6))),
        ),
        (
            "duplicate commit is answered, not applied",
            COMMITTED_6,
            Commit(2, 6, 4),
            COMMITTED_6,
            (Send(Committed(2, 6)),),
        ),
        (
            "late abort after a commit is answered committed",
            COMMITTED_6,
            Abort(2, 6, 4),
            COMMITTED_6,
            (Send(Committed(2, 6)),),
        ),
        ("abort", HOLDING, Abort(2, 6, 4), ABORTED_6, (ClientAborted(2, 6), Send(Aborted(2, 6)))),
        (
            "late commit after an abort is answered aborted",
            ABORTED_6,
            Commit(2, 6, 4),
            ABORTED_6,
            (Send(Aborted(2, 6)),),
        ),
        ("stale commit ignored", COMMITTED_6, Commit(2, 5, 4), COMMITTED_6, ()),
        (
            "return acknowledged",
            RETURNING,
            ReturnAck(2, 3),
            replace(RETURNING, return_pending=0, return_deadline=None),
            (ReturnAcknowledged(2, 3),),
        ),
        ("other return ack ignored", RETURNING, ReturnAck(2, 2), RETURNING, ()),
    ],
)
def test_receive(name: str, start: ClientState, msg, end: ClientState, actions: tuple) -> None:
    assert R.receive(T, start, msg, 0) == (end, actions)


def test_tx_wraps_on_the_wire() -> None:
    start = replace(FRESH, last_tx=0xFFFF)
    held, actions = R.receive(T, start, intention(0), 0)
    assert held.held_tx == 0x10000 and actions == (Send(Ack(2, 0)),)


def test_command_timer_commits_the_held_intention() -> None:
    c, actions = R.command_timer(T, HOLDING, 1000)
    assert c == COMMITTED_6
    assert actions == (ClientCommitted(2, 6, A, True), Send(Committed(2, 6)))


@pytest.mark.parametrize("start", [FRESH, replace(HOLDING, deadline=1001)])
def test_command_timer_idle_or_early(start: ClientState) -> None:
    assert R.command_timer(T, start, 1000) == (start, ())


def test_return_is_debited_first_and_resent_until_acked() -> None:
    c, actions = R.give_back(T, FRESH, 2000, 10)
    assert (c.usable, c.return_seq, c.return_pending, c.return_deadline) == (8000, 1, 2000, 310)
    assert actions == (Send(Return(2, 1, 2)),)
    again, resent = R.return_timer(T, c, 310)
    assert resent == (Send(Return(2, 1, 2)),) and again.return_deadline == 610
    assert not R.can_give_back(c)


def test_power_loss_keeps_the_record() -> None:
    c = R.power_loss(replace(HOLDING, return_seq=3, return_pending=2000, return_deadline=5), 77)
    assert (c.held_tx, c.held_amount, c.deadline, c.return_deadline) == (0, 0, None, 77)
    assert R.persistent(c) == (*R.persistent(HOLDING)[:5], 3, 2000)
