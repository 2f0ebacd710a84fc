"""The hardened rules (H1): one id per reservation, delivered count Gs, persistent client record.

Each rule closes a hazard of the paper's protocol (see ``docs/protocol.md``):
identical re-sends under one ``tx`` (a), no client TimeoutN and a persistent last resolved ``tx``
(b, d, e), numbered and acknowledged returns (c), a write-off that the client is paid back through
Gs, and both sides ignoring any response for another transaction.
"""

from __future__ import annotations

from canergy.core.actions import (
    Acknowledged,
    Admitted,
    ClientAborted,
    Credited,
    IntentionRefused,
    ReturnAcknowledged,
    ReturnCredited,
    Send,
)
from canergy.core.common import (
    at_end,
    begin,
    command_of,
    commit_into,
    decide,
    intention_of,
    reply_for,
    resolve,
    return_of,
    spend,
    start_return,
    wire_tx,
)
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import (
    RETURN_TIMEOUT,
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    PowerLoss,
    ResponseTimeout,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.table import ANY, STAY, ClientTable, SupervisorTable, cell
from canergy.core.timing import Timing
from canergy.frozen import evolve
from canergy.messages import (
    COUNTER_END,
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    USABLE_MAX_UJ,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Intention,
    Join,
    Return,
    ReturnAck,
)
from canergy.seqnum import unwrap, wrap

IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM = Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM
HOLDING, JOINING = Phase.AWAIT_COMMAND, Phase.JOINING

# -- supervisor, per node --------------------------------------------------------------------


def _other_tx(s: Session, tx: int) -> bool:
    return unwrap(tx, s.tx, TX_BITS) != s.tx


def on_ack(t: Timing, s: Session, msg: Ack, now: int) -> SessionStep:
    """ACK(tx): report ``Acknowledged`` (another tx: ignore)."""
    if _other_tx(s, msg.tx):
        return SessionStep(s)
    return SessionStep(evolve(s, phase=ACKED, deadline=None), (Acknowledged(s.node, s.tx),))


def on_committed(t: Timing, s: Session, msg: Committed, now: int) -> SessionStep:
    """COMMITTED(tx): Gs += Ts, Ts = 0 (another tx: ignore)."""
    if _other_tx(s, msg.tx):
        return SessionStep(s)
    return resolve(s, Outcome.COMMITTED)


def on_aborted(t: Timing, s: Session, msg: Aborted, now: int) -> SessionStep:
    """ABORTED(tx) after an abort decision: Us += Ts, Ts = 0 (the only way back to Us)."""
    if _other_tx(s, msg.tx) or s.decision is not Decision.ABORT:
        return SessionStep(s)
    return resolve(s, Outcome.ABORTED)


def credit_return(t: Timing, s: Session, msg: Return, now: int) -> SessionStep:
    """RETURN(q, x): credit and ack the next q (not at the end); re-ack an old q; ignore beyond.

    The end: a next number at ``COUNTER_END`` is ignored too (neither credited nor acked)."""
    seq = unwrap(msg.seq, s.returns_credited, SEQ_BITS)
    ack = (Send(ReturnAck(s.node, msg.seq)),)
    if seq == s.returns_credited + 1 and not at_end(s.returns_credited):
        amount = msg.amount_mj * QUANTUM_UJ
        s = evolve(s, returns_credited=seq, returned=s.returned + amount)
        return SessionStep(s, (ReturnCredited(s.node, seq, amount), *ack), amount)
    if seq <= s.returns_credited:
        return SessionStep(s, ack)
    return SessionStep(s)


def resend_or_write_off(t: Timing, s: Session, event: ResponseTimeout, now: int) -> SessionStep:
    """Re-send the identical frame; after N re-sends write off: Gs += Ts, Ts = 0."""
    if s.deadline is None or s.deadline > now:
        return SessionStep(s)
    if s.tries > t.retries:
        return resolve(s, Outcome.WRITTEN_OFF)  # passivity timeout
    msg = intention_of(s) if s.phase is WAIT_ACK else command_of(s)
    s = evolve(s, tries=s.tries + 1, deadline=now + t.response_timeout_us)
    return SessionStep(s, (Send(msg),))


def admit(t: Timing, s: Session, msg: Join, now: int) -> SessionStep:
    """JOIN(n) from a node without books: write off what is open; send ADMIT(n, tx, q).

    The wire carries the counters' low 16 bits; both counters first move up to the same high
    part (never back), which authenticated mode sends in the ADMIT's FV, so that a node
    admitted past transaction 65,535 starts from the supervisor's full counters."""
    step = write_off_and_lift(s)
    s = step.session
    answer = Admit(s.node, msg.nonce, wire_tx(s.tx), wrap(s.returns_credited, SEQ_BITS))
    admitted = Admitted(s.node, s.tx, s.returns_credited)
    return SessionStep(s, (*step.actions, admitted, Send(answer)))


def write_off_and_lift(s: Session) -> SessionStep:
    """Write off the open transaction (the node may have committed it before it lost its books)
    and move both counters up to the same high part above their wire bits (never back)."""
    step = SessionStep(s)
    if s.phase is not IDLE:
        step = resolve(s, Outcome.WRITTEN_OFF)
    s = step.session
    high = max(s.tx >> TX_BITS, s.returns_credited >> SEQ_BITS)
    s = evolve(
        s,
        tx=high << TX_BITS | wire_tx(s.tx),
        returns_credited=high << SEQ_BITS | wrap(s.returns_credited, SEQ_BITS),
    )
    return SessionStep(s, step.actions, step.credit)


def restart_session(t: Timing, s: Session, event: PowerLoss, now: int) -> SessionStep:
    """Keep the record; ACKED (not persisted) falls back to WAIT_ACK; open ones re-send at once."""
    phase = WAIT_ACK if s.phase is ACKED else s.phase
    open_ = phase in (WAIT_ACK, WAIT_CONFIRM)
    return SessionStep(evolve(s, phase=phase, tries=0, deadline=now if open_ else None))


def supervisor_record(s: Session) -> tuple[object, ...]:
    """What the supervisor persists for a node (ACKED is stored as WAIT_ACK)."""
    phase = WAIT_ACK if s.phase is ACKED else s.phase
    return (phase, s.tx, s.reserved, s.delivered, s.decision, s.returns_credited)


SUPERVISOR = SupervisorTable(
    "hardened",
    (IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM),
    [
        cell(IDLE, Begin, begin, to=WAIT_ACK),
        cell(ACKED, Decide, decide, to=WAIT_CONFIRM),
        cell(WAIT_ACK, Ack, on_ack, to=(ACKED, STAY)),
        cell((WAIT_ACK, ACKED, WAIT_CONFIRM), Committed, on_committed, to=(IDLE, STAY)),
        cell(WAIT_CONFIRM, Aborted, on_aborted, to=(IDLE, STAY)),
        cell(ANY, Return, credit_return),
        cell(ANY, Join, admit, to=(IDLE, STAY)),
        cell((WAIT_ACK, WAIT_CONFIRM), ResponseTimeout, resend_or_write_off, to=(IDLE, STAY)),
        cell(ACKED, PowerLoss, restart_session, to=WAIT_ACK),
        cell((IDLE, WAIT_ACK, WAIT_CONFIRM), PowerLoss, restart_session),
    ],
    supervisor_record,
)

# -- client ----------------------------------------------------------------------------------


def _hold(t: Timing, c: ClientState, tx: int, amount: int, now: int) -> ClientState:
    return evolve(
        c, phase=HOLDING, held_tx=tx, held_amount=amount, deadline=now + t.command_timeout_us
    )


def _drop_hold(c: ClientState) -> ClientState:
    return evolve(c, phase=IDLE, held_tx=0, held_amount=0, deadline=None)


def _resolved(c: ClientState, tx: int, outcome: Outcome) -> ClientState:
    return _drop_hold(evolve(c, last_tx=tx, outcome=outcome))


def on_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """INTENTION(k, a, Gs): pay back Gs > Rc; settle below k; hold and ACK a new k; re-reply.

    Admitted without books: a k below the admission moves nothing, a fresh one sets Rc = Gs.
    Refused (no ACK, nothing changes) when the pay-back and the amount would overflow Uc, and
    ignored when k is new and at or beyond ``COUNTER_END`` (no supervisor sends one).
    """
    if _beyond_end(msg.tx, c):
        return ClientStep(c)
    if c.credited_unknown:
        if unwrap(msg.tx, c.last_tx, TX_BITS) <= c.last_tx:
            return ClientStep(c)  # a frame of the node's earlier life
        c = evolve(c, credited=msg.delivered_mj * QUANTUM_UJ, credited_unknown=False)
    step = _take_intention(t, c, msg, now)
    if step.client.usable + step.client.held_amount > USABLE_MAX_UJ:
        return ClientStep(c, (IntentionRefused(c.node, unwrap(msg.tx, c.last_tx, TX_BITS)),))
    return step


def _beyond_end(wire: int, c: ClientState) -> bool:
    """A transaction ahead of ltx at or beyond ``COUNTER_END``: it would move ltx there."""
    tx = unwrap(wire, c.last_tx, TX_BITS)
    return tx > c.last_tx and tx >= COUNTER_END


def _take_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    notes: tuple[Credited, ...] = ()
    delivered = unwrap(msg.delivered_mj, c.credited // QUANTUM_UJ, DELIVERED_BITS) * QUANTUM_UJ
    if delivered > c.credited:  # pay back what the supervisor wrote off but we never got
        gain = delivered - c.credited
        c = evolve(c, usable=c.usable + gain, credited=delivered)
        notes = (Credited(c.node, gain),)
    tx = unwrap(msg.tx, c.last_tx, TX_BITS)
    if tx - 1 > c.last_tx:  # everything below tx is settled by the supervisor
        c = evolve(c, last_tx=tx - 1, outcome=Outcome.SETTLED)
        if c.held_tx and c.held_tx < tx:
            c = _drop_hold(c)
    if tx > c.last_tx:
        if c.held_tx != tx:
            c = _hold(t, c, tx, msg.amount_mj * QUANTUM_UJ, now)
        return ClientStep(c, (*notes, Send(Ack(c.node, msg.tx))))
    if tx == c.last_tx:
        return ClientStep(c, (*notes, *reply_for(c, tx, c.outcome)))
    return ClientStep(c, notes)


def on_command(t: Timing, c: ClientState, msg: Commit | Abort, now: int) -> ClientStep:
    """COMMIT/ABORT(k, a): resolve a new k (commit: Uc += a, Rc += a); re-reply for ltx."""
    tx = unwrap(msg.tx, c.last_tx, TX_BITS)
    if tx == c.last_tx:
        return ClientStep(c, reply_for(c, tx, c.outcome))  # a late ABORT after a commit: COMMITTED
    if tx < c.last_tx or _beyond_end(msg.tx, c):
        return ClientStep(c)
    if isinstance(msg, Commit):
        if c.usable + msg.amount_mj * QUANTUM_UJ > USABLE_MAX_UJ:  # never acknowledged so
            return ClientStep(c, (IntentionRefused(c.node, tx),))
        c, note = commit_into(c, tx, msg.amount_mj * QUANTUM_UJ, by_timeout=False)
        c = _resolved(c, tx, Outcome.COMMITTED)
        return ClientStep(c, (note, *reply_for(c, tx, Outcome.COMMITTED)))
    c = _resolved(c, tx, Outcome.ABORTED)
    return ClientStep(c, (ClientAborted(c.node, tx), *reply_for(c, tx, Outcome.ABORTED)))


def on_return_ack(t: Timing, c: ClientState, msg: ReturnAck, now: int) -> ClientStep:
    """RETURN_ACK(q) for the pending return: it is done (any other q: ignore)."""
    seq = unwrap(msg.seq, c.return_seq, SEQ_BITS)
    if seq != c.return_seq or not c.return_pending:
        return ClientStep(c)
    c = evolve(c, return_pending=0, return_deadline=None)
    return ClientStep(c, (ReturnAcknowledged(c.node, seq),))


def timeout_commit(t: Timing, c: ClientState, event: CommandTimeout, now: int) -> ClientStep:
    """No command for the held intention: commit it (safe: its id never changes)."""
    if c.deadline is None or c.deadline > now:
        return ClientStep(c)
    tx, amount = c.held_tx, c.held_amount
    c, note = commit_into(c, tx, amount, by_timeout=True)
    c = _resolved(c, tx, Outcome.COMMITTED)
    return ClientStep(c, (note, *reply_for(c, tx, Outcome.COMMITTED)))


def resend_return(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Re-send the pending RETURN under the same number."""
    if not c.return_pending or c.return_deadline is None or c.return_deadline > now:
        return ClientStep(c)
    c = evolve(c, return_deadline=now + t.return_retry_us)
    return ClientStep(c, (Send(return_of(c)),))


def can_give_back(c: ClientState) -> bool:
    """One numbered return at a time, none before the node is admitted, and none numbered at the
    end of the numbering (``COUNTER_END``)."""
    return c.return_pending == 0 and c.phase is not JOINING and not at_end(c.return_seq)


def give_back(t: Timing, c: ClientState, event: GiveBack, now: int) -> ClientStep:
    """Uc -= x, q += 1, persist, send RETURN(q, x); re-sent until RETURN_ACK(q)."""
    if at_end(c.return_seq):
        raise LocalProtocolError(
            f"node {c.node}: return {c.return_seq} is the last below {COUNTER_END:,}: its "
            "books must start again"
        )
    if not can_give_back(c):
        raise LocalProtocolError("a return is still waiting for its acknowledgement")
    return start_return(t, c, event.amount, now)


def restart_client(t: Timing, c: ClientState, event: PowerLoss, now: int) -> ClientStep:
    """Keep the record, lose the held intention; a pending return is re-sent at once."""
    c = evolve(_drop_hold(c), return_deadline=now if c.return_pending else None)
    return ClientStep(c)


def join(t: Timing, c: ClientState, event: BooksLost, now: int) -> ClientStep:
    """No valid record: start blank, send JOIN(n) and re-send it until ADMIT(n) answers."""
    c = evolve(ClientState(c.node), phase=JOINING, nonce=event.nonce, return_deadline=now)
    return resend_join(t, c, RETURN_TIMEOUT, now)


def resend_join(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Re-send JOIN(n) with the same nonce."""
    if c.return_deadline is None or c.return_deadline > now:
        return ClientStep(c)
    c = evolve(c, return_deadline=now + t.return_retry_us)
    return ClientStep(c, (Send(Join(c.node, c.nonce)),))


def join_again(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """An intention before admission: it moves nothing, but JOIN(n) is re-sent at once."""
    return ClientStep(c, (Send(Join(c.node, c.nonce)),))


def rejoin(t: Timing, c: ClientState, event: PowerLoss, now: int) -> ClientStep:
    """Still no record: JOIN again at once (firmware draws a new nonce; keeping it, as here,
    lets more stale ADMITs match, so the model checks the harder case)."""
    return ClientStep(evolve(c, return_deadline=now))


def on_admit(t: Timing, c: ClientState, msg: Admit, now: int) -> ClientStep:
    """ADMIT(n, k, q) for our nonce: ltx = k, returns from q, Uc = 0, Rc from the next intention
    (every frame of the node's earlier life is now at or below its counters)."""
    if msg.nonce != c.nonce:
        return ClientStep(c)  # an answer to another start
    return ClientStep(
        ClientState(
            c.node,
            last_tx=msg.tx,
            outcome=Outcome.SETTLED,
            return_seq=msg.seq,
            credited_unknown=True,
        )
    )


def client_record(c: ClientState) -> tuple[object, ...]:
    """What the client persists (one record, written before the reply that reports it); none
    while JOINING: a blank record on disk would be trusted at the next start."""
    if c.phase is JOINING:
        return ()
    return (
        c.usable,
        c.credited,
        c.spent,
        c.last_tx,
        c.outcome,
        c.return_seq,
        c.return_pending,
        c.credited_unknown,
    )


BOOKED = (IDLE, HOLDING)

CLIENT = ClientTable(
    "hardened",
    (IDLE, HOLDING, JOINING),
    [
        cell(IDLE, Intention, on_intention, to=(HOLDING, STAY)),
        cell(HOLDING, Intention, on_intention),
        cell(BOOKED, Commit, on_command, to=(IDLE, STAY)),
        cell(BOOKED, Abort, on_command, to=(IDLE, STAY)),
        cell(BOOKED, ReturnAck, on_return_ack),
        cell(HOLDING, CommandTimeout, timeout_commit, to=(IDLE, STAY)),
        cell(BOOKED, ReturnTimeout, resend_return),
        cell(BOOKED, Spend, spend),
        cell(BOOKED, GiveBack, give_back),
        cell(BOOKED, PowerLoss, restart_client, to=IDLE),
        cell(ANY, BooksLost, join, to=JOINING),
        cell(JOINING, ReturnTimeout, resend_join),
        cell(JOINING, Intention, join_again),
        cell(JOINING, PowerLoss, rejoin),
        cell(JOINING, Admit, on_admit, to=(IDLE, STAY)),
    ],
    client_record,
    can_give_back,
)

__all__ = ["CLIENT", "SUPERVISOR"]
