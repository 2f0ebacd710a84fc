"""The inductive invariant: clauses on a world, and the property ``P(m, world)`` of each message
in flight, with the assumptions the theorem states (bounded age on the wire, bounded life, fresh
nonces). Counters are compared in canonical numbering (``World``'s properties)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from canergy.core.state import Decision, Outcome
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    DELIVERED_BITS,
    QUANTUM_UJ,
    USABLE_MAX_UJ,
)
from canergy.prove import symbolic as sym
from canergy.prove.symbolic import Term, z3
from canergy.prove.world import H, Kind, Msg, World, epoch_of, msg_epoch

Clause = Callable[[World], Term]
MsgClause = Callable[[Msg, World], Term]

LIFE = COUNTER_BOUND
"""Bounded life: every 32-bit counter stays below this (a billion transactions per node)."""
Q = QUANTUM_UJ
GS_WRAP = (1 << DELIVERED_BITS) * Q
"""An INTENTION's Gs wraps at 2**24 mJ."""
COMMITTED, ABORTED = z3.IntVal(int(Outcome.COMMITTED)), z3.IntVal(int(Outcome.ABORTED))
D_NONE, D_COMMIT, D_ABORT = (z3.IntVal(int(d)) for d in Decision)


def ule(a: Term, b: Term) -> Term:
    return z3.ULE(a, b)


def ult(a: Term, b: Term) -> Term:
    return z3.ULT(a, b)


def low16(x: Term) -> Term:
    return z3.Extract(15, 0, x)


def near(a: Term, b: Term) -> Term:
    """``a`` within 2**15 of ``b`` (32-bit counters): the wire's 16 bits name it exactly."""
    return ult(a - b + (1 << 15), 1 << 16)


def one(x: Term) -> Term:
    return x + sym.counter(1)


def amount_mj(x: Term) -> Term:
    return z3.And(x >= 1, x <= AMOUNT_MAX_MJ)


def whole(x: Term) -> Term:
    """A whole number of wire quanta, at least zero."""
    return z3.And(x >= 0, x % Q == 0)


def _client_may_take(m_k: Term, w: World) -> Term:
    """Transaction ``m_k`` is one the client may still commit (after its last, or after the
    admission of a life that has no books yet)."""
    return z3.If(w.booked, ult(w.last, m_k), z3.And(w.admitted, ult(w.admitted_at, m_k)))


# -- clauses on a world -------------------------------------------------------------------------

S_IDLE, WAIT_CONFIRM = sym.S_IDLE, sym.WAIT_CONFIRM


def supervisor_books(w: World) -> Term:
    s = w.s
    return z3.And(
        z3.Or(*(s.phase == p for p in (sym.S_IDLE, sym.WAIT_ACK, sym.ACKED, sym.WAIT_CONFIRM))),
        (s.phase == S_IDLE) == (s.reserved == 0),
        z3.Implies(w.open, z3.And(s.reserved >= Q, s.reserved <= AMOUNT_MAX_MJ * Q)),
        whole(s.reserved),
        whole(s.delivered),
        s.returned >= 0,
    )


def decision(w: World) -> Term:
    d = w.s.decision
    known = z3.Or(d == D_NONE, d == D_COMMIT, d == D_ABORT)
    return z3.And(known, (w.s.phase == WAIT_CONFIRM) == (d != D_NONE))


def prophecy(w: World) -> Term:
    """Gs is H of the open transaction, or of the next one when none is open."""
    e = epoch_of(w)
    return w.s.delivered == z3.If(w.open, H(e, w.tx), H(e, one(w.tx)))


def lifts(w: World) -> Term:
    return z3.And(
        low16(w.shift_tx) == 0,
        low16(w.shift_seq) == 0,
        ule(w.shift_tx, w.s.tx),
        ule(w.shift_seq, w.s.returns_credited),
    )


def client_books(w: World) -> Term:
    c = w.c
    return z3.And(
        z3.Or(c.phase == sym.IDLE, c.phase == sym.HOLDING, c.phase == sym.JOINING),
        c.usable >= 0,
        c.spent >= 0,
        whole(c.credited),
        whole(c.return_pending),
        c.return_pending <= AMOUNT_MAX_MJ * Q,
        z3.Implies(z3.Not(w.booked), z3.And(c.usable == 0, c.spent == 0)),
    )


def numbering(w: World) -> Term:
    """A client with books counts in the supervisor's numbering, never ahead of it."""
    return z3.Implies(
        w.booked,
        z3.And(
            low16(w.off_tx) == 0,
            low16(w.off_seq) == 0,
            ule(w.off_tx, w.last),
            ule(w.off_seq, w.seq),
            ule(w.last, w.tx),
            ule(w.seq, one(w.rc)),
            z3.Implies(w.c.return_pending == 0, ule(w.seq, w.rc)),
        ),
    )


def pending_return(w: World) -> Term:
    """A return not yet credited was debited first."""
    c = w.c
    waiting = z3.And(w.booked, c.return_pending > 0, w.seq == one(w.rc))
    return z3.Implies(waiting, w.s.returned + c.return_pending <= w.given)


def returns(w: World) -> Term:
    return w.s.returned <= w.given


def held(w: World) -> Term:
    """A held intention: after the client's last, from the supervisor, its amount Ts while
    open; once the supervisor resolved it, it was delivered (H grew by its amount)."""
    c, e = w.c, epoch_of(w)
    current = z3.And(w.held == w.tx, w.open)
    return z3.Implies(
        c.phase == sym.HOLDING,
        z3.And(
            ult(w.last, w.held),
            ult(c.last_tx, c.held_tx),
            ule(w.held, w.tx),
            whole(c.held_amount),
            c.held_amount >= Q,
            c.held_amount <= AMOUNT_MAX_MJ * Q,
            z3.Implies(current, c.held_amount == w.s.reserved),
            z3.Implies(z3.Not(current), H(e, one(w.held)) == H(e, w.held) + c.held_amount),
        ),
    )


def energy(w: World) -> Term:
    """Every µJ credited to the client is usable, spent, given back or lost with its books."""
    return z3.And(
        w.c.usable + w.spent + w.given + w.lost == w.received,
        w.c.spent <= w.spent,
        w.spent >= 0,
        w.given >= 0,
        w.lost >= 0,
    )


def known_rc(w: World) -> Term:
    """A client that knows its Rc was credited no more than it (over every life)."""
    return z3.Implies(
        z3.And(w.booked, z3.Not(w.c.credited_unknown)),
        z3.And(w.received <= w.rc_true, w.roff % GS_WRAP == 0),
    )


def credit_bound(w: World) -> Term:
    """The client was credited at most H after its last transaction; for the open one, H before
    it, plus Ts if the client committed it. (Its Rc may be higher: an intention refused for
    overflow still teaches it Gs; a higher Rc only pays back less.)"""
    x, e = w.received, epoch_of(w)
    current = z3.And(w.last == w.tx, w.open)
    bound = z3.If(
        current, H(e, w.tx) + z3.If(w.c.outcome == COMMITTED, w.s.reserved, 0), H(e, one(w.last))
    )
    return z3.Implies(w.booked, x <= bound)


def passivity(w: World) -> Term:
    """The theorem's heart: the client was credited no more than Gs, plus Ts once it committed
    the open transaction."""
    return w.received <= w.s.delivered + z3.If(z3.And(w.open, w.cc), w.s.reserved, 0)


def commit_seen(w: World) -> Term:
    committed = z3.And(w.booked, w.last == w.tx, w.open, w.c.outcome == COMMITTED)
    return z3.Implies(committed, w.cc)


def cc_source(w: World) -> Term:
    """The open transaction was committed by this life, or by one not yet admitted again."""
    this_life = z3.And(w.booked, w.last == w.tx, w.c.outcome == COMMITTED)
    return z3.Implies(
        z3.And(w.open, w.cc), z3.Or(this_life, z3.And(z3.Not(w.booked), z3.Not(w.admitted)))
    )


def lives(w: World) -> Term:
    return z3.And(
        w.life >= 0,
        z3.Implies(z3.Not(w.admitted), z3.Not(w.booked)),
        z3.Implies(w.admitted, ule(w.admitted_at, w.tx)),
        z3.Implies(z3.And(w.admitted, w.open), ult(w.admitted_at, w.tx)),
        z3.Implies(z3.And(w.admitted, w.booked), ule(w.admitted_at, w.last)),
    )


STATE: tuple[tuple[str, Clause], ...] = (
    ("supervisor books", supervisor_books),
    ("decision", decision),
    ("Gs = H", prophecy),
    ("counter lifts", lifts),
    ("client books", client_books),
    ("numbering", numbering),
    ("pending return", pending_return),
    ("returned <= given", returns),
    ("held intention", held),
    ("energy identity", energy),
    ("received <= Rc", known_rc),
    ("received <= H", credit_bound),
    ("passivity", passivity),
    ("commit seen", commit_seen),
    ("commit source", cc_source),
    ("lives", lives),
)


# -- P(m, world) for each message in flight ----------------------------------------------------


def _tx_msg(m: Msg, w: World) -> Term:
    return z3.And(ule(m.k, w.tx), m.w == low16(m.k))


def _current(m: Msg, w: World) -> Term:
    """``m`` names the open transaction (of the world's epoch of ``H``)."""
    return z3.And(m.k == w.tx, w.open, msg_epoch(m, w) == epoch_of(w))


def p_intention(m: Msg, w: World) -> Term:
    current, e = _current(m, w), msg_epoch(m, w)
    return z3.And(
        _tx_msg(m, w),
        amount_mj(m.amount),
        H(e, m.k) % Q == 0,
        m.gs == (H(e, m.k) / Q) % (1 << DELIVERED_BITS),
        z3.Implies(current, m.amount * Q == w.s.reserved),
        z3.Implies(
            z3.And(z3.Not(current), _client_may_take(m.k, w)),
            H(e, one(m.k)) == H(e, m.k) + m.amount * Q,
        ),
    )


def p_commit(m: Msg, w: World) -> Term:
    current, e = _current(m, w), msg_epoch(m, w)
    return z3.And(
        _tx_msg(m, w),
        amount_mj(m.amount),
        z3.Implies(current, z3.And(m.amount * Q == w.s.reserved, w.s.decision == D_COMMIT)),
        z3.Implies(z3.Not(current), H(e, one(m.k)) == H(e, m.k) + m.amount * Q),
    )


def p_abort(m: Msg, w: World) -> Term:
    current = _current(m, w)
    return z3.And(_tx_msg(m, w), z3.Implies(current, w.s.decision == D_ABORT))


def p_return_ack(m: Msg, w: World) -> Term:
    return z3.And(ule(m.k, w.rc), m.w == low16(m.k))


def p_admit(m: Msg, w: World) -> Term:
    answers_this_life = z3.And(m.life == w.life, z3.Not(w.booked))
    return z3.And(
        ule(m.k, w.tx),
        ule(m.q, w.rc),
        m.admit_tx == low16(m.k),
        m.admit_seq == low16(m.q),
        m.life >= 0,
        m.life <= w.life,
        z3.Implies(
            answers_this_life,
            z3.And(
                w.admitted,
                ule(w.admitted_at, m.k),
                w.received <= H(msg_epoch(m, w), one(m.k)),
                z3.Implies(m.k == w.tx, z3.Not(w.open)),
            ),
        ),
    )


def p_ack(m: Msg, w: World) -> Term:
    return _tx_msg(m, w)


def p_aborted(m: Msg, w: World) -> Term:
    this_life = m.life == w.life
    return z3.And(
        _tx_msg(m, w),
        m.life >= 0,
        m.life <= w.life,
        z3.Implies(
            this_life,
            z3.And(
                w.booked,
                ule(m.k, w.last),
                z3.Implies(m.k == w.last, w.c.outcome == ABORTED),
            ),
        ),
        z3.Implies(z3.And(m.life < w.life, w.admitted), ule(m.k, w.admitted_at)),
        z3.Implies(z3.And(m.k == w.tx, w.open), z3.Not(w.cc)),
    )


def p_return(m: Msg, w: World) -> Term:
    return z3.And(
        ule(m.k, one(w.rc)),
        m.w == low16(m.k),
        amount_mj(m.amount),
        z3.Implies(m.k == one(w.rc), w.s.returned + m.amount * Q <= w.given),
    )


def p_join(m: Msg, w: World) -> Term:
    return z3.And(m.life >= 0, m.life <= w.life)


MESSAGE: dict[Kind, MsgClause] = {
    Kind.INTENTION: p_intention,
    Kind.COMMIT: p_commit,
    Kind.ABORT: p_abort,
    Kind.RETURN_ACK: p_return_ack,
    Kind.ADMIT: p_admit,
    Kind.ACK: p_ack,
    Kind.COMMITTED: p_ack,
    Kind.ABORTED: p_aborted,
    Kind.RETURN: p_return,
    Kind.JOIN: p_join,
}


def invariant(w: World) -> Term:
    return z3.And(*(clause(w) for _, clause in STATE))


# -- an older image of the node's record --------------------------------------------------------


def p_image(r: sym.Client, w: World, pending: Clause | None = None) -> Term:
    """What is known of an image the node's record may be put back to: a record the current
    life wrote (with books, in its numbering, after its admission) at an earlier point, so no
    number of it is ahead of the current record's, nor its Rc, nor what its actuator had used;
    what it lacks of the current Uc it debited since, what it holds it had received (Rc counts
    every credit since); and the invariant's own clauses on the
    node's books hold of it (``numbering``, ``client books``, ``pending return``).

    "Any older image" is encoded as a message in flight is: the node's writes form a channel to
    its later starts, and the restore step takes any record of it with this property as its
    hypothesis. A proof *with* the step needs this property to be inductive (established by
    every write, kept by every step, as ``P`` of a message is); the hardened rules fail already
    at the step itself, on an image a real trace reaches (an image from before a spend has Uc
    larger by what the actuator used: ``canergy check --old-copies 1``), so no stronger form
    can save them. ``pending``: the clause on its pending return (None: ``pending_return``)."""
    c, then = w.c, replace(w, c=r)
    return z3.And(
        w.booked,
        r.phase == sym.IDLE,
        r.held_tx == 0,
        r.held_amount == 0,
        z3.Or(*(r.outcome == int(o) for o in Outcome)),
        r.usable <= USABLE_MAX_UJ,
        c.usable <= r.usable + c.credited - r.credited,  # what it lacks now, it debited since
        r.usable <= w.received - (c.credited - r.credited),  # received then, Rc counts all since
        r.spent <= c.spent,
        r.credited <= c.credited,
        r.credited_unknown == c.credited_unknown,
        ule(w.admitted_at, then.last),
        ule(then.last, w.last),
        ule(then.seq, w.seq),
        numbering(then),
        client_books(then),
        (pending or pending_return)(then),
    )


def p_session_image(r: sym.Session, w: World, prophesied: bool = True) -> Term:
    """What is known of an image the supervisor's record of the session may be put back to: a
    record it wrote earlier in the current numbering (no counter of it ahead, its Gs and what
    it credited back not either, ACKED stored as WAIT_ACK), of which the invariant's clauses on
    the supervisor's books hold (``supervisor books``, ``decision``, ``Gs = H``, ``counter
    lifts``). Encoded as ``p_image`` is for the node's record. ``prophesied``: its Gs is ``H`` of
    the current epoch (under the witnessed rules an image may be of an earlier epoch, and a
    start that ends from it begins the next)."""
    then = replace(w, s=r)
    return z3.And(
        r.phase != sym.ACKED,
        ule(w.shift_tx, r.tx),
        ule(then.tx, w.tx),
        ule(w.shift_seq, r.returns_credited),
        ule(then.rc, w.rc),
        r.delivered <= w.s.delivered,
        r.returned <= w.s.returned,
        supervisor_books(then),
        decision(then),
        prophecy(then) if prophesied else z3.BoolVal(True),
        lifts(then),
    )


# -- the theorem's assumptions --------------------------------------------------------------------


def deliverable(m: Msg, w: World) -> Term:
    """Bounded age: a counter on the wire is within 2**15 of the receiver's (an INTENTION's Gs
    within 2**23 mJ of the client's Rc); and an ADMIT that matches a joining client's nonce
    answers its current life (nonces of a node's lives differ)."""
    k = m.kind
    if k in (Kind.INTENTION, Kind.COMMIT, Kind.ABORT):
        age = z3.Implies(w.booked, near(m.k, w.last))
        if k is Kind.INTENTION:
            gap = H(msg_epoch(m, w), m.k) / Q - w.rc_true / Q
            gs_age = z3.And(gap < (1 << (DELIVERED_BITS - 1)), gap > -(1 << (DELIVERED_BITS - 1)))
            age = z3.And(age, z3.Implies(z3.And(w.booked, z3.Not(w.c.credited_unknown)), gs_age))
        return age
    if k is Kind.RETURN_ACK:
        return z3.Implies(w.booked, near(m.k, w.seq))
    if k is Kind.ADMIT:
        match = z3.And(z3.Not(w.booked), m.nonce == w.c.nonce)
        return z3.Implies(match, m.life == w.life)
    if k in (Kind.ACK, Kind.COMMITTED, Kind.ABORTED):
        return near(m.k, w.tx)
    if k is Kind.RETURN:
        return near(m.k, w.rc)
    return z3.BoolVal(True)


def bounded(w: World) -> Term:
    """Bounded life: no counter, held or canonical, reaches ``LIFE``."""
    counters = (
        w.s.tx,
        w.s.returns_credited,
        w.c.last_tx,
        w.c.return_seq,
        w.c.held_tx,
        w.last,
        w.seq,
        w.held,
        w.admitted_at,
    )
    return z3.And(*(ult(x, LIFE) for x in counters))
