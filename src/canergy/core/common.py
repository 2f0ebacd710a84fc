"""Pieces every variant shares: wire messages from states, amounts, resolving, committing, and the
handlers for beginning, deciding and spending that are the same in every rule set."""

from __future__ import annotations

from canergy.core.actions import Action, ClientCommitted, Resolved, Send
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import Begin, BooksLost, Decide, Spend
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.steps import NO_ACTIONS, Actions, ClientStep, SessionStep
from canergy.core.timing import Timing
from canergy.frozen import evolve
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    COUNTER_END,
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    Abort,
    Aborted,
    Commit,
    Committed,
    Intention,
    Return,
    counter_beyond,
)
from canergy.seqnum import unwrap, wrap


def check_amount(amount: int) -> None:
    """A transferable amount: a positive whole number of wire quanta that fits one frame."""
    if amount <= 0 or amount % QUANTUM_UJ or amount > AMOUNT_MAX_MJ * QUANTUM_UJ:
        raise LocalProtocolError(
            f"amount {amount} µJ must be a positive multiple of {QUANTUM_UJ} µJ "
            f"and at most {AMOUNT_MAX_MJ * QUANTUM_UJ} µJ"
        )


def at_end(counter: int) -> bool:
    """``counter`` is at the end of its numbering: the next one would reach ``COUNTER_END``."""
    return counter + 1 >= COUNTER_END


def capped(counter: int) -> int:
    """A counter moved by a start (a void, a SYNC's lift), held below ``COUNTER_BOUND``: above
    ``COUNTER_END`` no number is issued, credited or held, so numbers there only void, and a
    record never leaves the range every loader takes."""
    return min(counter, COUNTER_BOUND - 1)


def check_life(s: Session) -> None:
    """A transaction may begin: the node's transaction number has room below ``COUNTER_END``."""
    if at_end(s.tx):
        raise LocalProtocolError(
            f"node {s.node}: transaction {s.tx} is the last below {COUNTER_END:,} "
            "(2^30 - 2^16, the bound the proof assumes less the admission's room): its books "
            "must start again (a new state file; with --auth keys of a new epoch)"
        )


def check_counters(s: Session) -> None:
    """A loaded record's counters are below ``COUNTER_BOUND`` (ValueError naming the field)."""
    for name, value in (("tx", s.tx), ("returns_credited", s.returns_credited)):
        if value >= COUNTER_BOUND:
            raise ValueError(f"node {s.node}: {name} {counter_beyond(value)}")


def never_begun(tx16: int, s: Session) -> bool:
    """An answer naming transaction ``tx16`` (the wire's 16 bits) names one the session ``s``
    never began: ahead of its books. No honest node sends it."""
    return unwrap(tx16, s.tx, TX_BITS) > s.tx


def wire_tx(tx: int) -> int:
    return wrap(tx, TX_BITS)


def intention_of(s: Session) -> Intention:
    return Intention(
        s.node,
        wire_tx(s.tx),
        s.reserved // QUANTUM_UJ,
        wrap(s.delivered // QUANTUM_UJ, DELIVERED_BITS),
    )


def command_of(s: Session) -> Commit | Abort:
    cls = Commit if s.decision is Decision.COMMIT else Abort
    return cls(s.node, wire_tx(s.tx), s.reserved // QUANTUM_UJ)


def return_of(c: ClientState) -> Return:
    return Return(c.node, wrap(c.return_seq, SEQ_BITS), c.return_pending // QUANTUM_UJ)


def start_intention(
    t: Timing, s: Session, tx: int, amount: int, now: int
) -> tuple[Session, Actions]:
    """Reserve ``amount`` as transaction ``tx`` and send its intention."""
    s = evolve(
        s,
        phase=Phase.WAIT_ACK,
        tx=tx,
        reserved=amount,
        decision=Decision.NONE,
        tries=1,
        deadline=now + t.response_timeout_us,
    )
    return s, (Send(intention_of(s)),)


def send_decision(t: Timing, s: Session, decision: Decision, now: int) -> tuple[Session, Actions]:
    s = evolve(
        s,
        phase=Phase.WAIT_CONFIRM,
        decision=decision,
        tries=1,
        deadline=now + t.response_timeout_us,
    )
    return s, (Send(command_of(s)),)


def begin(t: Timing, s: Session, event: Begin, now: int) -> SessionStep:
    """Us -= a, Ts = a, tx += 1; send INTENTION(tx, a, Gs); refused at the numbering's end.

    The end: ``COUNTER_END``, one below which no transaction is numbered."""
    check_amount(event.amount)
    check_life(s)
    s, actions = start_intention(t, s, s.tx + 1, event.amount, now)
    return SessionStep(s, actions, -event.amount)


def decide(t: Timing, s: Session, event: Decide, now: int) -> SessionStep:
    """Remember the decision; send COMMIT or ABORT(tx, a)."""
    return SessionStep(*send_decision(t, s, event.decision, now))


def resolve(s: Session, outcome: Outcome, extra: Actions = NO_ACTIONS) -> SessionStep:
    """Close the open transaction: an abort credits Ts back to Us, anything else delivers it."""
    amount = s.reserved
    credit = amount if outcome is Outcome.ABORTED else 0
    delivered = s.delivered if outcome is Outcome.ABORTED else s.delivered + amount
    done = evolve(
        s,
        phase=Phase.IDLE,
        reserved=0,
        delivered=delivered,
        decision=Decision.NONE,
        tries=0,
        deadline=None,
    )
    return SessionStep(done, (Resolved(s.node, s.tx, outcome, amount), *extra), credit)


def commit_into(
    c: ClientState, tx: int, amount: int, by_timeout: bool
) -> tuple[ClientState, Action]:
    """Add a committed amount to the usable budget and to the credited count Rc."""
    c = evolve(c, usable=c.usable + amount, credited=c.credited + amount)
    return c, ClientCommitted(c.node, tx, amount, by_timeout)


def reply_for(c: ClientState, tx: int, outcome: Outcome) -> Actions:
    """The confirmation a client sends for a resolved transaction (none when settled)."""
    if outcome is Outcome.COMMITTED:
        return (Send(Committed(c.node, wire_tx(tx))),)
    if outcome is Outcome.ABORTED:
        return (Send(Aborted(c.node, wire_tx(tx))),)
    return NO_ACTIONS


def start_blank(t: Timing, c: ClientState, event: BooksLost, now: int) -> ClientStep:
    """No valid record: start from zero as a new node would (trusts the next Gs in full)."""
    return ClientStep(ClientState(c.node))


def spend(t: Timing, c: ClientState, event: Spend, now: int) -> ClientStep:
    """Uc -= x, spent += x (the actuator used x; never more than Uc)."""
    if event.amount <= 0 or event.amount > c.usable:
        raise LocalProtocolError(f"cannot spend {event.amount} µJ of {c.usable} µJ")
    return ClientStep(evolve(c, usable=c.usable - event.amount, spent=c.spent + event.amount))


def start_return(t: Timing, c: ClientState, amount: int, now: int) -> ClientStep:
    """Debit the usable budget and send RETURN with the next sequence number."""
    check_amount(amount)
    if amount > c.usable:
        raise LocalProtocolError(f"cannot return {amount} µJ of {c.usable} µJ")
    c = evolve(
        c,
        usable=c.usable - amount,
        return_seq=c.return_seq + 1,
        return_pending=amount,
        return_deadline=now + t.return_retry_us,
    )
    return ClientStep(c, (Send(return_of(c)),))
