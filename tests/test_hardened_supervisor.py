"""Table-driven transitions of the hardened supervisor session rules."""

from __future__ import annotations

from dataclasses import replace

import pytest

from canergy.core import Acknowledged, Resolved, ReturnCredited, Send, Timing
from canergy.core.hardened import HardenedSupervisor as R
from canergy.core.state import Decision, Outcome, Phase, Session
from canergy.messages import Abort as AbortMsg
from canergy.messages import Aborted, Ack, Commit, Committed, Intention, Return, ReturnAck

T = Timing(response_timeout_us=100, retries=2)
TS = 5000  # reserved µJ (5 mJ)
OPEN = Session(
    node=3, phase=Phase.WAIT_ACK, tx=7, reserved=TS, delivered=2000, tries=1, deadline=100
)
ACKED = replace(OPEN, phase=Phase.ACKED, deadline=None)
COMMITTING = replace(OPEN, phase=Phase.WAIT_CONFIRM, decision=Decision.COMMIT)
ABORTING = replace(OPEN, phase=Phase.WAIT_CONFIRM, decision=Decision.ABORT)
IDLE = Session(node=3, tx=7, delivered=2000, returns_credited=4)

DELIVERED = replace(
    COMMITTING,
    phase=Phase.IDLE,
    reserved=0,
    delivered=7000,
    decision=Decision.NONE,
    tries=0,
    deadline=None,
)


@pytest.mark.parametrize(
    ("name", "start", "msg", "end", "actions", "credit"),
    [
        ("ack", OPEN, Ack(3, 7), ACKED, (Acknowledged(3, 7),), 0),
        ("ack for another tx", OPEN, Ack(3, 6), OPEN, (), 0),
        ("duplicate ack", ACKED, Ack(3, 7), ACKED, (), 0),
        ("ack when idle", IDLE, Ack(3, 7), IDLE, (), 0),
        (
            "committed",
            COMMITTING,
            Committed(3, 7),
            DELIVERED,
            (Resolved(3, 7, Outcome.COMMITTED, TS),),
            0,
        ),
        (
            "timeout-commit before the ack",
            OPEN,
            Committed(3, 7),
            replace(DELIVERED, tries=0),
            (Resolved(3, 7, Outcome.COMMITTED, TS),),
            0,
        ),
        (
            "timeout-commit beats the abort",
            ABORTING,
            Committed(3, 7),
            DELIVERED,
            (Resolved(3, 7, Outcome.COMMITTED, TS),),
            0,
        ),
        (
            "aborted returns Ts to Us",
            ABORTING,
            Aborted(3, 7),
            replace(DELIVERED, delivered=2000),
            (Resolved(3, 7, Outcome.ABORTED, TS),),
            TS,
        ),
        ("aborted without an abort decision", COMMITTING, Aborted(3, 7), COMMITTING, (), 0),
        ("aborted while only acked", ACKED, Aborted(3, 7), ACKED, (), 0),
        ("stale committed", COMMITTING, Committed(3, 6), COMMITTING, (), 0),
        ("stale aborted", ABORTING, Aborted(3, 6), ABORTING, (), 0),
        (
            "return next",
            IDLE,
            Return(3, 5, 9),
            replace(IDLE, returns_credited=5, returned=9000),
            (ReturnCredited(3, 5, 9000), Send(ReturnAck(3, 5))),
            9000,
        ),
        ("return duplicate", IDLE, Return(3, 4, 9), IDLE, (Send(ReturnAck(3, 4)),), 0),
        ("return from the future", IDLE, Return(3, 6, 9), IDLE, (), 0),
        (
            "return across the 16-bit wrap",
            replace(IDLE, returns_credited=0xFFFF),
            Return(3, 0, 1),
            replace(IDLE, returns_credited=0x10000, returned=1000),
            (ReturnCredited(3, 0x10000, 1000), Send(ReturnAck(3, 0))),
            1000,
        ),
    ],
)
def test_receive(name: str, start: Session, msg, end: Session, actions: tuple, credit: int) -> None:
    assert R.receive(T, start, msg, 50) == (end, actions, credit)


def test_begin_sends_intention_with_delivered_count() -> None:
    s, actions = R.begin(T, IDLE, TS, 10)
    assert (s.phase, s.tx, s.reserved, s.tries, s.deadline) == (Phase.WAIT_ACK, 8, TS, 1, 110)
    assert actions == (Send(Intention(3, 8, 5, 2)),)


def test_tx_wraps_on_the_wire() -> None:
    s, actions = R.begin(T, replace(IDLE, tx=0xFFFF), TS, 0)
    assert s.tx == 0x10000 and actions == (Send(Intention(3, 0, 5, 2)),)
    acked, notes, _ = R.receive(T, s, Ack(3, 0), 1)
    assert acked.phase is Phase.ACKED and notes == (Acknowledged(3, 0x10000),)


@pytest.mark.parametrize(
    ("start", "resent"),
    [(OPEN, Intention(3, 7, 5, 2)), (COMMITTING, Commit(3, 7, 5)), (ABORTING, AbortMsg(3, 7, 5))],
)
def test_timer_resends_the_identical_message(start: Session, resent) -> None:
    s, actions, credit = R.timer(T, start, 100)
    assert actions == (Send(resent),) and credit == 0
    assert (s.tries, s.deadline, s.tx, s.reserved) == (2, 200, 7, TS)


@pytest.mark.parametrize("start", [OPEN, COMMITTING, ABORTING])
def test_write_off_after_n_resends(start: Session) -> None:
    exhausted = replace(start, tries=T.retries + 1)
    s, actions, credit = R.timer(T, exhausted, 100)
    assert actions == (Resolved(3, 7, Outcome.WRITTEN_OFF, TS),)
    assert (s.phase, s.reserved, s.delivered, credit) == (Phase.IDLE, 0, 2000 + TS, 0)


@pytest.mark.parametrize("start", [replace(OPEN, deadline=101), ACKED, IDLE])
def test_timer_not_due_or_not_armed(start: Session) -> None:
    assert R.timer(T, start, 100) == (start, (), 0)


def test_decide_sends_command() -> None:
    s, actions, _ = R.decide(T, ACKED, Decision.ABORT, 40)
    assert s.phase is Phase.WAIT_CONFIRM and s.decision is Decision.ABORT and s.deadline == 140
    assert actions == (Send(AbortMsg(3, 7, 5)),)


def test_power_loss_keeps_the_record_and_resends() -> None:
    assert R.power_loss(ACKED, 900) == replace(OPEN, tries=0, deadline=900)
    assert R.power_loss(COMMITTING, 900) == replace(COMMITTING, tries=0, deadline=900)
    assert R.power_loss(IDLE, 900) == IDLE
    assert R.persistent(ACKED) == R.persistent(OPEN)
