"""The paper's rules read literally (Figs. 3 and 4), kept to show where they fail.

Reading chosen where the paper is silent, each the most charitable one: both sides check the id of
every response and command; a timeout or a wrong ACK makes the supervisor define a new intention
(new id, same reservation); the client rolls back a timeout-commit on a new intention by removing
what is left of it; only usable budgets are non-volatile; returns are sent once and credited on
arrival. ``credited``, ``return_seq`` and ``returns_credited`` are kept for the observer's ledger.
"""

from __future__ import annotations

from canergy.core.actions import Acknowledged, ClientAborted, ReturnCredited, RolledBack, Send
from canergy.core.common import (
    begin,
    commit_into,
    decide,
    reply_for,
    resolve,
    spend,
    start_blank,
    start_intention,
    start_return,
    wire_tx,
)
from canergy.core.inputs import (
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    PowerLoss,
    ResponseTimeout,
    Spend,
)
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.table import ANY, STAY, ClientTable, SupervisorTable, cell
from canergy.core.timing import Timing
from canergy.frozen import evolve
from canergy.messages import (
    QUANTUM_UJ,
    SEQ_BITS,
    Abort,
    Aborted,
    Ack,
    Commit,
    Committed,
    FinalAck,
    Intention,
    Return,
    StatusRequest,
)
from canergy.seqnum import unwrap

IDLE, WAIT_ACK, ACKED = Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED
WAIT_CONFIRM, WAIT_STATUS = Phase.WAIT_CONFIRM, Phase.WAIT_STATUS
AWAIT_COMMAND, AWAIT_SUPERVISOR = Phase.AWAIT_COMMAND, Phase.AWAIT_SUPERVISOR

# -- supervisor (Fig. 3), per node -----------------------------------------------------------


def credit_any_return(t: Timing, s: Session, msg: Return, now: int) -> SessionStep:
    """RETURN(q, x): Us += x for every copy that arrives (not part of the paper's protocol)."""
    amount = msg.amount_mj * QUANTUM_UJ
    seq = max(s.returns_credited, unwrap(msg.seq, s.returns_credited, SEQ_BITS))
    s = evolve(s, returns_credited=seq, returned=s.returned + amount)
    return SessionStep(s, (ReturnCredited(s.node, seq, amount),), amount)


def on_ack(t: Timing, s: Session, msg: Ack, now: int) -> SessionStep:
    """ACK(tx): report ``Acknowledged``; a wrong ACK defines a new intention (same Ts)."""
    if msg.tx == wire_tx(s.tx):
        return SessionStep(evolve(s, phase=ACKED, deadline=None), (Acknowledged(s.node, s.tx),))
    return SessionStep(*start_intention(t, s, s.tx + 1, s.reserved, now))


def on_outcome(t: Timing, s: Session, msg: Committed | Aborted, now: int) -> SessionStep:
    """COMMITTED/ABORTED(tx): resolve (aborted: Us += Ts) and send FINAL_ACK(tx)."""
    if msg.tx != wire_tx(s.tx):
        return SessionStep(s)
    final = (Send(FinalAck(s.node, wire_tx(s.tx))),)
    outcome = Outcome.COMMITTED if isinstance(msg, Committed) else Outcome.ABORTED
    return resolve(s, outcome, final)


def redefine_intention(t: Timing, s: Session, event: ResponseTimeout, now: int) -> SessionStep:
    """No ACK in time: define a new intention (new tx) for the same reservation."""
    if s.deadline is None or s.deadline > now:
        return SessionStep(s)
    return SessionStep(*start_intention(t, s, s.tx + 1, s.reserved, now))


def request_status(t: Timing, s: Session, event: ResponseTimeout, now: int) -> SessionStep:
    """No reply in time: send STATUS_REQUEST(tx); after N, passivity timeout (assume committed)."""
    if s.deadline is None or s.deadline > now:
        return SessionStep(s)
    asked = s.tries if s.phase is WAIT_STATUS else 0
    if asked >= max(t.retries, 1):
        return resolve(s, Outcome.WRITTEN_OFF, (Send(FinalAck(s.node, wire_tx(s.tx))),))
    s = evolve(s, phase=WAIT_STATUS, tries=asked + 1, deadline=now + t.response_timeout_us)
    return SessionStep(s, (Send(StatusRequest(s.node, wire_tx(s.tx))),))


def reset_session(t: Timing, s: Session, event: PowerLoss, now: int) -> SessionStep:
    """Only Us survives: Ts is lost (counted as delivered), ids restart."""
    return SessionStep(
        evolve(
            s,
            phase=IDLE,
            tx=0,
            reserved=0,
            delivered=s.delivered + s.reserved,
            decision=Decision.NONE,
            tries=0,
            deadline=None,
        )
    )


def nothing_persisted(s: Session) -> tuple[object, ...]:
    """Per node, the paper's supervisor persists nothing (Us is shared)."""
    return ()


SUPERVISOR = SupervisorTable(
    "paper",
    (IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM, WAIT_STATUS),
    [
        cell(IDLE, Begin, begin, to=WAIT_ACK),
        cell(ACKED, Decide, decide, to=WAIT_CONFIRM),
        cell(WAIT_ACK, Ack, on_ack, to=(ACKED, STAY)),
        cell((WAIT_CONFIRM, WAIT_STATUS), Committed, on_outcome, to=(IDLE, STAY)),
        cell((WAIT_CONFIRM, WAIT_STATUS), Aborted, on_outcome, to=(IDLE, STAY)),
        cell(ANY, Return, credit_any_return),
        cell(WAIT_ACK, ResponseTimeout, redefine_intention),
        cell(WAIT_CONFIRM, ResponseTimeout, request_status, to=(WAIT_STATUS, STAY)),
        cell(WAIT_STATUS, ResponseTimeout, request_status, to=(IDLE, STAY)),
        cell(ANY, PowerLoss, reset_session, to=IDLE),
    ],
    nothing_persisted,
)

# -- client (Fig. 4) -------------------------------------------------------------------------


def _await_supervisor(
    t: Timing, c: ClientState, outcome: Outcome, by_timeout: bool, now: int
) -> ClientState:
    return evolve(
        c,
        phase=AWAIT_SUPERVISOR,
        outcome=outcome,
        timeout_commit=by_timeout,
        deadline=now + t.quiet_timeout_us,
    )


def _forget(c: ClientState) -> ClientState:
    return evolve(
        c,
        phase=IDLE,
        held_tx=0,
        held_amount=0,
        outcome=Outcome.NONE,
        timeout_commit=False,
        deadline=None,
    )


def on_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """INTENTION(k, a): hold and ACK it, rolling back a timeout-commit; re-ACK a held k."""
    if c.phase is not IDLE and msg.tx == c.held_tx:
        if c.phase is AWAIT_COMMAND:
            return ClientStep(c, (Send(Ack(c.node, msg.tx)),))
        return ClientStep(c)
    notes: tuple[RolledBack, ...] = ()
    if c.phase is AWAIT_SUPERVISOR and c.timeout_commit:  # "Roll back?"
        removed = min(c.held_amount, c.usable)
        notes = (RolledBack(c.node, c.held_tx, removed),)
        c = evolve(c, usable=c.usable - removed, credited=c.credited - removed)
    c = evolve(
        c,
        phase=AWAIT_COMMAND,
        held_tx=msg.tx,
        held_amount=msg.amount_mj * QUANTUM_UJ,
        outcome=Outcome.NONE,
        timeout_commit=False,
        deadline=now + t.command_timeout_us,
    )
    return ClientStep(c, (*notes, Send(Ack(c.node, msg.tx))))


def on_commit(t: Timing, c: ClientState, msg: Commit, now: int) -> ClientStep:
    """COMMIT(k) for the held k: Uc += a; send COMMITTED(k)."""
    if msg.tx != c.held_tx:
        return ClientStep(c)
    c, note = commit_into(c, c.held_tx, c.held_amount, by_timeout=False)
    c = _await_supervisor(t, c, Outcome.COMMITTED, False, now)
    return ClientStep(c, (note, *reply_for(c, c.held_tx, Outcome.COMMITTED)))


def on_abort(t: Timing, c: ClientState, msg: Abort, now: int) -> ClientStep:
    """ABORT(k) for the held k: send ABORTED(k)."""
    if msg.tx != c.held_tx:
        return ClientStep(c)
    c = _await_supervisor(t, c, Outcome.ABORTED, False, now)
    return ClientStep(
        c, (ClientAborted(c.node, c.held_tx), *reply_for(c, c.held_tx, Outcome.ABORTED))
    )


def answer_status(t: Timing, c: ClientState, msg: StatusRequest, now: int) -> ClientStep:
    """STATUS_REQUEST(k) for the held k: re-send the outcome, re-arm TimeoutN."""
    if msg.tx != c.held_tx:
        return ClientStep(c)
    c = evolve(c, deadline=now + t.quiet_timeout_us)
    return ClientStep(c, reply_for(c, c.held_tx, c.outcome))


def on_final_ack(t: Timing, c: ClientState, msg: FinalAck, now: int) -> ClientStep:
    """FINAL_ACK(k) for the held k: forget the transaction."""
    if msg.tx != c.held_tx:
        return ClientStep(c)
    return ClientStep(_forget(c))


def timeout_commit(t: Timing, c: ClientState, event: CommandTimeout, now: int) -> ClientStep:
    """No command in time: commit the held intention (timeout-commit)."""
    if c.deadline is None or c.deadline > now:
        return ClientStep(c)
    c, note = commit_into(c, c.held_tx, c.held_amount, by_timeout=True)
    c = _await_supervisor(t, c, Outcome.COMMITTED, True, now)
    return ClientStep(c, (note, *reply_for(c, c.held_tx, Outcome.COMMITTED)))


def timeout_n(t: Timing, c: ClientState, event: CommandTimeout, now: int) -> ClientStep:
    """TimeoutN: no final ACK in time; assume the supervisor knows and forget."""
    if c.deadline is None or c.deadline > now:
        return ClientStep(c)
    return ClientStep(_forget(c))


def can_give_back(c: ClientState) -> bool:
    """Returns are fire-and-forget: always."""
    return True


def give_back(t: Timing, c: ClientState, event: GiveBack, now: int) -> ClientStep:
    """Uc -= x; send RETURN(q, x) once."""
    c, actions = start_return(t, c, event.amount, now)
    return ClientStep(evolve(c, return_deadline=None), actions)


def reset_client(t: Timing, c: ClientState, event: PowerLoss, now: int) -> ClientStep:
    """Only the usable budget (and the observer's counters) survive."""
    return ClientStep(
        evolve(
            c,
            last_tx=0,
            outcome=Outcome.NONE,
            held_tx=0,
            held_amount=0,
            phase=IDLE,
            timeout_commit=False,
            deadline=None,
            return_deadline=None,
        )
    )


def usable_only(c: ClientState) -> tuple[object, ...]:
    """The paper's client persists its usable budget (and spent, for the observer)."""
    return (c.usable, c.spent)


CLIENT = ClientTable(
    "paper",
    (IDLE, AWAIT_COMMAND, AWAIT_SUPERVISOR),
    [
        cell(IDLE, Intention, on_intention, to=AWAIT_COMMAND),
        cell(AWAIT_COMMAND, Intention, on_intention),
        cell(AWAIT_SUPERVISOR, Intention, on_intention, to=(AWAIT_COMMAND, STAY)),
        cell(AWAIT_COMMAND, Commit, on_commit, to=(AWAIT_SUPERVISOR, STAY)),
        cell(AWAIT_COMMAND, Abort, on_abort, to=(AWAIT_SUPERVISOR, STAY)),
        cell(AWAIT_SUPERVISOR, StatusRequest, answer_status),
        cell(AWAIT_SUPERVISOR, FinalAck, on_final_ack, to=(IDLE, STAY)),
        cell(AWAIT_COMMAND, CommandTimeout, timeout_commit, to=(AWAIT_SUPERVISOR, STAY)),
        cell(AWAIT_SUPERVISOR, CommandTimeout, timeout_n, to=(IDLE, STAY)),
        cell(ANY, Spend, spend),
        cell(ANY, GiveBack, give_back),
        cell(ANY, PowerLoss, reset_client, to=IDLE),
        cell(ANY, BooksLost, start_blank, to=IDLE),
    ],
    usable_only,
    can_give_back,
)

__all__ = ["CLIENT", "SUPERVISOR"]
