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
    NO_ACTIONS,
    ClientStep,
    SessionStep,
    SupervisorBase,
    commit_into,
    reply_for,
    resolve,
    start_intention,
    start_return,
    wire_tx,
)
from canergy.core.frozen import evolve
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.timing import Timing
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
    ToClient,
    ToSupervisor,
)
from canergy.seqnum import unwrap

_AWAITING_REPLY = (Phase.WAIT_CONFIRM, Phase.WAIT_STATUS)


class PaperSupervisor(SupervisorBase):
    """Fig. 3, per node."""

    @staticmethod
    def receive(t: Timing, s: Session, msg: ToSupervisor, now: int) -> SessionStep:
        if isinstance(msg, Return):  # not part of the protocol: credit whatever arrives
            amount = msg.amount_mj * QUANTUM_UJ
            seq = max(s.returns_credited, unwrap(msg.seq, s.returns_credited, SEQ_BITS))
            s = evolve(s, returns_credited=seq, returned=s.returned + amount)
            return s, (ReturnCredited(s.node, seq, amount),), amount
        same_tx = msg.tx == wire_tx(s.tx)
        if isinstance(msg, Ack) and s.phase is Phase.WAIT_ACK:
            if same_tx:
                return (
                    evolve(s, phase=Phase.ACKED, deadline=None),
                    (Acknowledged(s.node, s.tx),),
                    0,
                )
            s, actions = start_intention(t, s, s.tx + 1, s.reserved, now)  # incorrect ACK
            return s, actions, 0
        if s.phase in _AWAITING_REPLY and same_tx:
            final = (Send(FinalAck(s.node, wire_tx(s.tx))),)
            if isinstance(msg, Committed):
                return resolve(s, Outcome.COMMITTED, final)
            if isinstance(msg, Aborted):
                return resolve(s, Outcome.ABORTED, final)
        return s, NO_ACTIONS, 0

    @staticmethod
    def timer(t: Timing, s: Session, now: int) -> SessionStep:
        if s.deadline is None or s.deadline > now:
            return s, NO_ACTIONS, 0
        if s.phase is Phase.WAIT_ACK:  # define a new intention for the same reservation
            s, actions = start_intention(t, s, s.tx + 1, s.reserved, now)
            return s, actions, 0
        if s.phase in _AWAITING_REPLY:
            asked = s.tries if s.phase is Phase.WAIT_STATUS else 0
            if asked >= max(t.retries, 1):  # passivity timeout: assume committed
                return resolve(s, Outcome.WRITTEN_OFF, (Send(FinalAck(s.node, wire_tx(s.tx))),))
            s = evolve(
                s, phase=Phase.WAIT_STATUS, tries=asked + 1, deadline=now + t.response_timeout_us
            )
            return s, (Send(StatusRequest(s.node, wire_tx(s.tx))),), 0
        return s, NO_ACTIONS, 0

    @staticmethod
    def power_loss(s: Session, now: int) -> Session:
        """Only Us survives: the transaction budget and the ids are volatile."""
        return evolve(
            s,
            phase=Phase.IDLE,
            tx=0,
            reserved=0,
            delivered=s.delivered + s.reserved,
            decision=Decision.NONE,
            tries=0,
            deadline=None,
        )

    @staticmethod
    def persistent(s: Session) -> tuple[object, ...]:
        return ()


class PaperClient:
    """Fig. 4."""

    @staticmethod
    def receive(t: Timing, c: ClientState, msg: ToClient, now: int) -> ClientStep:
        if isinstance(msg, Intention):
            return _on_intention(t, c, msg, now)
        if c.held_tx != msg_tx(msg):
            return c, NO_ACTIONS
        if c.phase is Phase.AWAIT_COMMAND and isinstance(msg, Commit):
            c, note = commit_into(c, c.held_tx, c.held_amount, by_timeout=False)
            c = _await_supervisor(t, c, Outcome.COMMITTED, False, now)
            return c, (note, *reply_for(c, c.held_tx, Outcome.COMMITTED))
        if c.phase is Phase.AWAIT_COMMAND and isinstance(msg, Abort):
            c = _await_supervisor(t, c, Outcome.ABORTED, False, now)
            return c, (ClientAborted(c.node, c.held_tx), *reply_for(c, c.held_tx, Outcome.ABORTED))
        if c.phase is Phase.AWAIT_SUPERVISOR and isinstance(msg, StatusRequest):
            c = evolve(c, deadline=now + t.quiet_timeout_us)
            return c, reply_for(c, c.held_tx, c.outcome)
        if c.phase is Phase.AWAIT_SUPERVISOR and isinstance(msg, FinalAck):
            return _forget(c), NO_ACTIONS
        return c, NO_ACTIONS

    @staticmethod
    def command_timer(t: Timing, c: ClientState, now: int) -> ClientStep:
        if c.deadline is None or c.deadline > now:
            return c, NO_ACTIONS
        if c.phase is Phase.AWAIT_COMMAND:  # timeout-commit
            c, note = commit_into(c, c.held_tx, c.held_amount, by_timeout=True)
            c = _await_supervisor(t, c, Outcome.COMMITTED, True, now)
            return c, (note, *reply_for(c, c.held_tx, Outcome.COMMITTED))
        return _forget(c), NO_ACTIONS  # TimeoutN: assume the supervisor knows

    @staticmethod
    def return_timer(t: Timing, c: ClientState, now: int) -> ClientStep:
        return c, NO_ACTIONS  # returns are sent once

    @staticmethod
    def give_back(t: Timing, c: ClientState, amount: int, now: int) -> ClientStep:
        c, actions = start_return(t, c, amount, now)
        return evolve(c, return_deadline=None), actions

    @staticmethod
    def can_give_back(c: ClientState) -> bool:
        return True

    @staticmethod
    def power_loss(c: ClientState, now: int) -> ClientState:
        """Only the usable budget (and the observer's counters) survive."""
        return evolve(
            c,
            last_tx=0,
            outcome=Outcome.NONE,
            held_tx=0,
            held_amount=0,
            phase=Phase.IDLE,
            timeout_commit=False,
            deadline=None,
            return_deadline=None,
        )

    @staticmethod
    def persistent(c: ClientState) -> tuple[object, ...]:
        return (c.usable, c.spent)


def msg_tx(msg: ToClient) -> int:
    return getattr(msg, "tx", -1)


def _await_supervisor(
    t: Timing, c: ClientState, outcome: Outcome, by_timeout: bool, now: int
) -> ClientState:
    return evolve(
        c,
        phase=Phase.AWAIT_SUPERVISOR,
        outcome=outcome,
        timeout_commit=by_timeout,
        deadline=now + t.quiet_timeout_us,
    )


def _forget(c: ClientState) -> ClientState:
    return evolve(
        c,
        phase=Phase.IDLE,
        held_tx=0,
        held_amount=0,
        outcome=Outcome.NONE,
        timeout_commit=False,
        deadline=None,
    )


def _on_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    if c.phase is not Phase.IDLE and msg.tx == c.held_tx:
        if c.phase is Phase.AWAIT_COMMAND:
            return c, (Send(Ack(c.node, msg.tx)),)
        return c, NO_ACTIONS
    notes: tuple[RolledBack, ...] = ()
    if c.phase is Phase.AWAIT_SUPERVISOR and c.timeout_commit:  # "Roll back?"
        removed = min(c.held_amount, c.usable)
        notes = (RolledBack(c.node, c.held_tx, removed),)
        c = evolve(c, usable=c.usable - removed, credited=c.credited - removed)
    c = evolve(
        c,
        phase=Phase.AWAIT_COMMAND,
        held_tx=msg.tx,
        held_amount=msg.amount_mj * QUANTUM_UJ,
        outcome=Outcome.NONE,
        timeout_commit=False,
        deadline=now + t.command_timeout_us,
    )
    return c, (*notes, Send(Ack(c.node, msg.tx)))


__all__ = ["PaperClient", "PaperSupervisor"]
