"""The cases of the hardened client's transition table (``canergy.core.hardened.CLIENT``).

``CASES`` names the cells that do something, each from a start state through an event to its
end state and actions; ``IGNORED`` and ``REFUSED`` the cells that ignore an event or refuse a
request, tried from ``STATES`` with ``EVENTS``. tests/test_hardened_client.py runs them on the
Python table, tests/test_c_hardened.py on the C client, and both check that every cell of the
table has one (``support.cells.check_coverage``).
"""

from __future__ import annotations

from dataclasses import replace

from canergy.core import (
    ClientAborted,
    ClientCommitted,
    Credited,
    IntentionRefused,
    ReturnAcknowledged,
    Send,
    Timing,
)
from canergy.core.inputs import (
    COMMAND_TIMEOUT,
    POWER_LOSS,
    RETURN_TIMEOUT,
    BooksLost,
    CommandTimeout,
    GiveBack,
    Spend,
)
from canergy.core.state import ClientState, Outcome, Phase
from canergy.messages import (
    USABLE_MAX_UJ,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    FinalAck,
    Intention,
    Join,
    Return,
    ReturnAck,
    StatusRequest,
)
from support.cells import Case

T = Timing(command_timeout_us=1000, return_retry_us=300)
A = 4000  # 4 mJ
ID, HO, JO = Phase.IDLE, Phase.AWAIT_COMMAND, Phase.JOINING
FRESH = ClientState(
    node=2, usable=10_000, credited=50_000, spent=40_000, last_tx=5, outcome=Outcome.COMMITTED
)
HOLDING = replace(FRESH, phase=HO, held_tx=6, held_amount=A, deadline=1000)
COMMITTED_6 = replace(FRESH, usable=14_000, credited=54_000, last_tx=6)
ABORTED_6 = replace(FRESH, last_tx=6, outcome=Outcome.ABORTED)
RETURNING = replace(FRESH, return_seq=3, return_pending=2000, return_deadline=300)
COMMITS_6 = (ClientCommitted(2, 6, A, False), Send(Committed(2, 6)))
JOINING = ClientState(node=2, phase=JO, nonce=0xBEEF, return_deadline=300)
ADMITTED = ClientState(
    node=2, last_tx=40, outcome=Outcome.SETTLED, return_seq=7, credited_unknown=True
)
FULL = replace(FRESH, usable=USABLE_MAX_UJ - A + 1)  # one µJ short of room for A


def intention(tx: int, delivered_mj: int = 50) -> Intention:
    return Intention(2, tx, A // 1000, delivered_mj)


CASES = [
    Case(
        "new intention is held and acked", FRESH, intention(6), HOLDING, (Send(Ack(2, 6)),), now=0
    ),
    Case(
        "duplicate intention re-acked, timer kept",
        HOLDING,
        intention(6),
        HOLDING,
        (Send(Ack(2, 6)),),
    ),
    Case(
        "intention already committed gets the recorded reply",
        COMMITTED_6,
        intention(6),
        COMMITTED_6,
        (Send(Committed(2, 6)),),
    ),
    Case(
        "intention already aborted gets the recorded reply",
        ABORTED_6,
        intention(6),
        ABORTED_6,
        (Send(Aborted(2, 6)),),
    ),
    Case("stale intention ignored", COMMITTED_6, intention(5), COMMITTED_6),
    Case(
        "skipped transactions are settled",
        FRESH,
        intention(8),
        replace(HOLDING, last_tx=7, outcome=Outcome.SETTLED, held_tx=8),
        (Send(Ack(2, 8)),),
        now=0,
    ),
    Case(
        "a newer intention drops a stale hold",
        HOLDING,
        intention(9),
        replace(HOLDING, last_tx=8, outcome=Outcome.SETTLED, held_tx=9),
        (Send(Ack(2, 9)),),
        now=0,
    ),
    Case(
        "write-off paid back through Gs",
        FRESH,
        intention(6, delivered_mj=53),
        replace(HOLDING, usable=13_000, credited=53_000),
        (Credited(2, 3000), Send(Ack(2, 6))),
        now=0,
    ),
    Case(
        "older Gs pays nothing",
        FRESH,
        intention(6, delivered_mj=40),
        HOLDING,
        (Send(Ack(2, 6)),),
        now=0,
    ),
    Case("commit", HOLDING, Commit(2, 6, 4), COMMITTED_6, COMMITS_6),
    Case(
        "commit after a reset lost the hold uses the message amount",
        FRESH,
        Commit(2, 6, 4),
        COMMITTED_6,
        COMMITS_6,
    ),
    Case(
        "duplicate commit is answered, not applied",
        COMMITTED_6,
        Commit(2, 6, 4),
        COMMITTED_6,
        (Send(Committed(2, 6)),),
    ),
    Case("stale commit ignored while holding", HOLDING, Commit(2, 4, 4), HOLDING),
    Case("abort", HOLDING, Abort(2, 6, 4), ABORTED_6, (ClientAborted(2, 6), Send(Aborted(2, 6)))),
    Case(
        "late abort after a commit is answered committed",
        COMMITTED_6,
        Abort(2, 6, 4),
        COMMITTED_6,
        (Send(Committed(2, 6)),),
    ),
    Case(
        "late commit after an abort is answered aborted",
        ABORTED_6,
        Commit(2, 6, 4),
        ABORTED_6,
        (Send(Aborted(2, 6)),),
    ),
    Case("stale abort ignored", COMMITTED_6, Abort(2, 5, 4), COMMITTED_6),
    Case(
        "return acknowledged",
        RETURNING,
        ReturnAck(2, 3),
        replace(RETURNING, return_pending=0, return_deadline=None),
        (ReturnAcknowledged(2, 3),),
    ),
    Case("other return ack ignored", RETURNING, ReturnAck(2, 2), RETURNING),
    Case(
        "return acknowledged while holding",
        replace(RETURNING, phase=HO, held_tx=6, held_amount=A, deadline=1000),
        ReturnAck(2, 3),
        replace(HOLDING, return_seq=3),
        (ReturnAcknowledged(2, 3),),
    ),
    Case(
        "command timer commits the held intention",
        HOLDING,
        COMMAND_TIMEOUT,
        COMMITTED_6,
        (ClientCommitted(2, 6, A, True), Send(Committed(2, 6))),
        now=1000,
    ),
    Case("command timer not due yet", HOLDING, COMMAND_TIMEOUT, HOLDING, now=999),
    Case(
        "return re-sent under the same number",
        RETURNING,
        RETURN_TIMEOUT,
        replace(RETURNING, return_deadline=600),
        (Send(Return(2, 3, 2)),),
        now=300,
    ),
    Case(
        "return timer while holding, not due",
        replace(HOLDING, return_seq=3, return_pending=2000, return_deadline=300),
        RETURN_TIMEOUT,
        replace(HOLDING, return_seq=3, return_pending=2000, return_deadline=300),
        now=299,
    ),
    Case("spend", FRESH, Spend(2500), replace(FRESH, usable=7500, spent=42_500)),
    Case("spend while holding", HOLDING, Spend(10_000), replace(HOLDING, usable=0, spent=50_000)),
    Case(
        "give back: debited first, numbered, re-sent until acked",
        FRESH,
        GiveBack(2000),
        replace(FRESH, usable=8000, return_seq=1, return_pending=2000, return_deadline=310),
        (Send(Return(2, 1, 2)),),
        now=10,
    ),
    Case(
        "give back while holding",
        HOLDING,
        GiveBack(1000),
        replace(HOLDING, usable=9000, return_seq=1, return_pending=1000, return_deadline=310),
        (Send(Return(2, 1, 1)),),
        now=10,
    ),
    Case(
        "power loss keeps the record, re-sends a pending return at once",
        replace(RETURNING, return_deadline=5),
        POWER_LOSS,
        replace(RETURNING, return_deadline=77),
        now=77,
    ),
    Case("power loss drops the hold", HOLDING, POWER_LOSS, FRESH, now=77),
    *[
        Case(
            f"books lost while {start.phase.name}: start blank and send JOIN",
            start,
            BooksLost(0xBEEF),
            JOINING,
            (Send(Join(2, 0xBEEF)),),
            now=0,
        )
        for start in (FRESH, HOLDING, replace(JOINING, nonce=1))
    ],
    Case(
        "join re-sent with the same nonce",
        JOINING,
        RETURN_TIMEOUT,
        replace(JOINING, return_deadline=600),
        (Send(Join(2, 0xBEEF)),),
        now=300,
    ),
    Case("join timer not due yet", JOINING, RETURN_TIMEOUT, JOINING, now=299),
    Case(
        "power loss before admission joins again at once",
        JOINING,
        POWER_LOSS,
        replace(JOINING, return_deadline=77),
        now=77,
    ),
    Case(
        "admit answering our join: start from its counters",
        JOINING,
        Admit(2, 0xBEEF, 40, 7),
        ADMITTED,
    ),
    Case(
        "an intention before admission moves nothing and gets a JOIN",
        JOINING,
        intention(6, 9999),
        JOINING,
        (Send(Join(2, 0xBEEF)),),
    ),
    Case("admit for another nonce ignored", JOINING, Admit(2, 0xBEEE, 40, 7), JOINING),
    Case("after admission an old intention moves nothing", ADMITTED, intention(40, 9999), ADMITTED),
    Case(
        "after admission the first fresh intention sets Rc = Gs, no pay-back",
        ADMITTED,
        intention(41, 9999),
        replace(
            ADMITTED,
            credited=9_999_000,
            credited_unknown=False,
            phase=HO,
            held_tx=41,
            held_amount=A,
            deadline=1050,
        ),
        (Send(Ack(2, 41)),),
    ),
    Case(
        "intention that would overflow the record is refused",
        FULL,
        intention(6, 50),
        FULL,
        (IntentionRefused(2, 6),),
    ),
    Case(
        "pay-back that would overflow the record is refused",
        replace(FULL, usable=USABLE_MAX_UJ - 999),
        intention(5, 51),
        replace(FULL, usable=USABLE_MAX_UJ - 999),
        (IntentionRefused(2, 5),),
    ),
    Case(
        "commit that would overflow the record is refused",
        replace(FULL, usable=USABLE_MAX_UJ, phase=HO, held_tx=6, held_amount=A, deadline=9),
        Commit(2, 6, 4),
        replace(FULL, usable=USABLE_MAX_UJ, phase=HO, held_tx=6, held_amount=A, deadline=9),
        (IntentionRefused(2, 6),),
    ),
]
IGNORED = {
    (ID, StatusRequest),
    (HO, StatusRequest),
    (ID, FinalAck),
    (HO, FinalAck),
    (ID, CommandTimeout),
    (ID, Admit),
    (HO, Admit),
    *((JO, e) for e in (Commit, Abort, ReturnAck, StatusRequest, FinalAck)),
    (JO, CommandTimeout),
}
REFUSED = {(JO, Spend), (JO, GiveBack)}  # otherwise guarded by energy, not by phase
STATES = {ID: FRESH, HO: HOLDING, JO: JOINING}
EVENTS = {
    StatusRequest: StatusRequest(2, 6),
    FinalAck: FinalAck(2, 6),
    CommandTimeout: COMMAND_TIMEOUT,
    Admit: Admit(2, 0xBEEF, 40, 7),
    Intention: intention(6),
    Commit: Commit(2, 6, 4),
    Abort: Abort(2, 6, 4),
    ReturnAck: ReturnAck(2, 0),
    Spend: Spend(1000),
    GiveBack: GiveBack(1000),
}
