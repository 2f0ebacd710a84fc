"""The paper's two strawmen (Figs. 8 and 9) as rule sets for the core's wrappers.

Both send an INTENTION that the client books at once (every copy it receives) and acknowledges.

- ``optimistic``: the supervisor counts the energy as delivered the moment it sends it; an
  unanswered intention is simply given up. Lost frames dissipate energy.
- ``pessimistic``: the supervisor reserves the energy and, when no ACK comes back in time, puts it
  back in its usable budget, although the client may well have booked it. That creates energy.

Returns are credited for every RETURN frame that arrives and never acknowledged. These are not
protocols anyone should use; they exist to be compared against.
"""

from __future__ import annotations

from canergy.core.actions import Resolved, Send
from canergy.core.common import check_amount, spend, wire_tx
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import Begin, GiveBack, PowerLoss, ResponseTimeout, Spend
from canergy.core.state import ClientState, Outcome, Phase, Session
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.table import ANY, STAY, ClientTable, SupervisorTable, cell
from canergy.core.timing import Timing
from canergy.core.variants import Variant
from canergy.frozen import evolve
from canergy.messages import QUANTUM_UJ, SEQ_BITS, Ack, Intention, Return
from canergy.seqnum import unwrap, wrap

IDLE, WAIT_ACK = Phase.IDLE, Phase.WAIT_ACK


def credit_every_return(t: Timing, s: Session, msg: Return, now: int) -> SessionStep:
    """RETURN(q, x): Us += x for every copy."""
    amount = msg.amount_mj * QUANTUM_UJ
    seq = max(s.returns_credited, unwrap(msg.seq, s.returns_credited, SEQ_BITS))
    return SessionStep(evolve(s, returns_credited=seq, returned=s.returned + amount), (), amount)


def reset_session(t: Timing, s: Session, event: PowerLoss, now: int) -> SessionStep:
    """Forget the open intention."""
    return SessionStep(evolve(s, phase=IDLE, reserved=0, deadline=None))


def naive_record(s: Session) -> tuple[object, ...]:
    """Ids, the delivered count and the returns credited persist."""
    return (s.tx, s.delivered, s.returns_credited)


def naive_supervisor(pessimistic: bool) -> SupervisorTable:
    """One intention per transaction, never re-sent, never decided on."""

    def send_intention(t: Timing, s: Session, event: Begin, now: int) -> SessionStep:
        """Us -= a; send one INTENTION (optimistic: a counts as delivered at once)."""
        check_amount(event.amount)
        tx, amount = s.tx + 1, event.amount
        msg = Intention(s.node, wire_tx(tx), amount // QUANTUM_UJ, 0)
        if pessimistic:
            s = evolve(s, tx=tx, phase=WAIT_ACK, reserved=amount)
        else:  # gone for good the moment it is sent
            s = evolve(s, tx=tx, phase=WAIT_ACK, delivered=s.delivered + amount)
        s = evolve(s, deadline=now + t.response_timeout_us, tries=1)
        return SessionStep(s, (Send(msg),), -amount)

    def on_ack(t: Timing, s: Session, msg: Ack, now: int) -> SessionStep:
        """ACK(tx): the transaction counts as committed."""
        if msg.tx != wire_tx(s.tx):
            return SessionStep(s)
        amount = s.reserved  # 0 when optimistic: it counted as delivered on sending
        done = evolve(
            s,
            phase=IDLE,
            reserved=0,
            delivered=s.delivered + (s.reserved if pessimistic else 0),
            deadline=None,
        )
        return SessionStep(done, (Resolved(s.node, s.tx, Outcome.COMMITTED, amount),))

    def give_up(t: Timing, s: Session, event: ResponseTimeout, now: int) -> SessionStep:
        """No ACK: pessimistic puts Ts back into Us ("it did not arrive"); optimistic gives up."""
        done = evolve(s, phase=IDLE, reserved=0, deadline=None)
        if pessimistic:
            return SessionStep(
                done, (Resolved(s.node, s.tx, Outcome.ABORTED, s.reserved),), s.reserved
            )
        return SessionStep(done, (Resolved(s.node, s.tx, Outcome.WRITTEN_OFF, 0),))

    return SupervisorTable(
        "pessimistic" if pessimistic else "optimistic",
        (IDLE, WAIT_ACK),
        [
            cell(IDLE, Begin, send_intention, to=WAIT_ACK),
            cell(WAIT_ACK, Ack, on_ack, to=(IDLE, STAY)),
            cell(ANY, Return, credit_every_return),
            cell(WAIT_ACK, ResponseTimeout, give_up, to=IDLE),
            cell(ANY, PowerLoss, reset_session, to=IDLE),
        ],
        naive_record,
    )


def book_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """INTENTION(k, a): Uc += a for every copy; send ACK(k)."""
    amount = msg.amount_mj * QUANTUM_UJ
    c = evolve(c, usable=c.usable + amount, credited=c.credited + amount, last_tx=msg.tx)
    return ClientStep(c, (Send(Ack(c.node, msg.tx)),))


def send_return(t: Timing, c: ClientState, event: GiveBack, now: int) -> ClientStep:
    """Uc -= x; send RETURN(q, x) once."""
    check_amount(event.amount)
    if event.amount > c.usable:
        raise LocalProtocolError(f"cannot return {event.amount} µJ of {c.usable} µJ")
    seq = c.return_seq + 1
    c = evolve(c, usable=c.usable - event.amount, return_seq=seq, return_pending=event.amount)
    return ClientStep(c, (Send(Return(c.node, wrap(seq, SEQ_BITS), event.amount // QUANTUM_UJ)),))


def naive_client_record(c: ClientState) -> tuple[object, ...]:
    """Everything the naive client books persists."""
    return (c.usable, c.credited, c.spent, c.return_seq)


def always(c: ClientState) -> bool:
    """Returns are fire-and-forget: always."""
    return True


NAIVE_CLIENT = ClientTable(
    "naive",
    (IDLE,),
    [
        cell(IDLE, Intention, book_intention),
        cell(IDLE, Spend, spend),
        cell(IDLE, GiveBack, send_return),
    ],
    naive_client_record,
    always,
)

NAIVE: dict[str, Variant] = {
    "optimistic": Variant("optimistic", naive_supervisor(False), NAIVE_CLIENT),
    "pessimistic": Variant("pessimistic", naive_supervisor(True), NAIVE_CLIENT),
}
