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
from canergy.core.common import NO_ACTIONS, Actions, ClientStep, SessionStep, wire_tx
from canergy.core.frozen import evolve
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.core.timing import Timing
from canergy.core.variants import Variant
from canergy.messages import QUANTUM_UJ, Ack, Intention, Return, ToClient, ToSupervisor
from canergy.seqnum import unwrap


class _NaiveSupervisor:
    """Sends one intention per transaction, never re-sends, never decides."""

    pessimistic = False

    def begin(self, t: Timing, s: Session, amount: int, now: int) -> tuple[Session, Actions]:
        tx = s.tx + 1
        msg = Intention(s.node, wire_tx(tx), amount // QUANTUM_UJ, 0)
        if self.pessimistic:
            s = evolve(s, tx=tx, phase=Phase.WAIT_ACK, reserved=amount)
        else:  # gone for good the moment it is sent
            s = evolve(s, tx=tx, phase=Phase.WAIT_ACK, delivered=s.delivered + amount)
        return evolve(s, deadline=now + t.response_timeout_us, tries=1), (Send(msg),)

    def decide(self, t: Timing, s: Session, decision: Decision, now: int) -> SessionStep:
        return s, NO_ACTIONS, 0

    def receive(self, t: Timing, s: Session, msg: ToSupervisor, now: int) -> SessionStep:
        if isinstance(msg, Return):  # naive: every copy is credited
            amount = msg.amount_mj * QUANTUM_UJ
            seq = max(s.returns_credited, unwrap(msg.seq, s.returns_credited, 16))
            return evolve(s, returns_credited=seq, returned=s.returned + amount), NO_ACTIONS, amount
        if isinstance(msg, Ack) and s.phase is Phase.WAIT_ACK and msg.tx == wire_tx(s.tx):
            amount = s.reserved  # 0 when optimistic: it counted as delivered on sending
            done = evolve(
                s,
                phase=Phase.IDLE,
                reserved=0,
                delivered=s.delivered + (s.reserved if self.pessimistic else 0),
                deadline=None,
            )
            return done, (Resolved(s.node, s.tx, Outcome.COMMITTED, amount),), 0
        return s, NO_ACTIONS, 0

    def timer(self, t: Timing, s: Session, now: int) -> SessionStep:
        if s.phase is not Phase.WAIT_ACK:
            return evolve(s, deadline=None), NO_ACTIONS, 0
        done = evolve(s, phase=Phase.IDLE, reserved=0, deadline=None)
        if self.pessimistic:  # "it did not arrive": back into the usable budget
            return done, (Resolved(s.node, s.tx, Outcome.ABORTED, s.reserved),), s.reserved
        return done, (Resolved(s.node, s.tx, Outcome.WRITTEN_OFF, 0),), 0

    def power_loss(self, s: Session, now: int) -> Session:
        return evolve(s, phase=Phase.IDLE, reserved=0, deadline=None)

    def persistent(self, s: Session) -> tuple[object, ...]:
        return (s.tx, s.delivered, s.returns_credited)


class OptimisticSupervisor(_NaiveSupervisor):
    pessimistic = False


class PessimisticSupervisor(_NaiveSupervisor):
    pessimistic = True


class NaiveClient:
    """Books every intention copy at once and acknowledges it; returns are fire-and-forget."""

    def receive(self, t: Timing, c: ClientState, msg: ToClient, now: int) -> ClientStep:
        if not isinstance(msg, Intention):
            return c, NO_ACTIONS
        amount = msg.amount_mj * QUANTUM_UJ
        c = evolve(c, usable=c.usable + amount, credited=c.credited + amount, last_tx=msg.tx)
        return c, (Send(Ack(c.node, msg.tx)),)

    def command_timer(self, t: Timing, c: ClientState, now: int) -> ClientStep:
        return evolve(c, deadline=None), NO_ACTIONS

    def return_timer(self, t: Timing, c: ClientState, now: int) -> ClientStep:
        return evolve(c, return_deadline=None), NO_ACTIONS

    def give_back(self, t: Timing, c: ClientState, amount: int, now: int) -> ClientStep:
        seq = c.return_seq + 1
        c = evolve(c, usable=c.usable - amount, return_seq=seq, return_pending=amount)
        return c, (Send(Return(c.node, seq & 0xFFFF, amount // QUANTUM_UJ)),)

    def can_give_back(self, c: ClientState) -> bool:
        return True

    def power_loss(self, c: ClientState, now: int) -> ClientState:
        return c

    def persistent(self, c: ClientState) -> tuple[object, ...]:
        return (c.usable, c.credited, c.spent, c.return_seq)


NAIVE: dict[str, Variant] = {
    "optimistic": Variant("optimistic", OptimisticSupervisor(), NaiveClient()),
    "pessimistic": Variant("pessimistic", PessimisticSupervisor(), NaiveClient()),
}
