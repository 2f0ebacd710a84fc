"""The hardened rules (H1): one id per reservation, delivered count Gs, persistent client record.

Each rule closes a hazard of the paper's protocol (see ``docs/protocol.md``):
identical re-sends under one ``tx`` (a), no client TimeoutN and a persistent last resolved ``tx``
(b, d, e), numbered and acknowledged returns (c), a write-off that the client is paid back through
Gs, and both sides ignoring any response for another transaction.
"""

from __future__ import annotations

from canergy.core.actions import (
    Acknowledged,
    ClientAborted,
    Credited,
    ReturnAcknowledged,
    ReturnCredited,
)
from canergy.core.actions import Send as SendAction
from canergy.core.common import (
    NO_ACTIONS,
    ClientStep,
    SessionStep,
    SupervisorBase,
    command_of,
    commit_into,
    intention_of,
    reply_for,
    resolve,
    return_of,
    start_return,
)
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
    Ack,
    Commit,
    Committed,
    Intention,
    Return,
    ReturnAck,
    ToClient,
    ToSupervisor,
)
from canergy.seqnum import unwrap

_OPEN = (Phase.WAIT_ACK, Phase.WAIT_CONFIRM)


class HardenedSupervisor(SupervisorBase):
    """Supervisor rules for one node's session."""

    @staticmethod
    def receive(t: Timing, s: Session, msg: ToSupervisor, now: int) -> SessionStep:
        if isinstance(msg, Return):
            return _credit_return(s, msg)
        if s.phase is Phase.IDLE or unwrap(msg.tx, s.tx, TX_BITS) != s.tx:
            return s, NO_ACTIONS, 0  # a response for another transaction: ignore
        if isinstance(msg, Ack):
            if s.phase is not Phase.WAIT_ACK:
                return s, NO_ACTIONS, 0
            return evolve(s, phase=Phase.ACKED, deadline=None), (Acknowledged(s.node, s.tx),), 0
        if isinstance(msg, Committed):
            return resolve(s, Outcome.COMMITTED)
        if isinstance(msg, Aborted) and s.decision is Decision.ABORT:
            return resolve(s, Outcome.ABORTED)  # the only way from Ts back to Us
        return s, NO_ACTIONS, 0

    @staticmethod
    def timer(t: Timing, s: Session, now: int) -> SessionStep:
        if s.deadline is None or s.deadline > now or s.phase not in _OPEN:
            return s, NO_ACTIONS, 0
        if s.tries > t.retries:
            return resolve(s, Outcome.WRITTEN_OFF)  # passivity timeout: Gs += Ts
        msg = intention_of(s) if s.phase is Phase.WAIT_ACK else command_of(s)
        s = evolve(s, tries=s.tries + 1, deadline=now + t.response_timeout_us)
        return s, (SendAction(msg),), 0

    @staticmethod
    def power_loss(s: Session, now: int) -> Session:
        """Restart from the persistent record; open transactions re-send at once.

        ``ACKED`` is not persisted (the intention is simply re-sent and re-acknowledged).
        """
        phase = Phase.WAIT_ACK if s.phase is Phase.ACKED else s.phase
        return evolve(s, phase=phase, tries=0, deadline=now if phase in _OPEN else None)

    @staticmethod
    def persistent(s: Session) -> tuple[object, ...]:
        phase = Phase.WAIT_ACK if s.phase is Phase.ACKED else s.phase
        return (phase, s.tx, s.reserved, s.delivered, s.decision, s.returns_credited)


def _credit_return(s: Session, msg: Return) -> SessionStep:
    """Credit only the next return number; re-acknowledge old ones; ignore the rest."""
    seq = unwrap(msg.seq, s.returns_credited, SEQ_BITS)
    ack = (SendAction(ReturnAck(s.node, msg.seq)),)
    if seq == s.returns_credited + 1:
        amount = msg.amount_mj * QUANTUM_UJ
        s = evolve(s, returns_credited=seq, returned=s.returned + amount)
        return s, (ReturnCredited(s.node, seq, amount), *ack), amount
    if seq <= s.returns_credited:
        return s, ack, 0
    return s, NO_ACTIONS, 0


class HardenedClient:
    """Client rules; every change to the persistent fields is persisted before the reply."""

    @staticmethod
    def receive(t: Timing, c: ClientState, msg: ToClient, now: int) -> ClientStep:
        if isinstance(msg, Intention):
            return _on_intention(t, c, msg, now)
        if isinstance(msg, Commit | Abort):
            return _on_command(c, msg)
        if isinstance(msg, ReturnAck):
            seq = unwrap(msg.seq, c.return_seq, SEQ_BITS)
            if seq == c.return_seq and c.return_pending:
                c = evolve(c, return_pending=0, return_deadline=None)
                return c, (ReturnAcknowledged(c.node, seq),)
        return c, NO_ACTIONS

    @staticmethod
    def command_timer(t: Timing, c: ClientState, now: int) -> ClientStep:
        """No command for the held intention: commit it (safe: its id never changes)."""
        if not c.held_tx or c.deadline is None or c.deadline > now:
            return c, NO_ACTIONS
        tx, amount = c.held_tx, c.held_amount
        c, note = commit_into(c, tx, amount, by_timeout=True)
        c = _resolved(c, tx, Outcome.COMMITTED)
        return c, (note, *reply_for(c, tx, Outcome.COMMITTED))

    @staticmethod
    def return_timer(t: Timing, c: ClientState, now: int) -> ClientStep:
        if not c.return_pending or c.return_deadline is None or c.return_deadline > now:
            return c, NO_ACTIONS
        c = evolve(c, return_deadline=now + t.return_retry_us)
        return c, (SendAction(return_of(c)),)

    @staticmethod
    def give_back(t: Timing, c: ClientState, amount: int, now: int) -> ClientStep:
        return start_return(t, c, amount, now)

    @staticmethod
    def can_give_back(c: ClientState) -> bool:
        return c.return_pending == 0

    @staticmethod
    def power_loss(c: ClientState, now: int) -> ClientState:
        """Volatile hold lost; a pending return is re-sent at once."""
        return evolve(
            c,
            held_tx=0,
            held_amount=0,
            deadline=None,
            return_deadline=now if c.return_pending else None,
        )

    @staticmethod
    def persistent(c: ClientState) -> tuple[object, ...]:
        return (
            c.usable,
            c.credited,
            c.spent,
            c.last_tx,
            c.outcome,
            c.return_seq,
            c.return_pending,
        )


def _resolved(c: ClientState, tx: int, outcome: Outcome) -> ClientState:
    return evolve(c, last_tx=tx, outcome=outcome, held_tx=0, held_amount=0, deadline=None)


def _on_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
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
            c = evolve(c, held_tx=0, held_amount=0, deadline=None)
    if tx > c.last_tx:
        if c.held_tx != tx:
            c = evolve(
                c,
                held_tx=tx,
                held_amount=msg.amount_mj * QUANTUM_UJ,
                deadline=now + t.command_timeout_us,
            )
        return c, (*notes, SendAction(Ack(c.node, msg.tx)))
    if tx == c.last_tx:
        return c, (*notes, *reply_for(c, tx, c.outcome))
    return c, notes


def _on_command(c: ClientState, msg: Commit | Abort) -> ClientStep:
    tx = unwrap(msg.tx, c.last_tx, TX_BITS)
    if tx == c.last_tx:
        return c, reply_for(c, tx, c.outcome)  # a late ABORT after a commit is answered COMMITTED
    if tx < c.last_tx:
        return c, NO_ACTIONS
    if isinstance(msg, Commit):
        c, note = commit_into(c, tx, msg.amount_mj * QUANTUM_UJ, by_timeout=False)
        c = _resolved(c, tx, Outcome.COMMITTED)
        return c, (note, *reply_for(c, tx, Outcome.COMMITTED))
    c = _resolved(c, tx, Outcome.ABORTED)
    return c, (ClientAborted(c.node, tx), *reply_for(c, tx, Outcome.ABORTED))


__all__ = ["HardenedClient", "HardenedSupervisor"]
