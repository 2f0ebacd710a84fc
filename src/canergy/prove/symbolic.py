"""The hardened rules of one supervisor session and its client as z3 terms.

Counters are bit-vectors of their real widths (32 bits held, 16 on the wire, Gs's 24 bits in
mJ), energies are integers in µJ, phases and outcomes small integers (their ``IntEnum`` values).
Each handler takes a state of terms and a message of terms and returns the next state and what
is sent, by the same guards as ``canergy.core.hardened`` (its table's dispatch included: an
event a phase has no cell for leaves the state as it is). Timers are taken as due; deadlines,
retry counts and notes are not modelled (they move no energy).

``tests/test_prove_symbolic.py`` evaluates every handler on concrete states drawn by hypothesis
and compares it with the Python table, field by field: a cell changed in one and not the other
fails there.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, TypeVar

from canergy.core.state import Decision, Outcome, Phase
from canergy.extras import MissingExtra
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    USABLE_MAX_UJ,
    MsgType,
)

try:
    import z3 as z3  # re-exported: the other proof modules take it from here
except ImportError as exc:
    raise MissingExtra("prove", exc) from exc

Term = Any
"""A z3 expression (z3-solver ships no type hints)."""

COUNTER = 32
"""Held counters: tx, last tx, return numbers (the FV's width)."""


def counter(value: int) -> Term:
    return z3.BitVecVal(value, COUNTER)


def at_end(value: Term) -> Term:
    """``core.common.at_end``: the next counter would reach ``COUNTER_END``."""
    return z3.UGE(value, counter(COUNTER_END - 1))


def capped(value: Term) -> Term:
    """``core.common.capped``: a counter a start moved, held below ``COUNTER_BOUND``."""
    top = counter(COUNTER_BOUND - 1)
    return z3.If(z3.ULT(value, top), value, top)


def beyond_end(tx: Term, last: Term) -> Term:
    """``tx`` (widened) is ahead of ``last`` and at or beyond ``COUNTER_END``."""
    return z3.And(tx - last > 0, z3.UGE(tx, counter(COUNTER_END)))


def unwrap(wire: Term, reference: Term, bits: int) -> Term:
    """``canergy.seqnum.unwrap`` on bit-vectors: the value congruent to the ``bits``-wide
    ``wire`` nearest ``reference`` (32 bits)."""
    width = reference.size()
    diff = z3.Extract(bits - 1, 0, z3.ZeroExt(width - wire.size(), wire) - reference)
    return reference + z3.SignExt(width - bits, diff)


def unwrap_int(wire: Term, reference: Term, bits: int) -> Term:
    """``unwrap`` on integers (Gs in mJ against Rc in mJ)."""
    modulus = 1 << bits
    diff = (wire - reference) % modulus
    return reference + z3.If(diff >= modulus // 2, diff - modulus, diff)


def low(value: Term, bits: int) -> Term:
    return z3.Extract(bits - 1, 0, value)


@dataclass(frozen=True)
class Sent:
    """What a step sends: ``present`` says whether it sends at all; ``kind`` is a ``MsgType``
    value term, the fields are terms (unused ones zero)."""

    present: Term
    kind: Term
    a: Term
    b: Term
    c: Term
    d: Term
    """A DEBIT's nonce (16 bits; zero for every other kind)."""

    @staticmethod
    def none() -> Sent:
        zero16 = z3.BitVecVal(0, 16)
        return Sent(z3.BoolVal(False), z3.IntVal(0), zero16, z3.IntVal(0), z3.IntVal(0), zero16)

    @staticmethod
    def of(
        kind: MsgType,
        a: Term,
        b: Term | None = None,
        c: Term | None = None,
        d: Term | None = None,
    ) -> Sent:
        return Sent(
            z3.BoolVal(True),
            z3.IntVal(int(kind)),
            a,
            z3.IntVal(0) if b is None else b,
            z3.IntVal(0) if c is None else c,
            z3.BitVecVal(0, 16) if d is None else d,
        )


R = TypeVar("R", "Client", "Session", "Sent")


def pick(cond: Term, yes: R, no: R) -> R:
    """``If`` over two records of terms of one class (field by field)."""
    return type(yes)(*(z3.If(cond, getattr(yes, f.name), getattr(no, f.name)) for f in fields(yes)))


# -- the client ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Client:
    usable: Term
    credited: Term
    spent: Term
    last_tx: Term
    outcome: Term
    return_seq: Term
    return_pending: Term
    credited_unknown: Term
    held_tx: Term
    held_amount: Term
    phase: Term
    nonce: Term
    pending_draw: Term
    """The pending debit is a draw for the actuator (witnessed rules; hardened: always false)."""


IDLE, HOLDING, JOINING, RESUMING = (
    z3.IntVal(int(p)) for p in (Phase.IDLE, Phase.AWAIT_COMMAND, Phase.JOINING, Phase.RESUMING)
)
COMMITTED, ABORTED, SETTLED = (
    z3.IntVal(int(o)) for o in (Outcome.COMMITTED, Outcome.ABORTED, Outcome.SETTLED)
)


def _drop_hold(c: Client) -> Client:
    return replace(c, phase=IDLE, held_tx=counter(0), held_amount=z3.IntVal(0))


def _reply_for(c: Client, tx: Term, outcome: Term) -> Sent:
    answer = pick(
        outcome == COMMITTED,
        Sent.of(MsgType.COMMITTED, low(tx, TX_BITS)),
        Sent.of(MsgType.ABORTED, low(tx, TX_BITS)),
    )
    return pick(z3.Or(outcome == COMMITTED, outcome == ABORTED), answer, Sent.none())


def _take_intention(
    c: Client, tx16: Term, amount_mj: Term, delivered_mj: Term
) -> tuple[Client, Sent]:
    delivered = unwrap_int(delivered_mj, c.credited / QUANTUM_UJ, DELIVERED_BITS) * QUANTUM_UJ
    gain = delivered > c.credited
    c = replace(
        c,
        usable=z3.If(gain, c.usable + delivered - c.credited, c.usable),
        credited=z3.If(gain, delivered, c.credited),
    )
    tx = unwrap(tx16, c.last_tx, TX_BITS)
    settle = tx - c.last_tx > 1  # signed distance (z3's > on bit-vectors), exact within 2**15
    settled = replace(c, last_tx=tx - 1, outcome=SETTLED)
    drop = z3.And(settled.held_tx != counter(0), z3.ULT(settled.held_tx, tx))
    settled = pick(drop, _drop_hold(settled), settled)
    c = pick(settle, settled, c)
    fresh = tx - c.last_tx > 0
    held = replace(c, phase=HOLDING, held_tx=tx, held_amount=amount_mj * QUANTUM_UJ)
    taken = pick(c.held_tx != tx, held, c)
    same = tx == c.last_tx
    out_state = pick(fresh, taken, c)
    sent = pick(
        fresh,
        Sent.of(MsgType.ACK, tx16),
        pick(same, _reply_for(c, tx, c.outcome), Sent.none()),
    )
    return out_state, sent


def on_intention(c: Client, tx16: Term, amount_mj: Term, delivered_mj: Term) -> tuple[Client, Sent]:
    """INTENTION(k, a, Gs) in every phase (JOINING: JOIN again)."""
    tx = unwrap(tx16, c.last_tx, TX_BITS)
    stale = z3.Or(z3.And(c.credited_unknown, tx - c.last_tx <= 0), beyond_end(tx, c.last_tx))
    known = replace(
        c,
        credited=z3.If(c.credited_unknown, delivered_mj * QUANTUM_UJ, c.credited),
        credited_unknown=z3.BoolVal(False),
    )
    taken, sent = _take_intention(known, tx16, amount_mj, delivered_mj)
    refused = taken.usable + taken.held_amount > USABLE_MAX_UJ
    booked_state = pick(stale, c, pick(refused, known, taken))
    booked_sent = pick(z3.Or(stale, refused), Sent.none(), sent)
    joining = c.phase == JOINING
    return (
        pick(joining, c, booked_state),
        pick(joining, Sent.of(MsgType.JOIN, c.nonce), booked_sent),
    )


def on_command(c: Client, commit: bool, tx16: Term, amount_mj: Term) -> tuple[Client, Sent]:
    """COMMIT or ABORT(k, a) in IDLE and HOLDING (JOINING: ignored)."""
    tx = unwrap(tx16, c.last_tx, TX_BITS)
    ahead = tx - c.last_tx
    amount = amount_mj * QUANTUM_UJ
    if commit:
        resolved = _drop_hold(
            replace(
                c,
                usable=c.usable + amount,
                credited=c.credited + amount,
                last_tx=tx,
                outcome=COMMITTED,
            )
        )
        overflow = c.usable + amount > USABLE_MAX_UJ
        new_state = pick(overflow, c, resolved)
        new_sent = pick(overflow, Sent.none(), Sent.of(MsgType.COMMITTED, low(tx, TX_BITS)))
    else:
        new_state = _drop_hold(replace(c, last_tx=tx, outcome=ABORTED))
        new_sent = Sent.of(MsgType.ABORTED, low(tx, TX_BITS))
    take = z3.And(ahead > 0, z3.Not(beyond_end(tx, c.last_tx)))
    state = pick(take, new_state, c)
    sent = pick(take, new_sent, pick(ahead == 0, _reply_for(c, tx, c.outcome), Sent.none()))
    joining = c.phase == JOINING
    return pick(joining, c, state), pick(joining, Sent.none(), sent)


def on_return_ack(c: Client, seq16: Term) -> tuple[Client, Sent]:
    """RETURN_ACK(q) in IDLE and HOLDING: the pending return is done when q is its number."""
    seq = unwrap(seq16, c.return_seq, SEQ_BITS)
    done = z3.And(seq == c.return_seq, c.return_pending != 0, c.phase != JOINING)
    return pick(done, replace(c, return_pending=z3.IntVal(0)), c), Sent.none()


def on_admit(c: Client, nonce16: Term, tx16: Term, seq16: Term) -> tuple[Client, Sent]:
    """ADMIT(n, k, q) while JOINING, for its nonce: a fresh record at the counters given."""
    zero = z3.IntVal(0)
    admitted = Client(
        usable=zero,
        credited=zero,
        spent=zero,
        last_tx=z3.ZeroExt(COUNTER - TX_BITS, tx16),
        outcome=SETTLED,
        return_seq=z3.ZeroExt(COUNTER - SEQ_BITS, seq16),
        return_pending=zero,
        credited_unknown=z3.BoolVal(True),
        held_tx=counter(0),
        held_amount=zero,
        phase=IDLE,
        nonce=z3.BitVecVal(0, 16),
        pending_draw=z3.BoolVal(False),
    )
    taken = z3.And(c.phase == JOINING, nonce16 == c.nonce)
    return pick(taken, admitted, c), Sent.none()


def timeout_commit(c: Client) -> tuple[Client, Sent]:
    """The command timer of a held intention, due: commit it (HOLDING only)."""
    amount = c.held_amount
    resolved = _drop_hold(
        replace(
            c,
            usable=c.usable + amount,
            credited=c.credited + amount,
            last_tx=c.held_tx,
            outcome=COMMITTED,
        )
    )
    holding = c.phase == HOLDING
    return (
        pick(holding, resolved, c),
        pick(holding, Sent.of(MsgType.COMMITTED, low(c.held_tx, TX_BITS)), Sent.none()),
    )


# -- the supervisor's session ----------------------------------------------------------------------


@dataclass(frozen=True)
class Session:
    phase: Term
    tx: Term
    reserved: Term
    delivered: Term
    decision: Term
    returns_credited: Term
    returned: Term
    resume_nonce: Term
    """The last start answered (witnessed rules; hardened: never moved): its key (17 bits: the
    nonce, and above it whether it was a SYNC's counts), the node's debit number in it and the
    number voided."""
    resume_from: Term
    resume_to: Term
    witness: Term
    """W, the highest transaction the node has shown it persisted (witnessed rules)."""
    sync_nonce: Term
    """The nonce of the supervisor's start, SYNC(n), while it waits (witnessed rules)."""
    join_nonce: Term
    """The last JOIN admitted (witnessed rules; hardened: never moved): its nonce (16 bits) and
    the k and C of its ADMIT (``join_seq`` 0: none), so that a copy gets the same ADMIT."""
    join_tx: Term
    join_seq: Term
    resync: Term
    """The SYNC is a re-sync of this idle session alone (witnessed rules,
    ``witnessed.resync_session``; volatile: a start and a re-sync's counts clear it)."""


S_IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM = (
    z3.IntVal(int(p)) for p in (Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM)
)
SYNCING, SYNC_BOOKS = z3.IntVal(int(Phase.SYNCING)), z3.IntVal(int(Phase.SYNC_BOOKS))
"""A start's phases (witnessed rules): the supervisor's, and the node's answering a SYNC."""
KEY_BITS = 17
"""``Session.resume_nonce``: a nonce and whether it was a SYNC's counts."""
NO_DECISION, ABORT = z3.IntVal(int(Decision.NONE)), z3.IntVal(int(Decision.ABORT))


@dataclass(frozen=True)
class SessionStep:
    session: Session
    sent: Sent
    credit: Term
    """µJ back to (positive) or out of (negative) the usable budget Us."""


def _resolve(s: Session, aborted: Term) -> SessionStep:
    done = replace(
        s,
        phase=S_IDLE,
        reserved=z3.IntVal(0),
        delivered=z3.If(aborted, s.delivered, s.delivered + s.reserved),
        decision=NO_DECISION,
    )
    return SessionStep(done, Sent.none(), z3.If(aborted, s.reserved, 0))


def _unchanged(s: Session) -> SessionStep:
    return SessionStep(s, Sent.none(), z3.IntVal(0))


def _other_tx(s: Session, tx16: Term) -> Term:
    return unwrap(tx16, s.tx, TX_BITS) != s.tx


def choose(cond: Term, yes: SessionStep, no: SessionStep) -> SessionStep:
    return SessionStep(
        pick(cond, yes.session, no.session),
        pick(cond, yes.sent, no.sent),
        z3.If(cond, yes.credit, no.credit),
    )


def on_ack(s: Session, tx16: Term) -> SessionStep:
    """ACK(k) in WAIT_ACK: ACKED (another k, another phase: nothing)."""
    acked = SessionStep(replace(s, phase=ACKED), Sent.none(), z3.IntVal(0))
    return choose(z3.And(s.phase == WAIT_ACK, z3.Not(_other_tx(s, tx16))), acked, _unchanged(s))


def on_committed(s: Session, tx16: Term) -> SessionStep:
    """COMMITTED(k) in any open phase: Gs += Ts."""
    open_ = z3.Or(s.phase == WAIT_ACK, s.phase == ACKED, s.phase == WAIT_CONFIRM)
    return choose(
        z3.And(open_, z3.Not(_other_tx(s, tx16))), _resolve(s, z3.BoolVal(False)), _unchanged(s)
    )


def on_aborted(s: Session, tx16: Term) -> SessionStep:
    """ABORTED(k) in WAIT_CONFIRM after an abort decision: Us += Ts."""
    taken = z3.And(s.phase == WAIT_CONFIRM, z3.Not(_other_tx(s, tx16)), s.decision == ABORT)
    return choose(taken, _resolve(s, z3.BoolVal(True)), _unchanged(s))


def credit_return(s: Session, seq16: Term, amount_mj: Term) -> SessionStep:
    """RETURN(q, x) in any phase: credit the next number, re-acknowledge an old one."""
    seq = unwrap(seq16, s.returns_credited, SEQ_BITS)
    ahead = seq - s.returns_credited
    ack = Sent.of(MsgType.RETURN_ACK, seq16)
    amount = amount_mj * QUANTUM_UJ
    credited = SessionStep(
        replace(s, returns_credited=seq, returned=s.returned + amount), ack, amount
    )
    again = SessionStep(s, ack, z3.IntVal(0))
    next_one = z3.And(ahead == 1, z3.Not(at_end(s.returns_credited)))
    return choose(next_one, credited, choose(ahead <= 0, again, _unchanged(s)))


def admit(s: Session, nonce16: Term) -> SessionStep:
    """JOIN(n) in any phase: write off what is open, both counters up to one high half, ADMIT."""
    written = choose(s.phase != S_IDLE, _resolve(s, z3.BoolVal(False)), _unchanged(s))
    t = written.session
    high_tx, high_seq = z3.LShR(t.tx, 16), z3.LShR(t.returns_credited, 16)
    high = z3.If(z3.UGT(high_tx, high_seq), high_tx, high_seq)
    t = replace(
        t,
        tx=(high << 16) | (t.tx & 0xFFFF),
        returns_credited=(high << 16) | (t.returns_credited & 0xFFFF),
    )
    sent = Sent.of(
        MsgType.ADMIT,
        nonce16,
        z3.BV2Int(low(t.tx, TX_BITS)),
        z3.BV2Int(low(t.returns_credited, SEQ_BITS)),
    )
    return SessionStep(t, sent, written.credit)


def may_begin(s: Session) -> Term:
    """``core.common.check_life``: the node's numbering has room for one more transaction."""
    return z3.Not(at_end(s.tx))


def begin(s: Session, amount: Term) -> SessionStep:
    """Begin(a) in IDLE: Us -= a, tx += 1, INTENTION(tx, a, Gs) (when ``may_begin``)."""
    tx = s.tx + 1
    started = replace(s, phase=WAIT_ACK, tx=tx, reserved=amount, decision=NO_DECISION)
    delivered_mj = (s.delivered / QUANTUM_UJ) % (1 << DELIVERED_BITS)
    sent = Sent.of(MsgType.INTENTION, low(tx, TX_BITS), amount / QUANTUM_UJ, delivered_mj)
    return SessionStep(started, sent, -amount)


def decide(s: Session, commit: bool) -> SessionStep:
    """Decide in ACKED: COMMIT or ABORT(tx, Ts)."""
    decision = z3.IntVal(int(Decision.COMMIT if commit else Decision.ABORT))
    kind = MsgType.COMMIT if commit else MsgType.ABORT
    return SessionStep(
        replace(s, phase=WAIT_CONFIRM, decision=decision),
        Sent.of(kind, low(s.tx, TX_BITS), s.reserved / QUANTUM_UJ),
        z3.IntVal(0),
    )


# -- local events and timers ---------------------------------------------------------------------


def spend(c: Client, amount: Term) -> tuple[Client, Term]:
    """Spend(x) in IDLE and HOLDING: Uc -= x, spent += x; the term says whether the rules allow
    it (0 < x <= Uc, books kept), as the Python core refuses it otherwise."""
    allowed = z3.And(c.phase != JOINING, amount > 0, amount <= c.usable)
    return replace(c, usable=c.usable - amount, spent=c.spent + amount), allowed


def give_back(c: Client, amount: Term) -> tuple[Client, Sent, Term]:
    """GiveBack(x) with no return pending: Uc -= x, q += 1, RETURN(q, x); allowed when x is a
    whole number of mJ in one frame and at most Uc."""
    allowed = z3.And(
        c.phase != JOINING,
        c.return_pending == 0,
        z3.Not(at_end(c.return_seq)),
        amount > 0,
        amount % QUANTUM_UJ == 0,
        amount <= 65_535 * QUANTUM_UJ,
        amount <= c.usable,
    )
    seq = c.return_seq + 1
    returned = replace(c, usable=c.usable - amount, return_seq=seq, return_pending=amount)
    return returned, Sent.of(MsgType.RETURN, low(seq, SEQ_BITS), amount / QUANTUM_UJ), allowed


def resend_return(c: Client) -> tuple[Client, Sent]:
    """The return timer, due: the pending RETURN again (JOINING: the JOIN again)."""
    pending = z3.And(c.phase != JOINING, c.return_pending != 0)
    again = Sent.of(MsgType.RETURN, low(c.return_seq, SEQ_BITS), c.return_pending / QUANTUM_UJ)
    return c, pick(
        c.phase == JOINING, Sent.of(MsgType.JOIN, c.nonce), pick(pending, again, Sent.none())
    )


def client_power_loss(c: Client) -> tuple[Client, Sent]:
    """A reset with the record kept: the held intention is lost (JOINING: stays JOINING)."""
    return pick(c.phase == JOINING, c, _drop_hold(c)), Sent.none()


def books_lost(c: Client, nonce16: Term) -> tuple[Client, Sent]:
    """No valid record at start: a blank client, JOINING with a new nonce, JOIN(n)."""
    zero = z3.IntVal(0)
    blank = Client(
        usable=zero,
        credited=zero,
        spent=zero,
        last_tx=counter(0),
        outcome=z3.IntVal(int(Outcome.NONE)),
        return_seq=counter(0),
        return_pending=zero,
        credited_unknown=z3.BoolVal(False),
        held_tx=counter(0),
        held_amount=zero,
        phase=JOINING,
        nonce=nonce16,
        pending_draw=z3.BoolVal(False),
    )
    return blank, Sent.of(MsgType.JOIN, nonce16)


def response_timeout(s: Session, gives_up: Term) -> SessionStep:
    """The response timer of an open session, due: the identical frame again, or (``gives_up``:
    N re-sends done) a write-off, Gs += Ts."""
    waiting = z3.Or(s.phase == WAIT_ACK, s.phase == WAIT_CONFIRM)
    delivered_mj = (s.delivered / QUANTUM_UJ) % (1 << DELIVERED_BITS)
    intention = Sent.of(
        MsgType.INTENTION, low(s.tx, TX_BITS), s.reserved / QUANTUM_UJ, delivered_mj
    )
    command = pick(
        s.decision == ABORT,
        Sent.of(MsgType.ABORT, low(s.tx, TX_BITS), s.reserved / QUANTUM_UJ),
        Sent.of(MsgType.COMMIT, low(s.tx, TX_BITS), s.reserved / QUANTUM_UJ),
    )
    again = SessionStep(s, pick(s.phase == WAIT_ACK, intention, command), z3.IntVal(0))
    step = choose(gives_up, _resolve(s, z3.BoolVal(False)), again)
    return choose(waiting, step, _unchanged(s))


def supervisor_power_loss(s: Session) -> SessionStep:
    """A reset: ACKED (not persisted) falls back to WAIT_ACK; nothing sent at once here (open
    sessions re-send when their timer, set due, fires)."""
    return SessionStep(
        replace(s, phase=z3.If(s.phase == ACKED, WAIT_ACK, s.phase)), Sent.none(), z3.IntVal(0)
    )


# -- a gateway's link rules, on its client role ----------------------------------------------------


def forward(c: Client) -> tuple[Client, Term]:
    """``core.gateway.forward`` seen from the client role: all of Uc passed below (spent, and
    injected into the downstream usable budget); the term says whether there is any."""
    moved, _ = spend(c, c.usable)
    return moved, c.usable > 0


def give_back_from_below(c: Client, amount: Term) -> tuple[Client, Sent, Term]:
    """``core.gateway.withdraw_for_return`` then ``give_back``: ``amount`` taken back out of what
    was passed below (spent) and returned upstream in one step; allowed when the return is and
    no more was passed below than that (the downstream usable budget holds at most that)."""
    back = replace(c, usable=c.usable + amount, spent=c.spent - amount)
    returned, sent, allowed = give_back(back, amount)
    return returned, sent, z3.And(allowed, amount <= c.spent)
