"""The witnessed rules (``canergy.prove.witnessed``) as steps of a world, with both restore
steps, and the invariant tried on them (``canergy prove --rules witnessed``).

While the node's start waits for the supervisor's confirmation (RESUMING, or answering a
SYNC) the invariant speaks of its record as it stood when the start began (the ghost
``World.pre``), not of the record it started from, which may be an older image: what it holds
counts in the ledger only from the confirmation on. A confirmation that keeps the books counts
their Uc (and pending draw) from then on: the credits that record lacks are no longer received
(Gs pays them back), a return of the record at the start that the confirmation voids was given
back and came back, and the rest of the difference is lost. A pending draw counts as held until
the RETURN_ACK releases it to the actuator (spent) or a confirmation drops it (lost). What the
record's ``spent`` grows by in any phase is used.

Two more ghosts, each a pure function of the history: ``World.starts`` (the node's starts; a
DEBIT carries the start it was sent in, a confirmation the start it answers) and ``World.top``
(the highest return number any record of the node held). ``P`` of a confirmation of the current
start states what the supervisor saw when it answered: C was at most the number of the record
started from, so with Q one past it that record has every debit of the record at the start but
one not acknowledged, and Q and k are at least the record at the start's.

The supervisor's start has its ghost too, ``World.spre``: the session as it stood when the
start began (what was open written off). While the start waits for the node's books and counts
the invariant speaks of it, not of the record the supervisor started from (which may be an
older image); the record started from is no further in any counter. A restore or a power loss
of the supervisor then keeps every clause.

A third pair of ghosts names the supervisor's starts: ``World.sstarts`` counts them, a SYNC
carries the start it was sent in, the node's books and counts the start whose SYNC they
answer (``World.answering`` while it answers one); books and counts a start takes (its nonce)
are of that start (``deliverable``: assumption 5 for the supervisor's nonces).

A re-sync of the node (``supervisor re-syncs a node``: the supervisor's choice, from IDLE) is a
start of this one session without restore and without write-off, and the clauses of a start
mean the same of it: ``World.spre`` is the session as it stood (idle, nothing open),
``World.sstarts`` counts it (its nonce is drawn fresh, as a start's: assumption 5), its SYNC
phases are a start's. While it waits the session is the one at its start but for its phase
and nonce, Gs included (``resyncing``: its books move no Gs); a JOIN ends it and is
admitted as in IDLE (``join_while_syncing``), its counts end it as a start's.

The window (a) is four clauses (``witnessed``, ``window``, ``window at a start``, ``records of
the start``): W at most tx and the node's ``reach``, the highest transaction begun
(``World.begun``) at most tx and ``reach`` + B, and while a start of the supervisor's from an
older image waits, the node's record within B of what was begun; residual (d) is a hypothesis
of both restore steps (``not_from_an_image``, ``far_behind``). The supervisor's last answer to
a start is remembered with its ghosts (``World.rk``), as the last JOIN's ADMIT is, and ``P``
holds of it while a repeat can happen.

A confirmation of the node's start may carry a k below the ltx of the record at the start (that
record settled ahead for SYNCs whose counts were never taken): what it must be at least is
every transaction the node took (``World.taken``: an intention held, a COMMIT, an ABORT or a
timeout-commit resolved), and ``P`` of an INTENTION reads "the node may still take it" against
that, not against the ltx.

``World.sbegan`` (the node's first start after the supervisor's current one began) says no
confirmation of such a start is in flight while the supervisor's start waits; counts answering
it come from such a start, with an ltx within 2**15 of tx (assumption 3) that no record of this
life has gone below since. W is signed, as in both cores (counts whose ltx reads below 0 set it
there and close the window).

Counts that end a supervisor's start begin an epoch of ``H`` (``World.epoch``): the session
may go on from an older image with a Gs below the one the discarded history fixed for the
numbers it takes again, so each epoch has its own ``H``, equal to the Gs it began at up to one
past the tx it began at (``world.BASE_TX``, ``BASE_GS``); a frame of an earlier epoch names a
transaction at most the current epoch's base (``sent_in``), and a node with books outside a
start holds an ltx at or above it (``epochs``), so it takes none. What the session holds then
is at least what the node received: the books answering the start carry its Rc (a ghost,
``Msg.rc``), and Gs after them is at least it (``books taken``); books with Rc unknown come
from a life admitted afresh that has received at most the Gs of its admission
(``World.ags``, ``unknown books``), which the image holds (residual: no image from before that
admission, in ``reported``; the rules now pay for such an image with the counts afresh,
``witnessed.ahead_of_image``, which this ledger of what the node received cannot use: what a
node lost with its books counts in it, and the debits bound only what it drew); the node is
not put back below its record at the start in Rc while a start behind in Gs waits (residual
(d) in Rc, ``far_behind_rc``).

Proved: every step keeps every clause, the supervisor's DEBIT proved branch by branch
(``_debit_branches``) after lemmas on its counters (among them that counts ending a start leave
tx at or above a syncing node's last: without it the remembered answer's ``P`` in the branch
"counts that end a re-sync, found behind" took 61 to over 1,500 million of z3's steps by seed
and process), the books' fields and the repeat of the last answer. The proof
is under assumption 2 narrowed (``canergy.prove.NARROWED``): the restore steps take an image
of the stated kind (``p_image``, ``p_session_image``) and the residual (d) as hypotheses. The
images are shown to be of that kind for the copies each side writes (a step of each side
writes one, ``write_copy``, ``write_session_copy``, kept as the ghosts ``World.copy`` and
``World.scopy``): a copy written while no start of that side waits, or while a start of that
side's from its own record waits (for the node its RESUME after a power loss or its answer to
a SYNC: ``copy_covered``; ``session_copy_covered``), is of that kind
at every later step until that side's record goes back (``went_back``, ``session_went_back``; the
clauses ``copies the node wrote``, ``copies the supervisor wrote``). A start of the
supervisor's ends either side's copies only when it goes on from an older image
(``World.sforked``), not when it goes on from its own record (a power loss, a re-sync), which
holds every counter at least where it stood (``own_start``).

Counts that end a start are read against the record started from, so ``deliverable`` asks
their q within 2**15 of its C (assumption 3 of the receiver's counter), and ``bounded`` its tx
below the cap where their ltx is held (assumption 4).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, TypeVar

from canergy.core.state import Outcome
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    SYNC_CONFIRMED,
    USABLE_MAX_UJ,
)
from canergy.prove import invariant as inv
from canergy.prove import steps as st
from canergy.prove import symbolic as sym
from canergy.prove import witnessed as wit
from canergy.prove.invariant import COMMITTED, Q, low16, one, ule, whole
from canergy.prove.symbolic import Term, z3
from canergy.prove.world import (
    BASE_GS,
    BASE_TX,
    TO_CLIENT,
    W_TO_SUPERVISOR,
    H,
    Kind,
    Msg,
    World,
    epoch_of,
    msg_epoch,
)

T = TypeVar("T")

# -- what the node holds ---------------------------------------------------------------------------


def starting(c: sym.Client) -> Term:
    """The node waits for the supervisor to confirm its start (RESUME or a SYNC's answer)."""
    return z3.Or(c.phase == sym.RESUMING, c.phase == sym.SYNCING)


def holds(c: sym.Client) -> Term:
    """Uc and a pending draw (debited, not yet released to the actuator)."""
    return c.usable + z3.If(c.pending_draw, c.return_pending, 0)


def _ghost(value: T | None, what: str) -> T:
    """A ghost of the witnessed proof's world (None only in the hardened proof's worlds)."""
    assert value is not None, f"a world of the witnessed proof {what}"
    return value


def pre(w: World) -> sym.Client:
    return _ghost(w.pre, "has the record at the start")


def starts(w: World) -> Term:
    return _ghost(w.starts, "counts the node's starts")


def top(w: World) -> Term:
    return _ghost(w.top, "has the highest number")


def spre(w: World) -> sym.Session:
    return _ghost(w.spre, "has the session at its start")


def sstarts(w: World) -> Term:
    return _ghost(w.sstarts, "counts the supervisor's starts")


def sbegan(w: World) -> Term:
    return _ghost(w.sbegan, "has the node's first start since the supervisor's")


def begun(w: World) -> Term:
    return _ghost(w.begun, "has the highest transaction begun")


def umax(a: Term, b: Term) -> Term:
    """The higher of two counters (unsigned)."""
    return z3.If(z3.UGT(a, b), a, b)


def taken(w: World) -> Term:
    return _ghost(w.taken, "has the highest transaction taken")


def took(w: World) -> Term:
    return _ghost(w.took, "has how the highest transaction taken ended")


def lhi(w: World) -> Term:
    return _ghost(w.lhi, "has the highest ltx of the start")


def answering(w: World) -> Term:
    return _ghost(w.answering, "has the SYNC answered")


def current_sync(m: Msg, w: World) -> Term:
    """``m`` is a SYNC of the supervisor's current start, or a DEBIT answering one, and that
    start waits."""
    return z3.And(m.sstart == sstarts(w), wit.in_start(w.s))


def view(w: World) -> World:
    """The world the hardened clauses speak of: while the node's start waits, its record as it
    stood when the start began; while the supervisor's start waits, its session record as it
    stood when that start began (``World.spre``)."""
    return replace(
        w,
        c=sym.pick(starting(w.c), pre(w), w.c),
        s=sym.pick(wit.in_start(w.s), spre(w), w.s),
    )


def counted(w: World) -> Term:
    """What counts as the node's in the ledger (Uc and a pending draw, of ``view``)."""
    return holds(view(w).c)


def image_seq(w: World) -> Term:
    """The return number of the record the node started from (canonical)."""
    return w.c.return_seq + w.off_seq


def start_seq(w: World) -> Term:
    """The return number of the record at the start (canonical)."""
    return pre(w).return_seq + w.off_seq


def _voided(image_seq: Term, later: sym.Client, later_seq: Term) -> Term:
    """The ``later`` record holds a debit numbered one past an image's, not acknowledged (its
    amount; else 0): a confirmation of the image voids it."""
    pending = z3.And(one(image_seq) == later_seq, later.return_pending > 0)
    return z3.If(pending, later.return_pending, 0)


def _confirmable(image_seq: Term, later: sym.Client, later_seq: Term) -> Term:
    """An image may be confirmed in place of the ``later`` record: it has every debit of it
    but one not acknowledged (so the actuator used nothing it lacks)."""
    return z3.Or(image_seq == later_seq, _voided(image_seq, later, later_seq) > 0)


def _lacks(image: sym.Client, image_seq: Term, later: sym.Client, later_seq: Term) -> Term:
    """An image that may be confirmed holds no more than the ``later`` record, less the credits
    it lacks, plus the one debit it lacks."""
    return z3.Implies(
        _confirmable(image_seq, later, later_seq),
        image.usable + (later.credited - image.credited)
        <= later.usable + _voided(image_seq, later, later_seq),
    )


def voided(w: World) -> Term:
    """What a confirmation of the record started from voids of the record at the start."""
    return _voided(image_seq(w), pre(w), start_seq(w))


def confirmable(w: World) -> Term:
    return _confirmable(image_seq(w), pre(w), start_seq(w))


def expected(c: sym.Client) -> Term:
    """The nonce of the ADMIT that confirms the node's start."""
    return z3.If(c.phase == sym.SYNCING, c.nonce ^ SYNC_CONFIRMED, c.nonce)


def this_start(m: Msg, w: World) -> Term:
    return z3.And(starting(w.c), m.start == starts(w))


def confirms(m: Msg, c: sym.Client) -> Term:
    """The node reads the ADMIT's Q as one past its own number: books kept."""
    return sym.unwrap(m.admit_seq, c.return_seq, SEQ_BITS) - c.return_seq == 1


# -- the invariant ------------------------------------------------------------------------------


def supervisor_books(w: World) -> Term:
    s = w.s
    phases = (sym.S_IDLE, sym.WAIT_ACK, sym.ACKED, sym.WAIT_CONFIRM, sym.SYNCING, sym.SYNC_BOOKS)
    return z3.And(
        z3.Or(*(s.phase == p for p in phases)),
        z3.Not(w.open) == (s.reserved == 0),
        z3.Implies(w.open, z3.And(s.reserved >= Q, s.reserved <= AMOUNT_MAX_MJ * Q)),
        whole(s.reserved),
        whole(s.delivered),
        s.returned >= 0,
        answered(s),
        inv.decision(w),
        inv.lifts(w),
        z3.Implies(wit.in_start(s), z3.And(waiting(w), fresh_sync(s))),
        z3.Implies(s.resync, resyncing(w)),
        sstarts(w) >= 0,
    )


def fresh_sync(s: sym.Session) -> Term:
    """A start's SYNC waits under a nonce not the last start answered's (``sync_nonce_for``):
    its counts are never read as a repeat of that answer."""
    return wit.sync_nonce_for(s, s.sync_nonce) == s.sync_nonce


RESYNC_KEPT = (
    "tx",
    "reserved",
    "decision",
    "returns_credited",
    "returned",
    "resume_nonce",
    "resume_from",
    "resume_to",
    "witness",
    "join_nonce",
    "join_tx",
    "join_seq",
    "delivered",
)
"""What a re-sync leaves as it stood at its start until its counts (or a JOIN) end it."""


def resyncing(w: World) -> Term:
    """A re-sync waits (``Session.resync``): a start of this session without restore, so the
    session at its start (``World.spre``) is the session itself but for the start's phase and
    nonce. Gs too: the books answering the re-sync's SYNC carry the node's Rc, at most Gs
    with nothing restored, and move no Gs (a rule of both cores: raised by them, the JOIN that
    ends a re-sync after its books left Gs above ``H``)."""
    s, r = w.s, spre(w)
    return z3.And(
        wit.in_start(s),
        *(getattr(s, f) == getattr(r, f) for f in RESYNC_KEPT),
    )


def waiting(w: World) -> Term:
    """A supervisor's start waits: the session at its start is idle, nothing open, and the
    record it started from no further in any counter than it, nor in what it credited back
    (``credited_back``)."""
    at_start = replace(w, s=spre(w))
    r = spre(w)
    return z3.And(
        r.phase == sym.S_IDLE,
        inv.supervisor_books(at_start),
        ule(w.tx, at_start.tx),
        ule(w.rc, at_start.rc),
        credited_back(w),
        answered(r),
    )


def credited_back(w: World) -> Term:
    """While a start waits, the record started from has credited back no more returns than the
    session at the start: an image holds at most what was credited then (``p_session_image``),
    and a start's books and counts credit none. When the counts end the start, ``returned <=
    given`` and ``pending return`` speak of the image's again."""
    return w.s.returned <= spre(w).returned


def answered(s: sym.Session) -> Term:
    """The last start answered was answered above its number (C = max(C, q) + 1), and C has
    not gone back below that answer since."""
    return z3.Implies(
        s.resume_to != 0,
        z3.And(z3.UGT(s.resume_to, s.resume_from), z3.ULE(s.resume_to, s.returns_credited)),
    )


def _record(c: sym.Client, booked: Term) -> Term:
    return z3.And(
        z3.Or(*(c.outcome == int(o) for o in Outcome if o is not Outcome.WRITTEN_OFF)),  # its own
        c.usable >= 0,
        c.spent >= 0,
        whole(c.credited),
        whole(c.return_pending),
        c.return_pending <= AMOUNT_MAX_MJ * Q,
        z3.Implies(c.pending_draw, c.return_pending > 0),
        z3.Implies(z3.Not(booked), z3.And(c.usable == 0, c.spent == 0, z3.Not(c.pending_draw))),
    )


def client_books(w: World) -> Term:
    """The node's record (and, while it starts, the one at the start) is well formed."""
    c, p = w.c, pre(w)
    real, at_start = replace(view(w), c=c), replace(view(w), c=p)
    phases = (sym.IDLE, sym.HOLDING, sym.JOINING, sym.RESUMING, sym.SYNCING)
    return z3.And(
        z3.Or(*(c.phase == ph for ph in phases)),
        _record(c, w.booked),
        starts(w) >= 0,
        answering(w) >= -1,
        answering(w) <= sstarts(w),
        z3.Implies(
            z3.And(c.phase == sym.SYNCING, answering(w) == sstarts(w), wit.in_start(w.s)),
            c.nonce == w.s.sync_nonce,
        ),
        ule(top(w), one(view(w).rc)),
        z3.Implies(c.phase != sym.JOINING, ule(w.seq, top(w))),  # no record holds more
        z3.Implies(starting(c), ule(start_seq(w), top(w))),  # the record at the start neither
        # no record holds more, but one number past it that C voided (a repeat's answer)
        z3.Implies(
            view(w).booked,
            z3.Or(
                ule(top(w), view(w).seq),
                z3.And(top(w) == one(view(w).seq), ule(top(w), view(w).rc)),
            ),
        ),
        z3.Implies(starting(c), z3.And(c.held_tx == 0, c.held_amount == 0)),
        # a SYNC answered settles B ahead (SETTLED); counts that follow a confirmation come
        # from the record confirmed, the record at this start
        z3.Implies(
            z3.And(c.phase == sym.SYNCING, c.outcome != sym.SETTLED), c.last_tx == p.last_tx
        ),
        z3.Implies(
            starting(c),
            z3.And(
                p.phase == sym.IDLE,
                p.held_tx == 0,
                p.held_amount == 0,
                _record(p, z3.BoolVal(True)),
                c.spent <= p.spent,  # the record started from is that one or an older image
                c.credited <= p.credited,
                z3.Or(
                    c.outcome == sym.SETTLED,
                    z3.Implies(real.last == at_start.last, c.outcome == p.outcome),
                ),
                z3.Implies(z3.ULT(view(w).tx, real.last), c.outcome == sym.SETTLED),
                c.credited_unknown == p.credited_unknown,
                _lacks(c, image_seq(w), p, start_seq(w)),
                ule(w.off_seq, real.seq),
                ule(real.seq, at_start.seq),
                z3.Implies(z3.Not(c.pending_draw), inv.pending_return(real)),
            ),
        ),
    )


def energy(w: World) -> Term:
    """Every µJ credited to the node is held (as counted), spent, given back or lost."""
    v = view(w)
    return z3.And(
        counted(w) + w.spent + w.given + w.lost == w.received,
        v.c.spent <= w.spent,
        w.spent >= 0,
        w.given >= 0,
        w.lost >= 0,
    )


def pending_return(w: World) -> Term:
    """A pending return (not a draw) not yet credited was debited first; and given back, of
    any record of the node (credited or voided since, it stays given)."""
    v = view(w)
    given = [
        z3.Implies(
            z3.And(c.phase != sym.JOINING, z3.Not(c.pending_draw)), c.return_pending <= w.given
        )
        for c in (w.c, v.c)
    ]
    return z3.And(z3.Implies(z3.Not(v.c.pending_draw), inv.pending_return(v)), *given)


def numbering(w: World) -> Term:
    """The hardened clause on ``view``, but while a start waits the record at its start may be
    ahead of the supervisor's tx: a start confirmed with k below the ltx of the record it
    started from (settled ahead for a SYNC whose counts the supervisor never took) goes on
    answering with that record until its counts move tx (its outcome: settled)."""
    v = view(w)
    ahead = replace(v, s=replace(v.s, tx=v.c.last_tx + v.off_tx + v.shift_tx))
    settled_ahead = z3.And(starting(w.c), v.c.outcome == sym.SETTLED)
    return z3.If(settled_ahead, inv.numbering(ahead), inv.numbering(v))


def remembered(s: sym.Session, k: Term, q: Term, life: Term, epoch: Term) -> Msg:
    """The ADMIT of the last JOIN admitted (``Session.join_*``) with its ghosts, as sent again
    in ``epoch``."""
    zero = z3.IntVal(0)
    return Msg(
        Kind.ADMIT,
        w=z3.BitVecVal(0, 16),
        amount=zero,
        gs=zero,
        nonce=s.join_nonce,
        admit_tx=low16(s.join_tx),
        admit_seq=low16(s.join_seq),
        k=k,
        q=q,
        life=life,
        flags=zero,
        start=z3.IntVal(-1),
        sstart=z3.IntVal(-1),
        epoch=epoch,
        rc=zero,
        rcl=zero,
    )


def joined(w: World) -> Msg:
    """The ADMIT a copy of the last JOIN admitted gets again, with its ghosts (``World.jk``)."""
    assert w.jk is not None and w.jq is not None and w.jlife is not None
    return remembered(w.s, w.jk, w.jq, w.jlife, epoch_of(w))


def answer_of(s: sym.Session, rk: Term, rstart: Term, shift_seq: Term, epoch: Term) -> Msg:
    """The supervisor's last answer to a start (``Session.resume_*``) with its ghosts: the
    nonce answered (flipped for a SYNC's counts), k the last transaction closed then (``rk``),
    Q the C it set (``resume_to``), the node's start it answered (``rstart``); as sent again
    in ``epoch``."""
    zero = z3.IntVal(0)
    counts = z3.Extract(sym.KEY_BITS - 1, 16, s.resume_nonce) != 0
    nonce = z3.Extract(15, 0, s.resume_nonce)
    return Msg(
        Kind.ADMIT,
        w=z3.BitVecVal(0, 16),
        amount=zero,
        gs=zero,
        nonce=z3.If(counts, nonce ^ SYNC_CONFIRMED, nonce),
        admit_tx=low16(rk),
        admit_seq=low16(s.resume_to),
        k=rk,
        q=s.resume_to - shift_seq,
        life=z3.IntVal(-1),
        flags=zero,
        start=rstart,
        sstart=z3.IntVal(-1),
        epoch=epoch,
        rc=zero,
        rcl=zero,
    )


def rk(w: World) -> Term:
    return _ghost(w.rk, "has the last answer's k")


def rstart(w: World) -> Term:
    return _ghost(w.rstart, "has the start the last answer answered")


def last_answer(w: World) -> Msg:
    """The supervisor's last answer to a start, with its ghosts (``World.rk``)."""
    return answer_of(w.s, rk(w), rstart(w), w.shift_seq, epoch_of(w))


def answer_remembered(w: World) -> Term:
    """While a repeat of the supervisor's last answer to a start can happen, that answer is
    one it sent, and a repeat of the start's frame gets it again (with k the same or later):
    its ``P`` holds, as of a frame in flight."""
    own = z3.And(ule(rk(w), w.tx), rstart(w) >= 0)  # of the session's own record (an image's)
    return z3.Implies(wit.may_repeat(w.s), z3.And(own, p_admit(last_answer(w), w)))


def join_remembered(w: World) -> Term:
    """The ADMIT of the last JOIN admitted (``join_seq`` 0: none) is one the supervisor sent,
    and a copy of that JOIN sends it again: its ``P`` holds, as of a frame in flight."""
    assert w.jlife is not None and w.jk is not None and w.jq is not None
    # of the session's own record (an image's too): no further than its counters
    own = z3.And(ule(w.jk, w.tx), ule(w.jq, w.rc))
    return z3.Implies(w.s.join_seq != 0, z3.And(w.jlife >= 0, own, p_admit(joined(w), w)))


_REPLACED = {
    "numbering": numbering,
    "supervisor books": supervisor_books,
    "client books": client_books,
    "energy identity": energy,
    "pending return": pending_return,
}


def _on_view(clause: inv.Clause) -> inv.Clause:
    return lambda w: clause(view(w))


B = wit.WINDOW


def reach(w: World) -> Term:
    """The highest ltx the supervisor may count on the node holding (canonical): of the record
    it holds, or while it starts the highest of the start's records (``World.lhi``); a node
    without books, the transaction its life was admitted at."""
    return z3.If(w.c.phase == sym.JOINING, w.admitted_at, z3.If(starting(w.c), lhi(w), w.last))


def behind(w: World) -> Term:
    """A supervisor's start waits from a record behind the session at its start (an older
    image: its tx below)."""
    return z3.And(wit.in_start(w.s), z3.ULT(w.tx, replace(w, s=spre(w)).tx))


def behind_c(w: World) -> Term:
    """A supervisor's start waits from a record behind the session at its start in C (an older
    image: its C below)."""
    return z3.And(wit.in_start(w.s), z3.ULT(w.rc, replace(w, s=spre(w)).rc))


def far_behind_c(w: World) -> Term:
    """Residual (d) in return numbers: a start of the supervisor's from an image behind in C
    waits while the node's record is more than one number below the highest any record of it
    held (``World.top``), or, in a start, one below a record at the start whose debit was
    acknowledged (not ``confirmable``): both rolled back past the same debit."""
    near = z3.And(ule(top(w), one(w.seq)), z3.Implies(starting(w.c), confirmable(w)))
    return z3.And(behind_c(w), w.c.phase != sym.JOINING, z3.Not(near))


def far_behind(w: World) -> Term:
    """Residual (d): both records rolled back past the same event. A start of the supervisor's
    from an older image waits while the record the node holds is more than B behind the
    highest transaction begun (``World.begun``)."""
    return z3.And(behind(w), w.c.phase != sym.JOINING, z3.Not(ule(begun(w), w.last + B)))


def far_behind_rc(w: World) -> Term:
    """Residual (d) in Rc: a start of the supervisor's from an image behind in Gs waits while
    the node, in a start, holds a record behind the record at its start in Rc: both rolled
    back past the same credit."""
    rolled_back = z3.And(starting(w.c), w.c.credited < pre(w).credited)
    return z3.And(behind_gs(w), rolled_back)


def answers_this_start(w: World) -> Term:
    """The node has answered the SYNC of the supervisor's current start (settled B ahead)."""
    return z3.And(w.c.phase == sym.SYNCING, answering(w) == sstarts(w))


def not_from_an_image(w: World) -> Term:
    """Residual (d), as the supervisor's restore takes it: the node is not in a start from an
    older image behind the records of that start (in ltx, in return numbers: more than one
    below ``top`` or lacking an acknowledged debit, in Rc)."""
    in_c = z3.And(ule(top(w), one(w.seq)), confirmable(w))
    in_rc = pre(w).credited <= w.c.credited
    return z3.Implies(starting(w.c), z3.And(ule(lhi(w), w.last), in_c, in_rc))


def taken_records(w: World) -> Term:
    """The transactions the node took (``World.taken``) were begun; the intention it holds it
    took, and the ltx of each of its records that resolved one (not settled ahead)."""
    v = view(w)
    return z3.And(
        ule(taken(w), begun(w)),
        z3.Implies(holding(w.c), ule(w.held, taken(w))),
        resolved_taken(w.c, w.last, w),
        z3.Implies(starting(w.c), resolved_taken(pre(w), v.last, w)),
        decided_on_an_ack(w.s, w),
        # a record with Rc unknown took nothing past its ltx: it learns its Rc with the first
        # intention it takes, and a record restored from before that starts (its confirmation
        # at or above every transaction taken)
        z3.Implies(z3.And(wit.booked(w.c), w.c.credited_unknown), ule(taken(w), w.last)),
    )


def decided_on_an_ack(r: sym.Session, w: World) -> Term:
    """A session record ``r`` that holds an ACK or a decision holds it of a transaction the
    node took (the supervisor decides only after an ACK): a COMMIT names one."""
    acked = z3.Or(r.phase == sym.ACKED, r.decision != inv.D_NONE)
    return z3.Implies(acked, ule(replace(w, s=r).tx, taken(w)))


def holding(c: sym.Client) -> Term:
    """The node's record holds an intention's number (HOLDING, or kept after it)."""
    return z3.And(c.phase != sym.JOINING, c.held_tx != 0)


def resolved_taken(r: sym.Client, last: Term, w: World) -> Term:
    """A record whose ltx a COMMIT, an ABORT or a timeout-commit set (``last``, canonical) has
    it at most ``World.taken``, and at it the outcome the node gave it (``World.took``)."""
    resolved = r.outcome != sym.SETTLED  # or the first record's, at 0
    decided = z3.Or(r.outcome == COMMITTED, r.outcome == inv.ABORTED)
    booked = r.phase != sym.JOINING
    return z3.And(
        z3.Implies(z3.And(booked, resolved), ule(last, taken(w))),
        z3.Implies(z3.And(booked, decided), last != 0),  # transactions are numbered from 1
        z3.Implies(z3.And(booked, decided, last == taken(w)), r.outcome == took(w)),
    )


def start_records(w: World) -> Term:
    """``World.lhi`` is below the end of the numbering and, while the node starts, at least
    the ltx of the record at the start and of the record it holds; a start of the node that
    answers the SYNC of the supervisor's waiting start began after it (``World.sbegan``)."""
    at_start = z3.And(ule(view(w).last, lhi(w)), ule(w.last, lhi(w)))
    answers_now = z3.And(answers_this_start(w), wit.in_start(w.s))
    return z3.And(
        z3.ULT(lhi(w), inv.LIFE),
        z3.Implies(starting(w.c), at_start),
        z3.Implies(answers_now, starts(w) >= sbegan(w)),  # the SYNC came first
        sbegan(w) <= starts(w) + 1,
        sbegan(w) >= 0,
    )


def known(w: World) -> Term:
    """The node has books, or its life was admitted: its ``reach`` means something."""
    return z3.Or(w.c.phase != sym.JOINING, w.admitted)


def witnessed(w: World) -> Term:
    """(a) W (raw) at most tx, and at most the node's ``reach`` once its life is admitted;
    an open transaction is numbered from 1."""
    s = view(w).s
    return z3.And(
        z3.Implies(w.open, w.s.tx != 0),
        s.witness <= s.tx,  # signed: counts whose ltx reads below 0 set W there
        z3.Implies(known(w), s.witness <= reach(w) + w.shift_tx),
    )


def window(w: World) -> Term:
    """(a) The window: the highest transaction begun at most the supervisor's tx (of ``view``)
    and at most ``reach`` + B (counts move tx over numbers nothing took)."""
    return z3.And(
        ule(begun(w), view(w).tx),
        z3.Implies(w.open, begun(w) == w.tx),
        z3.Implies(known(w), ule(begun(w), reach(w) + B)),
    )


def window_at_start(w: World) -> Term:
    """(a) While a supervisor's start from an older image waits, the record the node holds is
    at most B behind the session at the start (residual (d) for the rest), and at or above it
    once the node answered that start's SYNC."""
    answered = z3.Implies(z3.And(behind(w), answers_this_start(w)), ule(begun(w), w.last))
    rolled_back = z3.Or(far_behind(w), far_behind_c(w), far_behind_rc(w))
    return z3.And(z3.Not(rolled_back), answered)


def epochs(w: World) -> Term:
    """(c) The session's epoch of ``H`` began at or below its tx (of ``view``), below an open
    transaction; a node with books outside a start holds an ltx at or above that base (it was
    in a start when the epoch began, and every confirmation and admission since is at or
    above it), so no frame of an earlier epoch (``sent_in``) is one it takes."""
    e = epoch_of(w)
    outside = z3.And(w.c.phase != sym.JOINING, z3.Not(starting(w.c)))
    return z3.And(
        e >= 0,
        ule(BASE_TX(e), view(w).tx),
        z3.Implies(w.open, z3.ULT(BASE_TX(e), w.tx)),
        z3.Implies(outside, ule(BASE_TX(e), w.last)),
    )


def unknown_rc(c: sym.Client) -> Term:
    """A record with books whose Rc is unknown and has no floor (its books say so)."""
    return z3.And(c.phase != sym.JOINING, wit.no_floor(c))


def reports(w: World) -> Term:
    """The node's record has books that report what it received: an Rc known (or kept as a
    floor) at least that (on the supervisor's scale, the wire's 24 bits its low bits)."""
    c = w.c
    known = z3.And(c.phase != sym.JOINING, z3.Not(unknown_rc(c)))
    rc_true = c.credited + w.roff
    return z3.And(known, w.received <= rc_true, w.roff % inv.GS_WRAP == 0)


def learned(w: World) -> Term:
    """While a start waits, what the node received is at most the Gs of the record the start
    resumes from, or its books report it (``reports``): the image is not from before grants
    the books cannot report (residual, ``reported``), and the books only raise Gs. A node that
    lost its books sends none in this start (the start ignores its JOIN)."""
    waits = z3.And(wit.in_start(w.s), w.c.phase != sym.JOINING)
    return z3.Implies(waits, z3.Or(covered(w, w.s.delivered), reports(w)))


def covered(w: World, gs: Term) -> Term:
    """A Gs ``gs`` holds what the node received, and what any transaction begun may still
    deliver to it (``H`` past the highest begun): a COMMIT of the discarded history the node
    may still take raises what it received no higher."""
    return z3.And(w.received <= gs, H(epoch_of(w), one(begun(w))) <= gs)


def reported(r: sym.Session, w: World) -> Term:
    """Residual (d) for what the node's books cannot report, as the supervisor's restore takes
    it: the image's Gs is at least what the node received, or the node's books report it (a
    copy from before its admission afresh, or from before grants a copy of its own record
    found behind lacks, is not covered), and then also what any transaction begun may still
    deliver (``covered``)."""
    return z3.Or(covered(w, r.delivered), reports(w))


def no_intention_unknown(w: World) -> Term:
    """A record learns its Rc with the first intention it takes: one that has not holds none."""
    return z3.And(
        *(
            z3.Implies(r.credited_unknown, z3.And(r.held_tx == 0, r.phase != sym.HOLDING))
            for r in (w.c, view(w).c)
        )
    )


def behind_gs(w: World) -> Term:
    """A supervisor's start waits from a record below the session at its start in Gs."""
    return z3.And(wit.in_start(w.s), w.s.delivered < spre(w).delivered)


def rc_scale(w: World) -> Term:
    """The node's Rc maps to the supervisor's Gs by whole wraps of the wire's 24 bits (an
    admission sets the offset from an intention's Gs, a floor adds one wrap): the books' low
    bits read the same on either scale (stated for z3, which does not find it in the proof of
    the books sent)."""
    wire = 1 << DELIVERED_BITS
    return z3.And(
        w.roff % inv.GS_WRAP == 0,
        (w.rc_true / Q) % wire == (w.c.credited / Q) % wire,
    )


def books_taken(w: World) -> Term:
    """A start that took the books answering its SYNC holds a Gs at least what the node
    received."""
    return z3.Implies(w.s.phase == sym.SYNC_BOOKS, w.received <= w.s.delivered)


def books_from_a_start(w: World) -> Term:
    """The books a start took came from the node's life now, still in a start that began since
    the supervisor's (no confirmation of it is sent until the counts are taken; it takes no
    intention meanwhile), or from an earlier one: this life is not admitted (the start ignores
    its JOIN)."""
    since = z3.And(starting(w.c), sbegan(w) <= starts(w))
    return z3.Implies(w.s.phase == sym.SYNC_BOOKS, z3.Or(since, z3.Not(w.admitted)))


def given_past(r: sym.Session, w: World) -> Term:
    """A session record ``r`` (an image, or the one a start resumes from) that has not passed
    the number of the node's pending return (not a draw, of ``view``) credited back only
    debits numbered below it, each given back, and that return was given besides."""
    c = view(w).c
    returning = z3.And(c.phase != sym.JOINING, c.return_pending > 0, z3.Not(c.pending_draw))
    below = z3.ULT(r.returns_credited - w.shift_seq, c.return_seq + w.off_seq)
    return z3.Implies(z3.And(returning, below), r.returned + c.return_pending <= w.given)


def image_given(w: World) -> Term:
    """While a start waits, the record it resumes from meets ``given_past``."""
    return z3.Implies(wit.in_start(w.s), given_past(w.s, w))


COPIES = "copies the node wrote"
SESSION_COPIES = "copies the supervisor wrote"
OWN_START = "a start from the supervisor's own record"


def fits(w: World) -> Term:
    """What the node's record holds with its held intention fits a record (the rules refuse an
    intention beyond ``USABLE_MAX_UJ``), of the record and of the one at its start."""
    records = (w.c, pre(w))
    return z3.And(
        *(z3.And(c.held_amount >= 0, c.usable + c.held_amount <= USABLE_MAX_UJ) for c in records)
    )


def copies(w: World) -> Term:
    """A copy the node wrote since its record last went back (``World.copied``) is an older
    image of the kind the restore step takes (``p_image``), and a start in progress began from
    the record at its start (one from another record ended the copies: ``went_back``)."""
    image = p_image(_ghost(w.copy, "copy"), w)
    plain = z3.Implies(starting(w.c), _same_books(w.c, pre(w)))
    return z3.Implies(_ghost(w.copied, "copied"), z3.And(image, plain))


def session_copies(w: World) -> Term:
    """A copy the supervisor wrote since its record of the node last went back
    (``World.scopied``) is an older image of the kind its restore step takes
    (``p_session_image``, with the answers that copy remembers), and no start in progress
    went on from an older image (``forked``: that ended them)."""
    image = p_session_image(
        _ghost(w.scopy, "scopy"), w, _ghost(w.scopy_join, "join"), _ghost(w.scopy_answer, "answer")
    )
    unforked = z3.Implies(wit.in_start(w.s), z3.Not(forked(w)))
    return z3.Implies(_ghost(w.scopied, "scopied"), z3.And(image, unforked))


def own_start(w: World) -> Term:
    """A start of the supervisor's that went on from its own record (a power loss, a re-sync:
    not ``forked``) holds every counter of that record at least where it stood at the start:
    what it confirms is then ahead of every copy written before."""
    then = replace(w, s=spre(w))
    ahead = z3.And(
        ule(then.tx, w.tx),
        ule(then.rc, w.rc),
        spre(w).delivered <= w.s.delivered,
        spre(w).returned <= w.s.returned,
    )
    return z3.Implies(z3.And(wit.in_start(w.s), z3.Not(forked(w))), ahead)


STATE: tuple[tuple[str, inv.Clause], ...] = (
    *((name, _REPLACED.get(name, _on_view(clause))) for name, clause in inv.STATE),
    ("epochs", epochs),
    ("Rc on the supervisor's scale", rc_scale),
    ("what the node received is learned", learned),
    ("no intention with Rc unknown", no_intention_unknown),
    ("books taken", books_taken),
    ("books from a start", books_from_a_start),
    ("returns given past an image", image_given),
    ("remembered JOIN", join_remembered),
    ("remembered answer", answer_remembered),
    ("records of the start", start_records),
    ("transactions taken", taken_records),
    ("witness", witnessed),
    ("window", window),
    ("window at a start", window_at_start),
    ("a record fits", fits),
    (OWN_START, own_start),
    (COPIES, copies),
    (SESSION_COPIES, session_copies),
)


def _returning(then: World) -> Term:
    """An image's pending return that is not a draw was debited first (a draw is not given
    back: ``pending_return``)."""
    return z3.Implies(z3.Not(then.c.pending_draw), inv.pending_return(then))


def _same_return(image: sym.Client, image_seq: Term, later: sym.Client, later_seq: Term) -> Term:
    """An image at the ``later`` record's return number had the same return pending there (or
    none, and the later record none either): the later one has at most had it acknowledged."""
    pending = later.return_pending > 0
    same = z3.And(
        image.return_pending == later.return_pending, image.pending_draw == later.pending_draw
    )
    return z3.Implies(image_seq == later_seq, z3.Implies(pending, same))


def p_image(r: sym.Client, w: World) -> Term:
    """An older image of the node's record: the hardened ``p_image`` against the record the
    invariant speaks of, well formed as a witnessed record (a pending draw is pending), with
    the outcome of the record at the same last transaction, and, when it has every debit of the
    record but one not acknowledged, no more than it holds less the credits since."""
    v = view(w)
    then = replace(v, c=r)
    return z3.And(
        inv.p_image(r, v, _returning),
        _record(r, z3.BoolVal(True)),
        z3.Implies(then.last == v.last, r.outcome == v.c.outcome),
        z3.Implies(z3.ULT(v.tx, then.last), r.outcome == sym.SETTLED),
        _lacks(r, then.seq, v.c, v.seq),
        resolved_taken(r, then.last, w),
        ule(then.seq, top(w)),  # a number a record of the node held
        _same_return(r, then.seq, v.c, v.seq),
        z3.Implies(z3.Not(r.pending_draw), r.return_pending <= w.given),  # given back then
    )


IMAGE_JOIN = (
    z3.BitVec("session_image.join_k", sym.COUNTER),
    z3.BitVec("session_image.join_q", sym.COUNTER),
    z3.Int("session_image.join_life"),
)
"""The ghosts of the ADMIT that an older image of the supervisor's record remembers as its last
JOIN's (``World.jk``): any, of an ADMIT it sent."""


IMAGE_ANSWER = (
    z3.BitVec("session_image.answer_k", sym.COUNTER),
    z3.Int("session_image.answer_start"),
)
"""The ghosts of the last answer to a start that an older image of the supervisor's record
remembers (``World.rk``): any, of an ADMIT it sent."""


def p_session_image(
    r: sym.Session,
    w: World,
    join: tuple[Term, Term, Term] = IMAGE_JOIN,
    answer: tuple[Term, Term] = IMAGE_ANSWER,
) -> Term:
    """An older image of the supervisor's record: the hardened ``p_session_image`` against
    ``view``, its last start answered above its number, and the ADMITs of its last JOIN
    admitted and its last start answered ones that were sent (``P`` holds of them now, as of
    every ADMIT sent); and a pending return of the node's numbered past its C was given back
    beside what it credited back (``given_past``). Its Gs is not said to meet ``H``: it may be
    of an earlier epoch."""
    then = replace(w, s=r)
    joined_life = join[2] >= 0
    own = z3.And(ule(join[0], then.tx), ule(join[1], then.rc))
    remembered_join = p_admit(remembered(r, *join, epoch_of(w)), w)
    sent = z3.Implies(r.join_seq != 0, z3.And(joined_life, own, remembered_join))
    last = answer_of(r, *answer, w.shift_seq, epoch_of(w))
    answer_own = z3.And(ule(answer[0], then.tx), answer[1] >= 0)
    answer_sent = z3.Implies(wit.may_repeat(r), z3.And(answer_own, p_admit(last, w)))
    image = inv.p_session_image(r, view(w), prophesied=False)
    return z3.And(image, answered(r), sent, answer_sent, given_past(r, w), decided_on_an_ack(r, w))


def _msg_on_view(clause: inv.MsgClause) -> inv.MsgClause:
    return lambda m, w: clause(m, view(w))


def p_debit(m: Msg, w: World) -> Term:
    """A DEBIT is one the codec takes (its flags and fields), from a life of the node; a draw,
    a RESUME or a SYNC's counts carries a debit number at most one past the supervisor's
    count, and a RESUME's pending return numbered next was debited first (as a RETURN). A
    RESUME or counts of the node's current start carries the start's number, nonce and phase
    (RESUMING, SYNCING), counts the ltx of the record that answers."""
    v, f = view(w), m.flags
    draw, resume, resume_draw = f == wit.DRAW, f == wit.START, f == wit.START | wit.DRAW
    counts, books, unknown = wit.is_counts(f), f == wit.BOOKS, f == wit.UNKNOWN_BOOKS
    numbered = z3.Or(draw, resume, resume_draw, counts)
    books_ = z3.Or(books, unknown)
    answer = z3.Or(counts, books_)  # a SYNC's answer
    # the low 24 bits of the Rc the books carry, as the node puts them on the wire (16 in the
    # number's field, 8 in the amount's): read in bits, not as integers (z3 gives up on that)
    low = m.rcl
    wire = z3.And(
        low == (m.rc / Q) % (1 << DELIVERED_BITS),
        m.w == z3.Int2BV(low, 16),
        m.amount == low / (1 << 16),
    )
    # (where the start's Gs is below what the node received; the checker splits the clause)
    books_rc = z3.And(w.received <= m.rc, m.rc % Q == 0, *wire.children())
    return z3.And(
        m.life >= 0,
        m.life <= w.life,
        m.start >= 0,
        m.start <= starts(w),
        m.sstart >= -1,
        m.sstart <= sstarts(w),
        z3.Implies(m.sstart >= 0, z3.Or(counts, books, unknown)),
        z3.Implies(current_sync(m, w), m.nonce == w.s.sync_nonce),
        z3.Or(numbered, books, unknown),
        z3.Implies(draw, z3.And(inv.amount_mj(m.amount), m.nonce == 0)),
        z3.Implies(resume, z3.And(m.amount >= 0, m.amount <= AMOUNT_MAX_MJ)),
        z3.Implies(resume_draw, inv.amount_mj(m.amount)),
        z3.Implies(counts, z3.And(m.amount >= 0, m.amount < 1 << 16)),
        z3.Implies(books, z3.And(m.amount >= 0, m.amount < 1 << 8)),
        z3.Implies(unknown, z3.And(m.amount == 0, m.w == 0)),
        z3.Implies(numbered, z3.And(ule(m.k, inv.one(v.rc)), m.w == low16(m.k))),
        z3.Implies(numbered, ule(m.k, top(w))),
        z3.Implies(
            z3.And(this_start(m, w), z3.Or(resume, resume_draw, counts)),
            z3.And(m.k == image_seq(w), m.nonce == w.c.nonce),
        ),
        z3.Implies(z3.And(this_start(m, w), z3.Or(resume, resume_draw)), w.c.phase == sym.RESUMING),
        z3.Implies(
            z3.And(this_start(m, w), counts),
            z3.And(w.c.phase == sym.SYNCING, z3.Int2BV(m.amount, 16) == low16(w.c.last_tx)),
        ),
        z3.Implies(
            z3.And(resume, m.amount > 0, m.k == inv.one(v.rc)),
            v.s.returned + m.amount * Q <= v.given,
        ),
        z3.Implies(counts, z3.And(z3.Int2BV(m.amount, 16) == low16(m.q), z3.ULT(m.q, inv.LIFE))),
        z3.Implies(numbered, z3.ULT(m.k, inv.LIFE)),  # a record's numbers (assumption 4)
        z3.Implies(z3.And(current_sync(m, w), counts, m.life == w.life), w.c.phase != sym.JOINING),
        z3.Implies(m.life == w.life, w.c.phase != sym.JOINING),  # a life joining sends none
        # a start of this life began after every frame of an earlier life
        z3.Implies(z3.And(m.life < w.life, starting(w.c)), m.start < starts(w)),
        # a life that began after its answer began in this start, whose JOIN waits for its end
        z3.Implies(z3.And(current_sync(m, w), answer, m.life < w.life), z3.Not(w.admitted)),
        z3.Implies(z3.And(current_sync(m, w), counts, behind(w)), ule(begun(w), m.q)),
        z3.Implies(z3.And(current_sync(m, w), counts, behind_c(w)), ule(top(w), one(m.k))),
        # counts of this life answering the supervisor's current start: the node is still in
        # a start (none of its starts since that start began is confirmed while it waits)
        z3.Implies(z3.And(current_sync(m, w), counts, m.life == w.life), starting(w.c)),
        # books and counts answering the supervisor's current start: of a start since it began
        z3.Implies(current_sync(m, w), m.start >= sbegan(w)),
        # counts answering the supervisor's current start: no record of this life has since
        # gone below their ltx (a confirmation waits for them; a restart keeps World.lhi)
        z3.Implies(z3.And(current_sync(m, w), counts, m.life == w.life), ule(m.q, reach(w))),
        # books answering the supervisor's current start: the node still in a start; while
        # that start is behind in Gs, the Rc they carry (or the Gs of the admission, unknown)
        # at least what the node received
        z3.Implies(z3.And(current_sync(m, w), books_, m.life == w.life), starting(w.c)),
        z3.Implies(z3.And(current_sync(m, w), books, w.s.delivered < w.received), books_rc),
        z3.Implies(z3.And(current_sync(m, w), unknown), w.received <= w.s.delivered),
    )


def _evidence(m: Msg, w: World, ahead: int) -> Term:
    """An ACK (``ahead`` 1) or a COMMITTED (0) names a transaction at most ``ahead`` past the
    node's ``reach`` (this life), or at most the admission of this life (an earlier one)."""
    v = view(w)
    most = reach(w) + ahead
    return z3.And(
        inv.p_ack(m, v),
        m.life >= 0,
        m.life <= w.life,
        z3.Implies(m.life == w.life, z3.And(w.c.phase != sym.JOINING, ule(m.k, most))),
        ule(m.k, taken(w)),  # of any life: a transaction the node took
        # a node in a start sends none: sent before it, by a record at most the one at the
        # start (whose ltx a confirmation of the start does not go below)
        z3.Implies(z3.And(m.life == w.life, starting(w.c)), ule(m.k, v.last + ahead)),
        z3.Implies(z3.And(m.life < w.life, w.admitted), ule(m.k, w.admitted_at)),
    )


def p_return(m: Msg, w: World) -> Term:
    """The hardened ``P``, and numbered at most the node's number (of ``view``) while it has
    books: a confirmation that moves C to it leaves no RETURN to credit."""
    v = view(w)
    return z3.And(inv.p_return(m, v), ule(m.k, top(w)))


def p_return_ack(m: Msg, w: World) -> Term:
    """The hardened ``P``, and numbered at most ``World.top``: it acknowledges a debit."""
    return z3.And(inv.p_return_ack(m, view(w)), ule(m.k, top(w)))


def p_aborted(m: Msg, w: World) -> Term:
    """The hardened ``P``, where the node's last transaction may also have been settled by a
    confirmation (found behind: admitted at it; or the first record's, confirmed at it) rather
    than aborted; of this life, a transaction the node took (``World.taken``)."""
    v = view(w)
    unresolved = z3.Or(v.c.outcome == sym.SETTLED, v.c.outcome == int(Outcome.NONE))
    settled = z3.And(m.life == w.life, m.k == v.last, unresolved)
    marked = replace(v, c=sym.pick(settled, replace(v.c, outcome=inv.ABORTED), v.c))
    aborted = z3.Implies(m.k == taken(w), took(w) == inv.ABORTED)
    took_it = z3.And(ule(m.k, taken(w)), m.k != 0, aborted)
    any_life = z3.And(ule(m.k, taken(w)), m.k != 0)  # of any life: a transaction it took
    return z3.And(inv.p_aborted(m, marked), any_life, z3.Implies(m.life == w.life, took_it))


def p_admit(m: Msg, w: World) -> Term:
    """An ADMIT answers a JOIN (``life`` the JOIN's: the hardened ``P``), or it is a SYNC or a
    start's confirmation (``life`` -1): its counters the supervisor's, then or earlier."""
    v = view(w)
    # a confirmation of a start the node has left: no node takes it (its nonce is that start's,
    # assumption 5), its counters as sent (a start of the supervisor's from an older image may
    # end below them)
    # a SYNC of a start of the supervisor's that has ended: the node answers a SYNC by its
    # nonce alone
    stale = z3.Or(
        z3.And(m.start >= 0, z3.Not(this_start(m, w))),
        z3.And(m.sstart >= 0, z3.Not(current_sync(m, w))),
    )
    ours = z3.And(
        z3.Or(m.start >= 0, m.sstart >= 0),  # a confirmation or a SYNC
        z3.Implies(z3.Not(stale), z3.And(ule(m.k, v.tx), ule(m.q, v.rc))),
        m.admit_tx == low16(m.k),
        m.admit_seq == low16(m.q),
        m.start >= -1,
        m.start <= starts(w),
        m.sstart >= -1,
        m.sstart <= sstarts(w),
        z3.Implies(m.sstart >= 0, m.start == -1),
        # no confirmation of a start of the node's since the supervisor's began is sent while
        # that start waits
        z3.Implies(z3.And(m.start >= 0, wit.in_start(w.s)), m.start < sbegan(w)),
        z3.Implies(
            current_sync(m, w),
            z3.And(m.nonce == w.s.sync_nonce, m.k == w.tx, m.q == w.rc),
        ),
        z3.Implies(z3.And(m.k == v.tx, z3.Not(stale)), z3.Not(v.open)),
        z3.Implies(
            this_start(m, w),
            z3.And(
                # Q at most one below any number a record of the node held, which C has
                # passed (a repeat of counts answers with Q and voids Q + 1)
                ule(top(w), one(m.q)),
                ule(top(w), v.rc),
                ule(taken(w), m.k),  # below the record at the start's ltx only settled ahead
                z3.Implies(w.admitted, ule(w.admitted_at, m.k)),
                m.epoch == epoch_of(w),  # sent in this epoch, at or above its base
                ule(BASE_TX(m.epoch), m.k),
                w.received <= H(m.epoch, one(m.k)),
                v.s.witness <= m.k + w.shift_tx,  # the window: nothing witnessed (signed)
                ule(begun(w), m.k + B),  # since it was sent, nor begun past it
                z3.Implies(w.c.phase == sym.SYNCING, ule(w.last, m.k)),
            ),
        ),
        z3.Implies(
            z3.And(this_start(m, w), confirms(m, w.c)),
            z3.And(
                confirmable(w),
                m.q == one(image_seq(w)),
                w.received - (pre(w).credited - w.c.credited) <= H(m.epoch, one(m.k)),
                z3.Implies(
                    z3.And(voided(w) > 0, z3.Not(pre(w).pending_draw)),
                    v.s.returned + voided(w) <= w.given,
                ),
            ),
        ),
    )
    answers_this_life = z3.And(m.life == w.life, z3.Not(v.booked))
    # an answer to a JOIN of an earlier life, or of this one once it has books: no node takes
    # it (assumption 5; a node with books reads it as a SYNC, by its nonce alone), its counters
    # on the wire as sent (a supervisor's start from an older image may end below them)
    wire = z3.And(m.admit_tx == low16(m.k), m.admit_seq == low16(m.q), m.life >= 0)
    inert = z3.Or(m.life < w.life, v.booked)
    join = z3.And(
        z3.If(inert, z3.And(wire, m.life <= w.life), inv.p_admit(m, v)),
        m.start == -1,
        m.sstart == -1,
        z3.Implies(answers_this_life, z3.And(ule(top(w), m.q), ule(taken(w), m.k))),
        z3.Implies(answers_this_life, z3.And(m.epoch == epoch_of(w), ule(BASE_TX(m.epoch), m.k))),
        # taken while a start waits, it leaves the node with books that report nothing: the
        # start's Gs holds what the node received (sent before the start: the supervisor's
        # restore takes it, residual ``reported``; none is sent during one)
        z3.Implies(z3.And(answers_this_life, wit.in_start(w.s)), covered(w, w.s.delivered)),
    )
    return z3.If(m.life == -1, ours, join)


def p_intention(m: Msg, w: World) -> Term:
    """The hardened ``P`` with "the node may still take it" read against the lower of its ltx
    and the higher of ``World.taken`` and this life's admission: an ltx settled ahead (a
    SYNC's answer) took nothing, and a confirmation of a start may set it back to the k it
    carries, at least both."""
    v = view(w)
    since = umax(taken(w), z3.If(w.admitted, w.admitted_at, sym.counter(0)))
    least = z3.If(ule(since, v.last), since, v.last)
    by_taken = replace(v, c=replace(v.c, last_tx=least - v.off_tx))
    return z3.And(inv.p_intention(m, by_taken), ule(m.k, begun(w)), sent_in(m, w))


def _begun(clause: inv.MsgClause) -> inv.MsgClause:
    """An INTENTION, COMMIT or ABORT names a transaction begun (``World.begun``)."""
    return lambda m, w: z3.And(clause(m, view(w)), ule(m.k, begun(w)), sent_in(m, w))


def p_commit(m: Msg, w: World) -> Term:
    """A COMMIT names a transaction begun and one the node took (the decision followed its
    ACK)."""
    return z3.And(_begun(inv.MESSAGE[Kind.COMMIT])(m, w), ule(m.k, taken(w)))


def sent_in(m: Msg, w: World) -> Term:
    """A supervisor's frame was sent in this epoch or an earlier one; of an earlier one, its
    transaction at most this epoch's base (counts that end a start take tx to the highest
    begun at least)."""
    e = epoch_of(w)
    earlier = z3.Implies(m.epoch != e, ule(m.k, BASE_TX(e)))
    return z3.And(m.epoch >= 0, m.epoch <= e, earlier)


MESSAGE: dict[Kind, inv.MsgClause] = {
    **{kind: _msg_on_view(p) for kind, p in inv.MESSAGE.items()},
    Kind.COMMIT: p_commit,
    Kind.ABORT: _begun(inv.MESSAGE[Kind.ABORT]),
    Kind.INTENTION: p_intention,
    Kind.ADMIT: p_admit,
    Kind.RETURN: p_return,
    Kind.RETURN_ACK: p_return_ack,
    Kind.ABORTED: p_aborted,
    Kind.DEBIT: p_debit,
    Kind.ACK: lambda m, w: _evidence(m, w, 1),
    Kind.COMMITTED: lambda m, w: _evidence(m, w, 0),
}


def deliverable(m: Msg, w: World) -> Term:
    """The hardened assumptions (an ADMIT that is a SYNC or a confirmation never matches a
    joining node's nonce: assumption 5); a DEBIT's debit number within 2**15 of the
    supervisor's count (books carry Rc instead), and the ltx that counts of the node's current
    start carry within 2**15 of the supervisor's tx."""
    if m.kind is Kind.DEBIT:
        age = z3.Implies(z3.Not(wit.is_books(m.flags)), inv.near(m.k, view(w).rc))
        counts = z3.And(this_start(m, w), wit.is_counts(m.flags))  # its ltx, as for a RESUME's q
        # counts answering the supervisor's current start, of any start of the node: their
        # ltx within 2**15 of its tx (assumption 3; the SYNC was sent at that tx)
        answering_now = z3.And(current_sync(m, w), wit.is_counts(m.flags))
        # counts that end a supervisor's start are read against the record it started from,
        # maybe an older image: their q within 2**15 of its C too (assumption 3 for an image)
        ending = z3.And(
            w.s.phase == sym.SYNC_BOOKS, m.nonce == w.s.sync_nonce, wit.is_counts(m.flags)
        )
        # the books and counts a start takes answer its own SYNC: the nonces of the
        # supervisor's starts differ, and from the node's (as assumption 5 asks of JOINs)
        books = z3.And(w.s.phase == sym.SYNCING, m.nonce == w.s.sync_nonce, wit.is_books(m.flags))
        # a RESUME that repeats the supervisor's last answered is of the start that answer
        # answered: a node's starts draw distinct nonces (assumption 5)
        resume = z3.Or(m.flags == wit.START, m.flags == wit.START | wit.DRAW)
        seq = sym.unwrap(m.w, w.s.returns_credited, SEQ_BITS)
        again = z3.And(resume, wit.repeats(w.s, wit.key_of(m.nonce, z3.BoolVal(False)), seq))
        # the Rc the books carry within 2**23 mJ of the supervisor's Gs (assumption 3, as an
        # INTENTION's Gs of the node's Rc)
        gap = m.rc / Q - w.s.delivered / Q
        half = 1 << (DELIVERED_BITS - 1)
        taken_books = z3.And(wit.in_start(w.s), m.nonce == w.s.sync_nonce, m.flags == wit.BOOKS)
        # (only where the start's Gs is below what the node received: the books then carry it)
        needed = z3.And(taken_books, w.s.delivered < w.received)
        rc_age = z3.Implies(needed, z3.And(gap < half, gap > -half))
        return z3.And(
            rc_age,
            z3.Implies(again, m.start == rstart(w)),
            age,
            z3.Implies(counts, inv.near(w.last, w.tx)),
            z3.Implies(answering_now, inv.near(m.q, w.tx)),
            z3.Implies(ending, inv.near(m.k, w.rc)),
            z3.Implies(z3.Or(ending, books), m.sstart == sstarts(w)),
        )
    if m.kind is Kind.ADMIT:
        ours = z3.And(starting(w.c), m.nonce == expected(w.c))
        real = z3.And(m.start == starts(w), inv.near(m.k, w.last))
        return z3.And(inv.deliverable(m, view(w)), z3.Implies(ours, real))
    return inv.deliverable(m, view(w))


def bounded(w: World) -> Term:
    """Bounded life (assumption 4), and the supervisor's C below the cap 2**30 - 1 where a
    start's void stops moving it (reached only after 2**16 voids past the end of the
    numbering), its tx below the same cap, where a SYNC's counts' ltx is held
    (``witnessed.ltx_of``): a lift at counts that find the node behind would otherwise move the
    proof's numbering back."""
    at_end = sym.counter(COUNTER_BOUND - 1)
    return z3.And(
        inv.bounded(w),
        inv.bounded(view(w)),
        z3.ULT(w.s.returns_credited, at_end),
        z3.ULT(w.s.tx, at_end),
    )


def resolved(before: World, after: World) -> Term:
    """The prophecy agrees with the run: when a transaction closes, or a SYNC's counts move tx
    up over numbers no transaction took, ``H`` of the next number, and of every number skipped,
    is Gs then (a number skipped is never begun: its ``H`` is fixed by the skip)."""
    before, after = view(before), view(after)
    skips = z3.And(z3.Not(after.open), z3.ULT(before.tx, after.tx))
    closes = z3.And(before.open, z3.Not(after.open))
    gs, e = after.s.delivered, epoch_of(after)
    return z3.And(
        z3.Implies(closes, gs == H(e, one(after.tx))),
        z3.Implies(skips, z3.And(gs == H(e, one(after.tx)), gs == H(e, one(before.tx)))),
    )


def invariant(w: World) -> Term:
    return z3.And(*(clause(w) for _, clause in STATE))


# -- the steps -----------------------------------------------------------------------------------


def client_sent(w: World, frames: wit.Frames) -> tuple[tuple[Term, Msg], ...]:
    """Both frames a client step sends, a DEBIT among the kinds."""
    out: list[tuple[Term, Msg]] = []
    for sent in frames:
        out += st.client_sent(w, sent)
        k = sym.unwrap(sent.a, w.c.return_seq, SEQ_BITS) + w.off_seq
        debit = st._msg(
            Kind.DEBIT,
            w=sent.a,
            amount=sent.b,
            flags=sent.c,
            nonce=sent.d,
            k=k,
            life=w.life,
            q=w.last,  # counts: the ltx they carry, canonical
            rc=w.rc_true,  # books: the Rc they carry, on the supervisor's scale
            rcl=(w.c.credited / Q) % (1 << DELIVERED_BITS),  # and its low bits on the wire
            start=starts(w),
            sstart=z3.If(w.c.phase == sym.SYNCING, answering(w), -1),
        )
        out.append((st._is(sent, Kind.DEBIT), debit))
    return tuple(out)


def _moved(
    w: World,
    c: sym.Client,
    gave: Term = 0,
    replaced: bool = False,
    unreceived: Term = 0,
    restarted: Term | None = None,
    confirmed: Term | None = None,
    answers: Term | None = None,
    resolves: bool = False,
    **ghost: Term,
) -> World:
    """The world after a client step: what counts for the node moved by ``net`` (plus what the
    actuator was released and what was given back, less what was ``unreceived``); a gain is
    received, a loss lost. A start keeps the record it began from (``pre``; a confirmation
    followed by the counts, ``confirmed``, starts again from the confirmed record) and counts
    as one more start (``restarted``, default: a start begun). What the record's ``spent``
    grew by is what the actuator used, in any phase (a record ``replaced`` by an older image
    used nothing). ``answers``: the supervisor's start whose SYNC the node answers now (None:
    the one it answered, while it still answers one)."""
    began = z3.And(starting(c), z3.Not(starting(w.c)))
    at_start = sym.client_power_loss(w.c)[0]
    again = z3.BoolVal(False) if confirmed is None else confirmed
    confirmed_record = replace(c, phase=sym.IDLE, nonce=z3.BitVecVal(0, 16))
    new_pre = sym.pick(began, at_start, sym.pick(again, confirmed_record, pre(w)))
    more = z3.Or(began, again) if restarted is None else z3.Or(began, again, restarted)
    assert w.starts is not None and w.top is not None
    sync = answering(w) if answers is None else answers
    answered = z3.If(c.phase == sym.SYNCING, sync, -1)
    after = replace(
        w, c=c, pre=new_pre, starts=w.starts + z3.If(more, 1, 0), answering=answered, **ghost
    )
    held_seq = c.return_seq + after.off_seq
    higher = z3.And(c.phase != sym.JOINING, z3.UGT(held_seq, w.top))
    after = replace(after, top=z3.If(higher, held_seq, w.top))
    # the highest ltx of the start's records: from the record at the start on, each record
    # the node answered or was put back to since; a confirmation followed by the counts
    # starts again from the confirmed record
    base = z3.If(again, after.last, z3.If(starting(w.c), lhi(w), w.last))
    now = after.last
    after = replace(after, lhi=umax(now, base))
    # the highest transaction taken: an intention held, and the ltx a step that ``resolves``
    # (a COMMIT, an ABORT, a timeout-commit) moves to
    most, how = taken(w), took(w)
    if resolves:
        moved = z3.And(c.last_tx != w.c.last_tx, z3.UGE(after.last, most))
        most, how = z3.If(moved, after.last, most), z3.If(moved, c.outcome, how)
    held = z3.And(holding(c), z3.UGT(after.held, most))
    none = z3.IntVal(int(Outcome.NONE))
    after = replace(after, taken=z3.If(held, after.held, most), took=z3.If(held, none, how))
    grown = c.spent - w.c.spent
    used = z3.IntVal(0) if replaced else z3.If(grown > 0, grown, 0)
    net = counted(after) - counted(w) + used + gave + unreceived
    after = replace(
        after,
        received=w.received + z3.If(net > 0, net, 0) - unreceived,
        lost=w.lost + z3.If(net < 0, -net, 0),
        spent=w.spent + used,
        given=w.given + gave,
    )
    v = view(after)
    committed = z3.And(v.booked, v.last == v.tx, v.c.outcome == COMMITTED)
    return replace(after, cc=z3.Or(w.cc, committed))


def _client(
    w: World,
    result: tuple[sym.Client, wit.Frames],
    replaced: bool = False,
    resolves: bool = False,
    **ghost: Any,
) -> st.Step:
    c, frames = result
    after = _moved(w, c, replaced=replaced, resolves=resolves, **ghost)
    return st.Step(after, client_sent(after, frames), z3.BoolVal(True), z3.IntVal(0))


def on_intention(w: World, m: Msg) -> st.Step:
    c, frames = wit.on_intention(w.c, m.w, m.amount, m.gs)
    learned = z3.And(w.c.credited_unknown, z3.Not(c.credited_unknown))
    roff = z3.If(learned, H(msg_epoch(m, w), m.k) - c.credited, w.roff)
    step = _client(w, (c, frames), roff=roff)
    lemmas = [(n, z3.Implies(z3.Not(starting(w.c)), x)) for n, x in st.on_intention(w, m).lemmas]
    return replace(step, lemmas=tuple(lemmas))


def on_admit(w: World, m: Msg) -> st.Step:
    """A JOIN's admission, a start's confirmation (kept, or found behind: counted afresh), or a
    SYNC; the ghost numbering follows an admission as under the hardened rules."""
    c = w.c
    c2, frames = wit.on_admit(c, m.nonce, m.admit_tx, m.admit_seq)
    joined = z3.And(c.phase == sym.JOINING, m.nonce == c.nonce)
    syncing = c.phase == sym.SYNCING
    expected = z3.If(syncing, c.nonce ^ SYNC_CONFIRMED, c.nonce)
    q = sym.unwrap(m.admit_seq, c.return_seq, SEQ_BITS)
    behind = z3.And(
        starting(c),
        m.nonce == expected,
        q - c.return_seq > 1,
        z3.Not(z3.UGE(q, sym.counter(COUNTER_BOUND))),
    )
    fresh = z3.Or(joined, behind)
    off_tx = z3.If(fresh, m.k - z3.ZeroExt(16, m.admit_tx), w.off_tx)
    off_seq = z3.If(joined, m.q - z3.ZeroExt(16, m.admit_seq), z3.If(behind, m.q - q, w.off_seq))
    # found behind: the floor (``witnessed.floor_of``) on the supervisor's scale as the Rc was
    roff = z3.If(joined, z3.IntVal(0), z3.If(behind, w.roff - (c2.credited - c.credited), w.roff))
    kept = z3.And(
        starting(c),
        m.nonce == expected,
        q - c.return_seq == 1,
        z3.Not(z3.UGE(q, sym.counter(COUNTER_BOUND))),
    )
    # kept: the credits the record started from lacks are no longer received (the supervisor
    # pays them back from Gs), and a return of the record at the start that this
    # confirmation voids was given back and came back
    p = pre(w)
    returned_back = z3.And(kept, voided(w) > 0, z3.Not(p.pending_draw))
    # a SYNC answered now (not the same one again, not a confirmation's counts)
    again = z3.And(syncing, m.nonce == c.nonce)
    new_sync = z3.And(
        z3.Extract(15, 15, m.nonce) == 0,
        z3.Or(wit.booked(c), z3.And(starting(c), m.nonce != expected, z3.Not(again))),
    )
    answers = z3.If(new_sync, m.sstart, z3.If(z3.And(kept, starting(c2)), -1, answering(w)))
    return _client(
        w,
        (c2, frames),
        gave=z3.If(returned_back, -voided(w), 0),
        unreceived=z3.If(kept, p.credited - c.credited, 0),
        restarted=z3.And(
            starting(c2), z3.Or(c2.phase != c.phase, c2.nonce != c.nonce, z3.Not(starting(c)))
        ),
        confirmed=z3.And(kept, starting(c2)),
        answers=answers,
        off_tx=off_tx,
        off_seq=off_seq,
        roff=roff,
    )


def draw(w: World, amount: Term) -> st.Step:
    c, sent, allowed = wit.draw(w.c, amount)
    after = _moved(w, c)
    return st.Step(after, client_sent(after, wit.one(sent)), allowed, z3.IntVal(0))


def give_back(w: World, amount: Term) -> st.Step:
    c, sent, allowed = wit.give_back(w.c, amount)
    after = _moved(w, c, gave=amount)
    return st.Step(after, client_sent(after, wit.one(sent)), allowed, z3.IntVal(0))


def books_lost(w: World, nonce: Term) -> st.Step:
    c, frames = wit.books_lost(w.c, nonce)
    zero32 = sym.counter(0)
    after = replace(
        w,
        c=c,
        lost=w.lost + counted(w),
        life=w.life + 1,
        admitted=z3.BoolVal(False),
        off_tx=zero32,
        off_seq=zero32,
        roff=z3.IntVal(0),
    )
    return st.Step(after, client_sent(after, frames), z3.BoolVal(True), z3.IntVal(0))


def restore(w: World, image: sym.Client, nonce: Term) -> st.Step:
    """The node's record put back to an older ``image`` and the node started from it, as after a
    power loss: RESUMING, what it held before parked (the image's Uc counts only once the
    supervisor confirms it)."""
    return _client(w, wit.power_loss(image, nonce), replaced=True, restarted=z3.BoolVal(True))


def copy_of(c: sym.Client) -> sym.Client:
    """The node's record as a restore starts from it: its held intention dropped (a start drops
    it, ``witnessed.power_loss``), so a copy written while it holds one is this one."""
    return sym._drop_hold(c)


WRITE_COPY = "client: a copy of its record written (a backup)"


def write_copy(w: World) -> st.Step:
    """Someone copies the node's record (a backup, an NV read-out): any time it has books. It
    changes nothing else; a restore may start from it later. The copy is of the kind the
    restore step takes when ``copy_covered``."""
    after = replace(w, copy=copy_of(w.c), copied=copy_covered(w))
    return st.Step(after, (), w.booked, z3.IntVal(0))


def copy_covered(w: World) -> Term:
    """A copy of the node's record is inside the theorem when written while no start of its
    waits, or while one waits holding the books of the record it began from (its own start
    after a power loss, RESUMING, or its answer to a SYNC of the supervisor's, SYNCING) with
    the supervisor not behind it (its tx at or above the node's ltx: no restore of the
    supervisor's). Not while a start from an older image waits."""
    v = view(w)
    return z3.Or(z3.Not(starting(w.c)), z3.And(_same_books(w.c, pre(w)), ule(v.last, v.tx)))


def went_back(before: World, after: World) -> Term:
    """The node's record went back: a new life, its Rc learned, its numbering or the
    supervisor's moved (a start of the supervisor's found it behind), the counts that end a
    start of the supervisor's from an older image (``forked``: a new epoch of ``H`` from a
    restore; one from its own record keeps them); the record the invariant speaks of is
    behind the one before in Rc, a debit, what its actuator used, ltx or return number, or its
    last transaction was settled anew (by the counts of a start); or a start begins or goes on
    from a record other than the one the invariant speaks of (an older image, a SYNC's
    settling). Copies written before are no longer of the kind the restore step takes
    (``World.copied``)."""
    b, a = view(before), view(after)
    return z3.Or(
        before.life != after.life,
        before.admitted_at != after.admitted_at,
        before.off_tx != after.off_tx,
        before.off_seq != after.off_seq,
        before.roff != after.roff,
        before.shift_tx != after.shift_tx,  # the supervisor's numbering moved
        before.shift_seq != after.shift_seq,
        z3.And(epoch_of(before) != epoch_of(after), forked(after)),  # counts ended a start
        b.c.credited_unknown != a.c.credited_unknown,
        a.c.credited < b.c.credited,
        a.c.usable - a.c.credited > b.c.usable - b.c.credited,  # a debit undone
        a.c.spent < b.c.spent,
        z3.ULT(a.last, b.last),
        z3.And(a.last == b.last, a.c.outcome != b.c.outcome),  # settled anew by counts
        z3.ULT(a.seq, b.seq),
        z3.And(starting(after.c), z3.Not(_same_books(after.c, b.c))),  # a start from another
    )


_BOOKS = (
    "usable", "credited", "spent", "last_tx", "outcome", "return_seq", "return_pending",
    "pending_draw", "credited_unknown",
)  # fmt: skip
"""The fields of a node's record a start keeps (not its phase, nonce or held intention)."""


def _same_books(a: sym.Client, b: sym.Client) -> Term:
    return z3.And(*(getattr(a, f) == getattr(b, f) for f in _BOOKS))


def keep_copies(before: World, step: st.Step) -> st.Step:
    """``step`` with each side's copies kept as long as that side's record did not go back
    (``went_back``, ``session_went_back``)."""
    after = step.after
    node = z3.And(_ghost(after.copied, "copied"), z3.Not(went_back(before, after)))
    supervisor = z3.Not(session_went_back(before, after))
    kept = replace(after, copied=node, scopied=z3.And(_ghost(after.scopied, "scopied"), supervisor))
    return replace(step, after=kept)


# -- the supervisor's steps ----------------------------------------------------------------------


def _session(
    w: World,
    step: sym.SessionStep,
    life: Term | None = None,
    start: Term | None = None,
    **ghost: Term,
) -> st.Step:
    """A supervisor step; an ADMIT it sends answers the JOIN of ``life``, or (None) is a SYNC
    or a start's confirmation (ghost life -1), that of the node's ``start`` (None: -1)."""
    after = replace(w, s=step.session, **ghost)
    answers = z3.IntVal(-1) if life is None else life
    sent = st.supervisor_sent(after, step.sent, answers)
    sync = z3.If(wit.in_start(after.s), sstarts(after), -1)  # a SYNC: the start it is sent in
    sent = tuple((cond, replace(m, sstart=sync) if m.kind is Kind.ADMIT else m) for cond, m in sent)
    if start is not None:  # a confirmation: k the last transaction closed (Q: ``on_debit``)
        closed = z3.If(after.s.phase == sym.S_IDLE, after.tx, after.tx - 1)
        sent = tuple(
            (cond, replace(m, start=start, k=closed)) if m.kind is Kind.ADMIT else (cond, m)
            for cond, m in sent
        )
    return st.Step(after, sent, z3.BoolVal(True), step.credit)


def _lift(s: sym.Session) -> tuple[Term, Term]:
    """How far an admission lifts tx and C (the high half, invisible on the wire)."""
    lifted = sym.admit(s, z3.BitVecVal(0, 16)).session
    return lifted.tx - s.tx, lifted.returns_credited - s.returns_credited


def on_join(w: World, m: Msg) -> st.Step:
    """A JOIN outside a start, or in a re-sync (which it ends): admitted afresh (its ADMIT
    remembered with its ghosts), or, a copy of the last JOIN admitted, that ADMIT sent again
    (its ghosts the remembered ones); at a start: ignored."""
    step = wit.admit(w.s, m.nonce)
    copy = z3.And(w.s.join_seq != 0, w.s.join_nonce == m.nonce)
    taken = z3.And(z3.Or(z3.Not(wit.in_start(w.s)), w.s.resync), z3.Not(copy))
    lift_tx, lift_seq = _lift(w.s)
    zero = sym.counter(0)
    shift_tx = w.shift_tx + z3.If(taken, lift_tx, zero)
    shift_seq = w.shift_seq + z3.If(taken, lift_seq, zero)
    first = z3.And(taken, m.life == w.life, z3.Not(w.admitted))
    admitted_at = z3.If(first, step.session.tx - shift_tx, w.admitted_at)
    again = joined(w)
    out = _session(
        w,
        step,
        m.life,
        shift_tx=shift_tx,
        shift_seq=shift_seq,
        admitted=z3.Or(w.admitted, first),
        admitted_at=admitted_at,
        jk=z3.If(taken, step.session.tx - shift_tx, again.k),
        jq=z3.If(taken, step.session.returns_credited - shift_seq, again.q),
        jlife=z3.If(taken, m.life, again.life),
    )
    sent = tuple(
        (
            cond,
            replace(
                msg,
                k=z3.If(copy, again.k, msg.k),
                q=z3.If(copy, again.q, msg.q),
                life=z3.If(copy, again.life, msg.life),
            )
            if msg.kind is Kind.ADMIT
            else msg,
        )
        for cond, msg in out.sent
    )
    return replace(out, sent=sent)


def next_epoch(w: World, ends_a_start: Term) -> Term:
    """Counts that end a supervisor's start begin the next epoch of ``H``."""
    return epoch_of(w) + z3.If(ends_a_start, 1, 0)


def on_debit(w: World, m: Msg) -> st.Step:
    """A DEBIT: a draw held, a RESUME or a SYNC's counts confirmed (lifted as for a JOIN when
    the node is behind), a SYNC's books taken."""
    s = w.s
    step = wit.on_debit(s, m.nonce, m.flags, m.w, m.amount)
    counts = wit.is_counts(m.flags)
    resumes = z3.And(
        z3.Not(wit.in_start(s)),
        z3.Not(wit.is_books(m.flags)),
        (m.flags / wit.START) % 2 == 1,
        z3.Or(z3.Not(counts), wit.counts_taken(s, m.nonce, m.amount)),  # ignored: no lift
    )
    counted_ = z3.And(s.phase == sym.SYNC_BOOKS, m.nonce == s.sync_nonce, counts)
    seq = sym.unwrap(m.w, s.returns_credited, SEQ_BITS)
    repeat = wit.repeats(s, wit.key_of(m.nonce, counts), seq)
    lifted = z3.And(z3.Or(resumes, counted_), seq - s.returns_credited < 0, z3.Not(repeat))
    lift_tx, lift_seq = _lift(s)
    zero = sym.counter(0)
    epoch = next_epoch(w, counted_)
    taken = _session(
        w,
        step,
        # a repeat sends the last answer again: of the start it answered (a start of the node's
        # with the same nonce is another only against assumption 5)
        start=z3.If(repeat, rstart(w), m.start),
        shift_tx=w.shift_tx + z3.If(lifted, lift_tx, zero),
        shift_seq=w.shift_seq + z3.If(lifted, lift_seq, zero),
        epoch=epoch,
    )
    after = taken.after
    # the new epoch's H is the Gs the counts leave, up to one past the tx they leave
    based = z3.And(BASE_TX(epoch) == after.tx, BASE_GS(epoch) == after.s.delivered)
    began = epoch != epoch_of(w)
    taken = replace(taken, enabled=z3.And(taken.enabled, z3.Implies(began, based)))
    fresh_answer = z3.And(z3.Or(resumes, counted_), z3.Not(repeat))
    # counts that end a start from an older image may set tx below this life's admission (both
    # records from before it): the life counts as admitted at the confirmation's k then
    lowered = z3.And(counted_, w.admitted, z3.ULT(after.tx, w.admitted_at))
    after = replace(
        after,
        rk=z3.If(fresh_answer, after.tx, rk(w)),
        rstart=z3.If(fresh_answer, m.start, rstart(w)),
        admitted_at=z3.If(lowered, after.tx, w.admitted_at),
    )

    # the C a confirmation carries (canonical): C after it, or a repeat's, the C before it
    # (the last answer's: a repeat of counts voids C + 1 after its answer)
    q = z3.If(repeat, w.rc, after.rc)
    sent = tuple((c, replace(x, q=q) if x.kind is Kind.ADMIT else x) for c, x in taken.sent)
    taken = replace(taken, after=after, sent=sent)
    leave_begun = z3.Implies(counted_, ule(begun(w), after.tx))
    # and at or above the last of a node that waits for this start's SYNC (a fact z3 takes in
    # seconds, where the remembered answer's P stated with it took 61 to over 1,500 million of
    # its steps by seed and process; docs/protocol.md, assumption 2)
    syncing = z3.And(counted_, this_start(m, w), w.c.phase == sym.SYNCING)
    leave_last = z3.Implies(syncing, ule(w.last, after.tx))
    last = last_answer(w)
    same_q = z3.And(
        *(z3.Implies(c, x.admit_seq == last.admit_seq) for c, x in sent if x.kind is Kind.ADMIT)
    )
    as_it_did = z3.Implies(
        z3.And(this_start(last, w), confirms(last, w.c)),
        z3.And(confirmable(w), last.q == one(image_seq(w))),
    )
    # books taken where the start's Gs is below what the node received: their two fields read
    # as the low bits the node put (P of the DEBIT), which unwrap to its Rc (assumption 3)
    needed = z3.And(
        s.phase == sym.SYNCING,
        m.nonce == s.sync_nonce,
        m.flags == wit.BOOKS,
        s.delivered < w.received,
    )
    paid = wit.ahead_of_image(s, m.flags, m.w)
    moved = after.s.delivered == s.delivered + paid
    read_mj = z3.BV2Int(m.w) + m.amount * (1 << 16)
    unwrapped = sym.unwrap_int(read_mj, s.delivered / Q, DELIVERED_BITS) * Q
    lemmas = (
        # what counts afresh move from Us to Gs (``witnessed.ahead_of_image``) is a whole number
        # of quanta: without it z3 did not decide Gs whole after them (400 million steps)
        ("lemma: counts afresh pay whole quanta", inv.whole(paid)),
        ("lemma: counts a start takes move Gs by what they pay", z3.Implies(counted_, moved)),
        ("lemma: C does not go back", ule(w.rc, after.rc)),
        ("lemma: tx does not go back", ule(w.tx, after.tx)),
        # so a frame of the epoch the counts end names a transaction at most the next's base
        ("lemma: counts that end a start leave tx at or above begun", leave_begun),
        ("lemma: counts that end a start leave tx at or above a syncing node's last", leave_last),
        ("lemma: the books' fields read as their low bits", z3.Implies(needed, read_mj == m.rcl)),
        ("lemma: the books' Rc unwrapped", z3.Implies(needed, unwrapped == m.rc)),
        # a repeat is the last answer again (k aside): Q as it read, to the start it answered
        ("lemma: a repeat sends the last answer's Q", z3.Implies(repeat, same_q)),
        ("lemma: the last answer confirms as it did", z3.Implies(repeat, as_it_did)),
    )
    lifts = seq - s.returns_credited < 0
    valid = (
        st.Valid(
            "valid: Gs whole after a whole payment",
            lambda d, p, e: z3.Implies(
                z3.And(inv.whole(d), inv.whole(p), e == d + p), inv.whole(e)
            ),
            (s.delivered, paid, after.s.delivered),
        ),
    )
    branches = _debit_branches(w, m, repeat, lifts)
    return replace(taken, lemmas=lemmas, valid=valid, branches=branches)


def _debit_branches(w: World, m: Msg, repeat: Term, lifts: Term) -> tuple[tuple[str, Term], ...]:
    """The DEBIT's branches: outside a start a draw, books, and a RESUME or late counts; in a
    start the books awaited, the books again, the counts that end a re-sync, a start from an
    older image or another start, and anything else after the books. A RESUME and counts are
    each answered again (``repeat``), found behind (``lifts``: numbered below C) or afresh."""
    s, f = w.s, m.flags
    outside, books = z3.Not(wit.in_start(s)), wit.is_books(f)
    counts, resumes = wit.is_counts(f), (f / wit.START) % 2 == 1
    after_books = s.phase == sym.SYNC_BOOKS
    ending = z3.And(after_books, m.nonce == s.sync_nonce, counts)
    answers = (
        ("again", repeat),
        ("found behind", z3.And(z3.Not(repeat), lifts)),
        ("afresh", z3.And(z3.Not(repeat), z3.Not(lifts))),
    )
    image = behind(w)
    answered = (
        ("a RESUME", z3.And(outside, z3.Not(books), resumes, z3.Not(counts))),
        ("late counts", z3.And(outside, counts)),
        ("counts that end a re-sync", z3.And(ending, s.resync)),
        ("counts that end a start from an older image", z3.And(ending, z3.Not(s.resync), image)),
        ("counts that end another start", z3.And(ending, z3.Not(s.resync), z3.Not(image))),
    )
    return (
        ("a draw", z3.And(outside, z3.Not(books), z3.Not(resumes))),
        *((f"{what}, {how}", z3.And(cond, a)) for what, cond in answered for how, a in answers),
        ("books outside a start", z3.And(outside, books)),
        ("a frame while the books are awaited", s.phase == sym.SYNCING),
        ("the books again", z3.And(after_books, books)),
        ("anything else after the books", z3.And(after_books, z3.Not(ending), z3.Not(books))),
    )


def begin(w: World, amount: Term) -> st.Step:
    step = _session(w, sym.begin(w.s, amount), cc=z3.BoolVal(False))
    step = replace(step, after=replace(step.after, begun=step.after.tx))
    most = AMOUNT_MAX_MJ * QUANTUM_UJ
    valid = z3.And(amount % QUANTUM_UJ == 0, amount >= QUANTUM_UJ, amount <= most)
    return replace(step, enabled=z3.And(w.s.phase == sym.S_IDLE, valid, wit.may_begin(w.s)))


def decide(commit: bool) -> st.Local:
    def decided(w: World) -> st.Step:
        step = _session(w, sym.decide(w.s, commit))
        return replace(step, enabled=w.s.phase == sym.ACKED)

    return decided


def restore_supervisor(
    w: World,
    image: sym.Session,
    nonce: Term,
    join: tuple[Term, Term, Term] | None = None,
    answer: tuple[Term, Term] | None = None,
) -> st.Step:
    """The supervisor's state file put back to an older ``image`` and started from it (a SYNC
    start): Us comes back with the file, so the session moves into Us what its books count less
    in the image. The session as it stood (what was open written off) is kept as the one at
    the start, unless a start already waits. ``join``: the ghosts of the ADMIT the image
    remembers as its last JOIN's (None: the record's own, a power loss)."""
    step = wit.start(image, nonce)
    idle = {"phase": sym.S_IDLE, "sync_nonce": z3.BitVecVal(0, 16)}
    latest = replace(wit.start(w.s, nonce).session, **idle)
    at_start = sym.pick(wit.in_start(w.s), spre(w), latest)
    after = replace(
        w,
        s=step.session,
        spre=at_start,
        cc=z3.And(w.cc, step.session.tx == w.s.tx),
        sstarts=sstarts(w) + 1,
        sbegan=starts(w) + 1,
        sforked=z3.Or(join is not None, z3.And(wit.in_start(w.s), forked(w))),
    )
    if join is not None:
        after = replace(after, jk=join[0], jq=join[1], jlife=join[2])
    if answer is not None:
        after = replace(after, rk=answer[0], rstart=answer[1])
    books = image.reserved + image.delivered - image.returned
    now = w.s.reserved + w.s.delivered - w.s.returned
    sent = st.supervisor_sent(after, step.sent, z3.IntVal(-1))
    return st.Step(after, sent, z3.BoolVal(True), now - books + step.credit)


WRITE_SESSION_COPY = "supervisor: a copy of its state file written (a backup)"


def write_session_copy(w: World) -> st.Step:
    """Someone copies the supervisor's state file (a backup, a VM snapshot) at any time, with
    the answers it remembers; ACKED is stored as WAIT_ACK and a start's phases as IDLE (its
    nonce is volatile). It changes nothing else; a restore may start from it later. The copy
    is of the kind the restore step takes when ``session_copy_covered``."""
    waits = wit.in_start(w.s)
    acked = w.s.phase == sym.ACKED
    phase = z3.If(acked, sym.WAIT_ACK, z3.If(waits, sym.S_IDLE, w.s.phase))
    nonce = z3.If(waits, z3.BitVecVal(0, 16), w.s.sync_nonce)
    copy = replace(w.s, phase=phase, sync_nonce=nonce, resync=z3.And(z3.Not(waits), w.s.resync))
    join = (_ghost(w.jk, "jk"), _ghost(w.jq, "jq"), _ghost(w.jlife, "jlife"))
    answer = (_ghost(w.rk, "rk"), _ghost(w.rstart, "rstart"))
    covered = session_copy_covered(w)
    after = replace(w, scopy=copy, scopied=covered, scopy_join=join, scopy_answer=answer)
    return st.Step(after, (), z3.BoolVal(True), z3.IntVal(0))


def session_copy_covered(w: World) -> Term:
    """A copy of the supervisor's state file is inside the theorem when written while no start
    of its waits for the node, or while a start from its own record waits (a power loss, a
    re-sync: not ``forked``) with the session's books still as they stood when it began (the
    node's books not taken, or taken without raising Gs). Not while a start from an older image
    waits, nor once the node's books raised Gs in that start."""
    own = z3.And(z3.Not(forked(w)), _as_it_stood(w.s, spre(w)))
    return z3.Or(z3.Not(wit.in_start(w.s)), own)


_SESSION_BOOKS = (
    "tx", "reserved", "delivered", "decision", "returns_credited", "returned", "resume_nonce",
    "resume_from", "resume_to", "witness", "join_nonce", "join_tx", "join_seq",
)  # fmt: skip
"""The fields of a session a copy must hold as they stood at the start: those its state file
keeps, not its phase in a start, its nonce or whether it is a re-sync; and the witness W, which
the file does not keep: a copy reloads it as 0, at or below the W asked for here (a window
only narrower), and the counts that end the start it begins set it (``witnessed``)."""


def _as_it_stood(s: sym.Session, at_start: sym.Session) -> Term:
    return z3.And(*(getattr(s, f) == getattr(at_start, f) for f in _SESSION_BOOKS))


def forked(w: World) -> Term:
    return _ghost(w.sforked, "knows whether the supervisor's start went on from an image")


def session_went_back(before: World, after: World) -> Term:
    """The supervisor's record of the node went back or was re-based: a start of its goes on
    from an older image (``forked``: it begins from one, a restore turns a start into one, or
    the counts that end one begin an epoch), its numbering moved, or its tx or C is behind.
    Copies written before are no longer of the kind its restore step takes
    (``World.scopied``): a copy newer than the image a start went on from is ahead of the
    books its counts confirm. A start from its own record (a power loss, a re-sync) keeps
    them: it holds every counter at least where it stood (``own_start``)."""
    b, a = view(before), view(after)
    begins = z3.And(wit.in_start(after.s), z3.Not(wit.in_start(before.s)))
    epoch = epoch_of(before) != epoch_of(after)
    return z3.Or(
        before.shift_tx != after.shift_tx,
        before.shift_seq != after.shift_seq,
        z3.And(forked(after), z3.Or(begins, z3.Not(forked(before)), epoch)),
        z3.ULT(a.tx, b.tx),
        z3.ULT(a.rc, b.rc),
    )


RESYNC = "supervisor re-syncs a node"


def resync(w: World, nonce: Term) -> st.Step:
    """The supervisor re-syncs the node (its choice, from IDLE, any fresh nonce): a start of
    this session alone, without restore and without write-off. Its ghosts are a start's: the
    session at the start is the session as it stands (``World.spre``), and the re-sync counts
    as one more of the supervisor's starts (``World.sstarts``): its SYNC carries it, so only
    the books and counts answering this SYNC are taken (``deliverable``, assumption 5: the
    nonce is drawn fresh, as a start's)."""
    step = wit.resync_session(w.s, nonce)
    at_start = replace(w.s, sync_nonce=z3.BitVecVal(0, 16), resync=z3.BoolVal(False))
    out = _session(
        w, step, spre=at_start, sstarts=sstarts(w) + 1, sbegan=starts(w) + 1,
        sforked=z3.BoolVal(False),
    )  # fmt: skip
    return replace(out, enabled=wit.may_resync(w.s))


def deliveries() -> dict[Kind, st.Deliver]:
    table: dict[Kind, st.Deliver] = {
        Kind.INTENTION: on_intention,
        Kind.COMMIT: lambda w, m: _client(
            w, wit.on_command(w.c, True, m.w, m.amount), resolves=True
        ),
        Kind.ABORT: lambda w, m: _client(
            w, wit.on_command(w.c, False, m.w, m.amount), resolves=True
        ),
        Kind.RETURN_ACK: lambda w, m: _client(w, wit.on_debit_ack(w.c, m.w)),
        Kind.ADMIT: on_admit,
        Kind.ACK: lambda w, m: _session(w, wit.on_ack(w.s, m.w)),
        Kind.COMMITTED: lambda w, m: _session(w, wit.on_committed(w.s, m.w)),
        Kind.ABORTED: lambda w, m: _session(w, wit.on_aborted(w.s, m.w)),
        Kind.RETURN: lambda w, m: _session(w, wit.credit_return(w.s, m.w, m.amount)),
        Kind.JOIN: on_join,
        Kind.DEBIT: on_debit,
    }
    assert set(table) == set(TO_CLIENT) | set(W_TO_SUPERVISOR)
    return table


def local() -> dict[str, st.Local]:
    """Each local request and timer of the witnessed tables (a gateway's link moves are not
    steps here: a witnessed gateway forwards by a draw)."""
    nonce = z3.BitVec("start.nonce", 16)
    return {
        "client: command timer (timeout-commit)": lambda w: _client(
            w, wit.timeout_commit(w.c), resolves=True
        ),
        "client: spend (DRAW)": lambda w: draw(w, z3.Int("spend.amount")),
        "client: give back": lambda w: give_back(w, z3.Int("give_back.amount")),
        "client: retry timer (RETURN, DRAW, JOIN, RESUME or a SYNC's answer again)": lambda w: (
            _client(w, wit.resend(w.c))
        ),
        "client: power loss (RESUME)": lambda w: _client(
            w, wit.power_loss(w.c, nonce), restarted=z3.BoolVal(True)
        ),
        "client: books lost (JOIN)": lambda w: books_lost(w, z3.BitVec("books_lost.nonce", 16)),
        WRITE_COPY: write_copy,
        WRITE_SESSION_COPY: write_session_copy,
        "supervisor: begin": lambda w: begin(w, z3.Int("begin.amount")),
        "supervisor: decide commit": decide(True),
        "supervisor: decide abort": decide(False),
        "supervisor: response timer (re-send, write off, or SYNC again)": lambda w: _session(
            w, wit.response_timeout(w.s, z3.Bool("response_timeout.gives_up"))
        ),
        "supervisor: power loss (SYNC)": lambda w: restore_supervisor(w, w.s, nonce),
        RESYNC: lambda w: resync(w, z3.BitVec("resync.nonce", 16)),
    }


MOVES: dict[str, tuple[str, ...]] = {
    "client receives INTENTION": ("Uc", "received"),
    "client receives COMMIT": ("Uc", "received"),
    "client receives RETURN_ACK": ("spent",),
    "client receives ADMIT": ("Uc", "lost"),
    "supervisor receives COMMITTED": ("Ts", "Gs"),
    "supervisor receives ABORTED": ("Ts",),
    "supervisor receives RETURN": ("returned",),
    "supervisor receives JOIN": ("Ts", "Gs"),
    "supervisor receives DEBIT": ("Ts", "Gs", "returned"),
    "client: command timer (timeout-commit)": ("Uc", "received"),
    "client: spend (DRAW)": ("Uc",),
    "client: give back": ("Uc", "given"),
    "client: books lost (JOIN)": ("Uc", "lost"),
    "client: restored from an older image": ("Uc",),
    "supervisor: restored from an older image": ("Ts", "Gs"),
    "supervisor: begin": ("Ts",),
    "supervisor: response timer (re-send, write off, or SYNC again)": ("Ts", "Gs"),
    "supervisor: power loss (SYNC)": ("Ts", "Gs"),
}
"""The energies each witnessed step's rule moves (the proof's vacuity checks, as for the
hardened steps)."""
