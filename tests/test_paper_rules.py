"""Every cell of the paper-literal tables (Figs. 3 and 4), including those the hazards rely on."""

from __future__ import annotations

from dataclasses import replace

import pytest
from support import cells
from support.cells import Case, params, run_case, run_ignored, run_refused

from canergy.core import (
    Acknowledged,
    ClientAborted,
    ClientCommitted,
    Resolved,
    ReturnCredited,
    RolledBack,
    Send,
    Timing,
)
from canergy.core.inputs import (
    COMMAND_TIMEOUT,
    POWER_LOSS,
    RESPONSE_TIMEOUT,
    RETURN_TIMEOUT,
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    ResponseTimeout,
    ReturnTimeout,
    Spend,
)
from canergy.core.paper import CLIENT, SUPERVISOR
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    FinalAck,
    Intention,
    Join,
    Return,
    ReturnAck,
    StatusRequest,
)

T = Timing(response_timeout_us=100, retries=1, command_timeout_us=100)
ID, WA, AC, WC, WS = (
    Phase.IDLE,
    Phase.WAIT_ACK,
    Phase.ACKED,
    Phase.WAIT_CONFIRM,
    Phase.WAIT_STATUS,
)
CMD, SUP = Phase.AWAIT_COMMAND, Phase.AWAIT_SUPERVISOR

# -- supervisor ------------------------------------------------------------------------------
IDLE = Session(node=1, tx=3, delivered=500)
OPEN = Session(node=1, phase=WA, tx=4, reserved=2000, tries=1, deadline=100)
ACKED = replace(OPEN, phase=AC, deadline=None)
WAITING = replace(OPEN, phase=WC, decision=Decision.COMMIT)
ASKED = replace(WAITING, phase=WS, tries=1, deadline=200)
RESOLVED = replace(
    OPEN, phase=ID, reserved=0, delivered=2000, decision=Decision.NONE, tries=0, deadline=None
)
FINAL = Send(FinalAck(1, 4))
REDEFINED = replace(OPEN, tx=5, tries=1, deadline=150)


def credited(s: Session, copies: int = 1) -> Case:
    return Case(
        f"every return is credited ({s.phase.name})",
        replace(s, returns_credited=1, returned=3000 * (copies - 1)),
        Return(1, 1, 3),
        replace(s, returns_credited=1, returned=3000 * copies),
        (ReturnCredited(1, 1, 3000),),
        3000,
    )


SUP_CASES = [
    Case(
        "begin",
        IDLE,
        Begin(2000),
        replace(IDLE, phase=WA, tx=4, reserved=2000, tries=1, deadline=150),
        (Send(Intention(1, 4, 2, 0)),),
        -2000,
    ),
    Case(
        "decide",
        ACKED,
        Decide(Decision.COMMIT),
        replace(WAITING, deadline=150),
        (Send(Commit(1, 4, 2)),),
    ),
    Case("ack", OPEN, Ack(1, 4), ACKED, (Acknowledged(1, 4),)),
    Case(
        "wrong ack defines a new intention",
        OPEN,
        Ack(1, 3),
        REDEFINED,
        (Send(Intention(1, 5, 2, 0)),),
    ),
    Case(
        "committed",
        WAITING,
        Committed(1, 4),
        replace(RESOLVED, decision=Decision.NONE),
        (Resolved(1, 4, Outcome.COMMITTED, 2000), FINAL),
    ),
    Case(
        "committed after a status request",
        ASKED,
        Committed(1, 4),
        RESOLVED,
        (Resolved(1, 4, Outcome.COMMITTED, 2000), FINAL),
    ),
    Case(
        "aborted",
        replace(WAITING, decision=Decision.ABORT),
        Aborted(1, 4),
        replace(RESOLVED, delivered=0),
        (Resolved(1, 4, Outcome.ABORTED, 2000), FINAL),
        2000,
    ),
    Case("aborted for another tx", ASKED, Aborted(1, 3), ASKED),
    credited(IDLE, 2),
    credited(OPEN),
    credited(ACKED),
    credited(WAITING),
    credited(ASKED),
    Case(
        "timeout defines a new intention for the same reservation",
        OPEN,
        RESPONSE_TIMEOUT,
        replace(REDEFINED, deadline=200),
        (Send(Intention(1, 5, 2, 0)),),
        now=100,
    ),
    Case(
        "no reply: status request",
        WAITING,
        RESPONSE_TIMEOUT,
        ASKED,
        (Send(StatusRequest(1, 4)),),
        now=100,
    ),
    Case(
        "passivity timeout after N status requests",
        ASKED,
        RESPONSE_TIMEOUT,
        RESOLVED,
        (Resolved(1, 4, Outcome.WRITTEN_OFF, 2000), FINAL),
        now=300,
    ),
    Case("power loss while idle", IDLE, POWER_LOSS, replace(IDLE, tx=0)),
    Case(
        "reset loses the transaction budget",
        replace(OPEN, delivered=500),
        POWER_LOSS,
        replace(RESOLVED, tx=0, delivered=2500),
    ),
    Case("reset while acked", ACKED, POWER_LOSS, replace(RESOLVED, tx=0)),
    Case("reset while waiting", WAITING, POWER_LOSS, replace(RESOLVED, tx=0)),
    Case("reset after a status request", ASKED, POWER_LOSS, replace(RESOLVED, tx=0)),
]
SUP_IGNORED = {
    (ID, Ack),
    (AC, Ack),
    (WC, Ack),
    (WS, Ack),
    (ID, Committed),
    (WA, Committed),
    (AC, Committed),
    (ID, Aborted),
    (WA, Aborted),
    (AC, Aborted),
    (ID, ResponseTimeout),
    (AC, ResponseTimeout),
    *((p, Join) for p in (ID, WA, AC, WC, WS)),  # the paper has no re-provisioning
    *((p, e) for p in (ID, WA, AC, WC, WS) for e in (Debit,)),  # nor witnessed records
}
SUP_REFUSED = {(p, Begin) for p in (WA, AC, WC, WS)} | {(p, Decide) for p in (ID, WA, WC, WS)}
SUP_STATES = {ID: IDLE, WA: OPEN, AC: ACKED, WC: WAITING, WS: ASKED}
SUP_EVENTS = {
    Ack: Ack(1, 4),
    Committed: Committed(1, 4),
    Aborted: Aborted(1, 4),
    ResponseTimeout: RESPONSE_TIMEOUT,
    Begin: Begin(1000),
    Decide: Decide(Decision.ABORT),
    Join: Join(1, 7),
    Debit: Debit(3, 9, Debit.START, 4, 0),
}

# -- client ----------------------------------------------------------------------------------
FRESH = ClientState(1, usable=1000, credited=1000)
HELD = replace(FRESH, phase=CMD, held_tx=4, held_amount=2000, deadline=100)
DONE = replace(HELD, phase=SUP, usable=3000, credited=3000, outcome=Outcome.COMMITTED, deadline=210)
TIMED = replace(DONE, timeout_commit=True, deadline=300)

CLIENT_CASES = [
    Case("intention held and acked", FRESH, Intention(1, 4, 2, 0), HELD, (Send(Ack(1, 4)),), now=0),
    Case("duplicate intention re-acked", HELD, Intention(1, 4, 2, 0), HELD, (Send(Ack(1, 4)),)),
    Case(
        "a new intention rolls back a timeout-commit",
        replace(TIMED, usable=500, spent=2500),
        Intention(1, 5, 2, 0),
        replace(HELD, usable=0, credited=2500, spent=2500, held_tx=5, deadline=250),
        (RolledBack(1, 4, 500), Send(Ack(1, 5))),
        now=150,
    ),
    Case("duplicate intention after the reply", DONE, Intention(1, 4, 2, 0), DONE),
    Case(
        "commit",
        HELD,
        Commit(1, 4, 2),
        DONE,
        (ClientCommitted(1, 4, 2000, False), Send(Committed(1, 4))),
        now=10,
    ),
    Case("commit for another tx", HELD, Commit(1, 3, 2), HELD),
    Case(
        "abort",
        HELD,
        Abort(1, 4, 2),
        replace(HELD, phase=SUP, outcome=Outcome.ABORTED, deadline=210),
        (ClientAborted(1, 4), Send(Aborted(1, 4))),
        now=10,
    ),
    Case(
        "status request answered, TimeoutN re-armed",
        DONE,
        StatusRequest(1, 4),
        replace(DONE, deadline=350),
        (Send(Committed(1, 4)),),
        now=150,
    ),
    Case("final ack forgets", DONE, FinalAck(1, 4), replace(FRESH, usable=3000, credited=3000)),
    Case(
        "timeout-commit",
        HELD,
        COMMAND_TIMEOUT,
        TIMED,
        (ClientCommitted(1, 4, 2000, True), Send(Committed(1, 4))),
        now=100,
    ),
    Case(
        "TimeoutN forgets",
        DONE,
        COMMAND_TIMEOUT,
        replace(FRESH, usable=3000, credited=3000),
        now=310,
    ),
    Case("spend", FRESH, Spend(400), replace(FRESH, usable=600, spent=400)),
    Case("spend while held", HELD, Spend(1000), replace(HELD, usable=0, spent=1000)),
    Case("spend while awaiting", DONE, Spend(1000), replace(DONE, usable=2000, spent=1000)),
    Case(
        "give back, sent once",
        FRESH,
        GiveBack(1000),
        replace(FRESH, usable=0, return_seq=1, return_pending=1000),
        (Send(Return(1, 1, 1)),),
    ),
    Case(
        "give back while held",
        HELD,
        GiveBack(1000),
        replace(HELD, usable=0, return_seq=1, return_pending=1000),
        (Send(Return(1, 1, 1)),),
    ),
    Case(
        "give back while awaiting",
        DONE,
        GiveBack(1000),
        replace(DONE, usable=2000, return_seq=1, return_pending=1000),
        (Send(Return(1, 1, 1)),),
    ),
    Case("reset while idle", replace(FRESH, last_tx=3), POWER_LOSS, FRESH),
    Case("reset forgets the hold", HELD, POWER_LOSS, FRESH),
    Case(
        "reset forgets a timeout-commit",
        TIMED,
        POWER_LOSS,
        replace(FRESH, usable=3000, credited=3000, outcome=Outcome.NONE),
    ),
    *[
        Case(f"lost books while {c.phase.name}: a blank record", c, BooksLost(7), ClientState(1))
        for c in (FRESH, HELD, DONE)
    ],
]
CLIENT_IGNORED = (
    {(ID, Commit), (SUP, Commit), (ID, Abort), (SUP, Abort)}
    | {(p, ReturnAck) for p in (ID, CMD, SUP)}
    | {(ID, StatusRequest), (CMD, StatusRequest), (ID, FinalAck), (CMD, FinalAck)}
    | {(ID, CommandTimeout)}
    | {(p, ReturnTimeout) for p in (ID, CMD, SUP)}
    | {(p, Admit) for p in (ID, CMD, SUP)}
)
CLIENT_STATES = {ID: FRESH, CMD: HELD, SUP: DONE}
CLIENT_EVENTS = {
    Commit: Commit(1, 4, 2),
    Abort: Abort(1, 4, 2),
    ReturnAck: ReturnAck(1, 1),
    StatusRequest: StatusRequest(1, 4),
    FinalAck: FinalAck(1, 4),
    CommandTimeout: COMMAND_TIMEOUT,
    ReturnTimeout: RETURN_TIMEOUT,
    Admit: Admit(1, 7, 4, 0),
}


@pytest.mark.parametrize("case", params(SUP_CASES))
def test_supervisor_cell(case: Case) -> None:
    run_case(SUPERVISOR, T, case)


@pytest.mark.parametrize("cell", sorted(SUP_IGNORED, key=str), ids=str)
def test_supervisor_ignored(cell: cells.CellKey) -> None:
    run_ignored(SUPERVISOR, T, cell, SUP_STATES, SUP_EVENTS)


@pytest.mark.parametrize("cell", sorted(SUP_REFUSED, key=str), ids=str)
def test_supervisor_refused(cell: cells.CellKey) -> None:
    run_refused(SUPERVISOR, T, cell, SUP_STATES, SUP_EVENTS)


@pytest.mark.parametrize("case", params(CLIENT_CASES))
def test_client_cell(case: Case) -> None:
    run_case(CLIENT, T, case)


@pytest.mark.parametrize("cell", sorted(CLIENT_IGNORED, key=str), ids=str)
def test_client_ignored(cell: cells.CellKey) -> None:
    run_ignored(CLIENT, T, cell, CLIENT_STATES, CLIENT_EVENTS)


def test_every_cell_has_a_test() -> None:
    cells.check_coverage(SUPERVISOR, SUP_CASES, SUP_IGNORED, SUP_REFUSED)
    cells.check_coverage(CLIENT, CLIENT_CASES, CLIENT_IGNORED, set())


def test_only_usable_persists() -> None:
    assert SUPERVISOR.persistent(OPEN) == SUPERVISOR.persistent(IDLE) == ()
    assert CLIENT.persistent(DONE) != CLIENT.persistent(FRESH)
    assert CLIENT.persistent(HELD) == CLIENT.persistent(FRESH)
