"""Pieces both variants share: building wire messages from states, resolving, committing."""

from __future__ import annotations

from canergy.core.actions import Action, ClientCommitted, Resolved, Send
from canergy.core.frozen import evolve
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.timing import Timing
from canergy.messages import (
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
)
from canergy.seqnum import wrap

Actions = tuple[Action, ...]
SessionStep = tuple[Session, Actions, int]
"""New session, actions, and energy (µJ) to credit to the supervisor's usable budget."""
ClientStep = tuple[ClientState, Actions]
NO_ACTIONS: Actions = ()


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


class SupervisorBase:
    """Starting a transaction and sending the decision are the same in every variant."""

    @staticmethod
    def begin(t: Timing, s: Session, amount: int, now: int) -> tuple[Session, Actions]:
        return start_intention(t, s, s.tx + 1, amount, now)

    @staticmethod
    def decide(t: Timing, s: Session, decision: Decision, now: int) -> SessionStep:
        s, actions = send_decision(t, s, decision, now)
        return s, actions, 0


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
    return done, (Resolved(s.node, s.tx, outcome, amount), *extra), credit


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


def spend(c: ClientState, amount: int) -> ClientState:
    """The actuator used ``amount`` µJ of the usable budget (same in every variant)."""
    return evolve(c, usable=c.usable - amount, spent=c.spent + amount)


def start_return(t: Timing, c: ClientState, amount: int, now: int) -> ClientStep:
    """Debit the usable budget and send RETURN with the next sequence number."""
    c = evolve(
        c,
        usable=c.usable - amount,
        return_seq=c.return_seq + 1,
        return_pending=amount,
        return_deadline=now + t.return_retry_us,
    )
    return c, (Send(return_of(c)),)
