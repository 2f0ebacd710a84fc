"""Every cell of the hardened supervisor's transition table (one node's session)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from support import cells
from support.cells import Case, params, run_case, run_ignored, run_refused

from canergy.core import Acknowledged, Admitted, Resolved, ReturnCredited, Send, Timing
from canergy.core.hardened import SUPERVISOR as TABLE
from canergy.core.inputs import POWER_LOSS, RESPONSE_TIMEOUT, Begin, Decide, PowerLoss
from canergy.core.inputs import ResponseTimeout as Timeout
from canergy.core.state import Decision, Outcome, Phase, Session
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    Intention,
    Join,
    Return,
    ReturnAck,
)

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
WRITTEN_OFF = (Resolved(3, 7, Outcome.WRITTEN_OFF, TS),)
ID, WA, AC, WC = Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM


def returned(s: Session, seq: int = 5, amount: int = 9000) -> Session:
    return replace(s, returns_credited=seq, returned=amount)


def credited(seq: int = 5, wire: int = 5, amount: int = 9000) -> tuple[object, ...]:
    return (ReturnCredited(3, seq, amount), Send(ReturnAck(3, wire)))


CASES = [
    Case(
        "begin reserves Ts from Us and sends the intention with Gs",
        IDLE,
        Begin(TS),
        replace(IDLE, phase=WA, tx=8, reserved=TS, tries=1, deadline=150),
        (Send(Intention(3, 8, 5, 2)),),
        -TS,
    ),
    Case(
        "decide sends the command",
        ACKED,
        Decide(Decision.ABORT),
        replace(ABORTING, deadline=150),
        (Send(Abort(3, 7, 5)),),
    ),
    Case("ack", OPEN, Ack(3, 7), ACKED, (Acknowledged(3, 7),)),
    Case("ack for another tx", OPEN, Ack(3, 6), OPEN),
    Case(
        "committed",
        COMMITTING,
        Committed(3, 7),
        DELIVERED,
        (Resolved(3, 7, Outcome.COMMITTED, TS),),
    ),
    Case(
        "timeout-commit before the ack",
        OPEN,
        Committed(3, 7),
        replace(DELIVERED, tries=0),
        (Resolved(3, 7, Outcome.COMMITTED, TS),),
    ),
    Case(
        "timeout-commit while the decision is pending",
        ACKED,
        Committed(3, 7),
        replace(DELIVERED, tries=0),
        (Resolved(3, 7, Outcome.COMMITTED, TS),),
    ),
    Case(
        "timeout-commit beats the abort",
        ABORTING,
        Committed(3, 7),
        DELIVERED,
        (Resolved(3, 7, Outcome.COMMITTED, TS),),
    ),
    Case("stale committed", COMMITTING, Committed(3, 6), COMMITTING),
    Case(
        "aborted returns Ts to Us",
        ABORTING,
        Aborted(3, 7),
        replace(DELIVERED, delivered=2000),
        (Resolved(3, 7, Outcome.ABORTED, TS),),
        TS,
    ),
    Case("aborted without an abort decision", COMMITTING, Aborted(3, 7), COMMITTING),
    Case("stale aborted", ABORTING, Aborted(3, 6), ABORTING),
    Case("return next", IDLE, Return(3, 5, 9), returned(IDLE), credited(), 9000),
    Case("return duplicate", IDLE, Return(3, 4, 9), IDLE, (Send(ReturnAck(3, 4)),)),
    Case("return from the future", IDLE, Return(3, 6, 9), IDLE),
    Case(
        "return across the 16-bit wrap",
        replace(IDLE, returns_credited=0xFFFF),
        Return(3, 0, 1),
        returned(IDLE, 0x10000, 1000),
        credited(0x10000, 0, 1000),
        1000,
    ),
    Case(
        "return while the intention is open",
        OPEN,
        Return(3, 1, 9),
        returned(OPEN, 1),
        credited(1, 1),
        9000,
    ),
    Case("return while acked", ACKED, Return(3, 1, 9), returned(ACKED, 1), credited(1, 1), 9000),
    Case(
        "return while confirming",
        COMMITTING,
        Return(3, 1, 9),
        returned(COMMITTING, 1),
        credited(1, 1),
        9000,
    ),
    Case(
        "timer re-sends the identical intention",
        OPEN,
        RESPONSE_TIMEOUT,
        replace(OPEN, tries=2, deadline=200),
        (Send(Intention(3, 7, 5, 2)),),
        now=100,
    ),
    Case(
        "timer re-sends the identical commit",
        COMMITTING,
        RESPONSE_TIMEOUT,
        replace(COMMITTING, tries=2, deadline=200),
        (Send(Commit(3, 7, 5)),),
        now=100,
    ),
    Case(
        "timer re-sends the identical abort",
        ABORTING,
        RESPONSE_TIMEOUT,
        replace(ABORTING, tries=2, deadline=200),
        (Send(Abort(3, 7, 5)),),
        now=100,
    ),
    Case(
        "write-off after N re-sends of the intention",
        replace(OPEN, tries=3),
        RESPONSE_TIMEOUT,
        replace(DELIVERED, tries=0),
        WRITTEN_OFF,
        now=100,
    ),
    Case(
        "write-off after N re-sends of the command",
        replace(ABORTING, tries=3),
        RESPONSE_TIMEOUT,
        DELIVERED,
        WRITTEN_OFF,
        now=100,
    ),
    Case("timer not due yet", OPEN, RESPONSE_TIMEOUT, OPEN, now=99),
    Case("power loss while idle", IDLE, POWER_LOSS, IDLE, now=900),
    Case(
        "power loss re-sends the intention at once",
        OPEN,
        POWER_LOSS,
        replace(OPEN, tries=0, deadline=900),
        now=900,
    ),
    Case(
        "power loss forgets the ack (not persisted)",
        ACKED,
        POWER_LOSS,
        replace(OPEN, tries=0, deadline=900),
        now=900,
    ),
    Case(
        "power loss re-sends the command at once",
        COMMITTING,
        POWER_LOSS,
        replace(COMMITTING, tries=0, deadline=900),
        now=900,
    ),
    Case(
        "join while idle: admit at the current counters",
        IDLE,
        Join(3, 0xBEEF),
        IDLE,
        (Admitted(3, 7, 4), Send(Admit(3, 0xBEEF, 7, 4))),
    ),
    *[
        Case(
            f"join while {s.phase.name}: write off, then admit",
            s,
            Join(3, 0xBEEF),
            replace(DELIVERED, delivered=2000 + TS, returns_credited=9),
            (*WRITTEN_OFF, Admitted(3, 7, 9), Send(Admit(3, 0xBEEF, 7, 9))),
        )
        for s in (replace(x, returns_credited=9) for x in (OPEN, ACKED, COMMITTING))
    ],
]
IGNORED = {
    (ID, Ack),
    (AC, Ack),
    (WC, Ack),
    (ID, Committed),
    (ID, Aborted),
    (WA, Aborted),
    (AC, Aborted),
    (ID, Timeout),
    (AC, Timeout),
    *((p, e) for p in (ID, WA, AC, WC) for e in (Debit,)),  # the witnessed rules' frames
}
REFUSED = {(WA, Begin), (AC, Begin), (WC, Begin), (ID, Decide), (WA, Decide), (WC, Decide)}
STATES = {ID: IDLE, WA: OPEN, AC: ACKED, WC: COMMITTING}
EVENTS = {
    Ack: Ack(3, 7),
    Committed: Committed(3, 7),
    Aborted: Aborted(3, 7),
    Timeout: RESPONSE_TIMEOUT,
    Begin: Begin(TS),
    Decide: Decide(Decision.COMMIT),
    PowerLoss: POWER_LOSS,
    Debit: Debit(3, 9, Debit.START, 4, 0),
}


@pytest.mark.parametrize("case", params(CASES))
def test_cell(case: Case) -> None:
    run_case(TABLE, T, case)


@pytest.mark.parametrize("cell", sorted(IGNORED, key=str), ids=str)
def test_ignored(cell: cells.CellKey) -> None:
    run_ignored(TABLE, T, cell, STATES, EVENTS)


@pytest.mark.parametrize("cell", sorted(REFUSED, key=str), ids=str)
def test_refused(cell: cells.CellKey) -> None:
    run_refused(TABLE, T, cell, STATES, EVENTS)


def test_every_cell_has_a_test() -> None:
    cells.check_coverage(TABLE, CASES, IGNORED, REFUSED)


def test_tx_wraps_on_the_wire() -> None:
    s, actions, _ = TABLE.step(T, replace(IDLE, tx=0xFFFF), Begin(TS), 0)
    assert s.tx == 0x10000 and actions == (Send(Intention(3, 0, 5, 2)),)
    acked, notes, _ = TABLE.step(T, s, Ack(3, 0), 1)
    assert acked.phase is Phase.ACKED and notes == (Acknowledged(3, 0x10000),)


def test_what_persists() -> None:
    assert TABLE.persistent(ACKED) == TABLE.persistent(OPEN)
    assert TABLE.persistent(OPEN) != TABLE.persistent(replace(OPEN, delivered=1))
    assert TABLE.persistent(OPEN) == TABLE.persistent(replace(OPEN, tries=5, deadline=7))
