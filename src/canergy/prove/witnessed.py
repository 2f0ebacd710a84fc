"""The witnessed rules (``canergy.core.witnessed``) as z3 terms: the cells they add to or change
in the hardened tables, both sides' starts included.

Each handler dispatches as the witnessed tables do (an event a phase has no cell for leaves the
state as it is) and reuses the hardened terms of ``symbolic`` for the cells the two share.
``tests/test_prove_symbolic.py`` compares every handler with the Python tables on concrete
states drawn by hypothesis, as it does the hardened ones.

A DEBIT is sent as ``Sent.of(DEBIT, q, amount_mj, flags, nonce)``; a SYNC's books as a DEBIT
with Rc's low 16 bits in ``q`` and its high 8 in ``amount_mj``, its counts with ltx's 16 wire
bits in ``amount_mj``. A client step sends up to two frames (``Frames``: the answer to a SYNC is
its books, then its counts; every other step sends at most the first). Timers are taken as due;
deadlines are not modelled.
"""

from __future__ import annotations

from dataclasses import replace

from canergy.core.witnessed import RECORD_MJ, ZERO_FLOOR_UJ
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    DELIVERED_BITS,
    NONCE_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    SYNC_CONFIRMED,
    TX_BITS,
    Debit,
    MsgType,
)
from canergy.prove import symbolic as sym
from canergy.prove.symbolic import Client, Sent, Session, SessionStep, Term, z3

BOOKED_PHASES = (sym.IDLE, sym.HOLDING)
DRAW, START, SYNC, BOOKS = Debit.DRAW, Debit.START, Debit.SYNC, Debit.BOOKS
COUNTS = START | SYNC
AFRESH_COUNTS = COUNTS | Debit.RC_UNKNOWN
"""The counts of a node admitted afresh that has taken no fresh intention since
(``Debit.afresh``)."""
UNKNOWN_BOOKS = BOOKS | Debit.RC_UNKNOWN
WINDOW = 64
"""B (``Timing.window``): the handlers take it as a parameter, this default as the core's."""

Frames = tuple[Sent, Sent]
"""What a client step sends: a frame, and a second one only in a SYNC's answer (its counts)."""


def booked(c: Client) -> Term:
    return z3.Or(*(c.phase == p for p in BOOKED_PHASES))


def _zero16() -> Term:
    return z3.BitVecVal(0, 16)


def no_floor(c: Client) -> Term:
    """``witnessed.books_of`` is unknown: Rc unknown and no floor (0 mJ modulo 2^32)."""
    return z3.And(c.credited_unknown, (c.credited / QUANTUM_UJ) % RECORD_MJ == 0)


def floor_of(c: Client) -> Term:
    """``witnessed.floor_of``: a known Rc of 0 mJ modulo 2^32 kept as 2^24 mJ more."""
    zero = z3.And(z3.Not(c.credited_unknown), (c.credited / QUANTUM_UJ) % RECORD_MJ == 0)
    return z3.If(zero, c.credited + ZERO_FLOOR_UJ, c.credited)


def one(sent: Sent) -> Frames:
    return sent, Sent.none()


def pick_frames(cond: Term, yes: Frames, no: Frames) -> Frames:
    return sym.pick(cond, yes[0], no[0]), sym.pick(cond, yes[1], no[1])


def _choose(
    cond: Term, yes: tuple[Client, Frames], no: tuple[Client, Frames]
) -> tuple[Client, Frames]:
    return sym.pick(cond, yes[0], no[0]), pick_frames(cond, yes[1], no[1])


# -- the client ----------------------------------------------------------------------------------


def can_debit(c: Client) -> Term:
    """One numbered debit at a time, none before the supervisor confirmed the books, none
    numbered at the end of the numbering."""
    return z3.And(c.return_pending == 0, booked(c), z3.Not(sym.at_end(c.return_seq)))


def draw_of(c: Client) -> Sent:
    return Sent.of(
        MsgType.DEBIT,
        sym.low(c.return_seq, SEQ_BITS),
        c.return_pending / QUANTUM_UJ,
        z3.IntVal(DRAW),
    )


def resume_of(c: Client) -> Sent:
    flags = z3.If(c.pending_draw, START | DRAW, START)
    pending = c.return_pending / QUANTUM_UJ
    return Sent.of(MsgType.DEBIT, sym.low(c.return_seq, SEQ_BITS), pending, flags, c.nonce)


def answer_of(c: Client) -> Frames:
    """The answer to SYNC(n): the books (n, Rc; unknown, flagged with both fields 0, only
    after an admission afresh without a floor: ``witnessed.books_of``), then the counts
    (n, q, ltx; flagged ``AFRESH_COUNTS`` while Rc is unknown or a floor)."""
    unknown = no_floor(c)
    # the low 24 bits of Rc in mJ: 16 in the number's field, 8 in the amount's (both 0 unknown)
    rc_low = (c.credited / QUANTUM_UJ) % (1 << DELIVERED_BITS)
    books = Sent.of(
        MsgType.DEBIT,
        z3.If(unknown, z3.BitVecVal(0, 16), z3.Int2BV(rc_low, 16)),
        z3.If(unknown, 0, rc_low / (1 << 16)),
        z3.If(unknown, UNKNOWN_BOOKS, BOOKS),
        c.nonce,
    )
    counts = Sent.of(
        MsgType.DEBIT,
        sym.low(c.return_seq, SEQ_BITS),
        z3.BV2Int(sym.low(c.last_tx, TX_BITS)),
        z3.If(c.credited_unknown, AFRESH_COUNTS, COUNTS),
        c.nonce,
    )
    return books, counts


def _debit(c: Client, amount: Term, is_draw: bool) -> tuple[Client, Term]:
    """``start_return``: Uc -= x as debit q + 1, pending; allowed for a valid amount within Uc."""
    allowed = z3.And(
        can_debit(c),
        amount > 0,
        amount % QUANTUM_UJ == 0,
        amount <= AMOUNT_MAX_MJ * QUANTUM_UJ,
        amount <= c.usable,
    )
    debited = replace(
        c,
        usable=c.usable - amount,
        return_seq=c.return_seq + 1,
        return_pending=amount,
        pending_draw=z3.BoolVal(is_draw) if is_draw else c.pending_draw,
    )
    return debited, allowed


def draw(c: Client, amount: Term) -> tuple[Client, Sent, Term]:
    """Spend(x): DRAW(q + 1, x); the actuator gets x only on its acknowledgement."""
    drawn, allowed = _debit(c, amount, True)
    return drawn, draw_of(drawn), allowed


def give_back(c: Client, amount: Term) -> tuple[Client, Sent, Term]:
    """GiveBack(x): RETURN(q + 1, x) as under the hardened rules, allowed by ``can_debit``."""
    returned, allowed = _debit(c, amount, False)
    seq = sym.low(returned.return_seq, SEQ_BITS)
    return returned, Sent.of(MsgType.RETURN, seq, amount / QUANTUM_UJ), allowed


def on_intention(
    c: Client, tx16: Term, amount_mj: Term, delivered_mj: Term
) -> tuple[Client, Frames]:
    """INTENTION: hardened while booked or joining, but Gs pays back only from a fresh one
    (k > ltx; an old one only re-replies); RESUMING: RESUME again, SYNCING: the answer again,
    nothing moves."""
    taken = sym.on_intention(c, tx16, amount_mj, delivered_mj)
    tx = sym.unwrap(tx16, c.last_tx, TX_BITS)
    old = z3.And(booked(c), z3.Not(c.credited_unknown), tx - c.last_tx <= 0)
    replied = sym.pick(tx == c.last_tx, sym._reply_for(c, tx, c.outcome), Sent.none())
    moved = (sym.pick(old, c, taken[0]), one(sym.pick(old, replied, taken[1])))
    waiting = _choose(c.phase == sym.SYNCING, (c, answer_of(c)), (c, one(resume_of(c))))
    return _choose(z3.Or(c.phase == sym.RESUMING, c.phase == sym.SYNCING), waiting, moved)


def on_command(c: Client, commit: bool, tx16: Term, amount_mj: Term) -> tuple[Client, Frames]:
    """COMMIT or ABORT: hardened while booked; ignored while joining or in a start."""
    state, sent = sym.on_command(c, commit, tx16, amount_mj)
    ignored = z3.Not(booked(c))
    return sym.pick(ignored, c, state), one(sym.pick(ignored, Sent.none(), sent))


def on_debit_ack(c: Client, seq16: Term) -> tuple[Client, Frames]:
    """RETURN_ACK(q) for the pending debit: done; a draw goes to the actuator (spent += x)."""
    state, sent = sym.on_return_ack(c, seq16)
    done = z3.And(booked(c), sym.unwrap(seq16, c.return_seq, SEQ_BITS) == c.return_seq)
    done = z3.And(done, c.return_pending != 0)
    released = replace(state, spent=c.spent + c.return_pending, pending_draw=z3.BoolVal(False))
    state = sym.pick(z3.And(done, c.pending_draw), released, state)
    return sym.pick(booked(c), state, c), one(sent)


def resend(c: Client) -> tuple[Client, Frames]:
    """The retry timer, due: the pending RETURN or DRAW, JOIN, RESUME, or a SYNC's answer again."""
    pending = z3.And(booked(c), c.return_pending != 0)
    debit = sym.pick(
        c.pending_draw,
        draw_of(c),
        Sent.of(MsgType.RETURN, sym.low(c.return_seq, SEQ_BITS), c.return_pending / QUANTUM_UJ),
    )
    sent = sym.pick(
        c.phase == sym.JOINING,
        Sent.of(MsgType.JOIN, c.nonce),
        sym.pick(c.phase == sym.RESUMING, resume_of(c), sym.pick(pending, debit, Sent.none())),
    )
    return c, pick_frames(c.phase == sym.SYNCING, answer_of(c), one(sent))


def power_loss(c: Client, nonce16: Term) -> tuple[Client, Frames]:
    """A start with a record (after a power loss, or from an older image: the node cannot tell):
    the held intention is lost, RESUMING with a new nonce, RESUME; joining: stays joining."""
    resumed = replace(
        c,
        phase=sym.RESUMING,
        held_tx=sym.counter(0),
        held_amount=z3.IntVal(0),
        nonce=nonce16,
    )
    joining = c.phase == sym.JOINING
    return sym.pick(joining, c, resumed), one(sym.pick(joining, Sent.none(), resume_of(resumed)))


def books_lost(c: Client, nonce16: Term) -> tuple[Client, Frames]:
    """No valid record: the hardened JOIN (any phase)."""
    state, sent = sym.books_lost(c, nonce16)
    return state, one(sent)


def answer_sync(c: Client, nonce16: Term, window: int = WINDOW) -> tuple[Client, Frames]:
    """SYNC(n) (an ADMIT not answering this node's start): settle the next B transactions
    (ltx += B), drop the held intention, answer with the books and the counts, move nothing
    until ADMIT(n ^ SYNC_CONFIRMED). An ADMIT with ``SYNC_CONFIRMED`` set is no SYNC: ignored."""
    synced = replace(
        c,
        phase=sym.SYNCING,
        held_tx=sym.counter(0),
        held_amount=z3.IntVal(0),
        nonce=nonce16,
        last_tx=sym.capped(c.last_tx + window),
        outcome=sym.SETTLED,
    )
    confirmation = z3.Extract(15, 15, nonce16) == 1
    return _choose(confirmation, (c, one(Sent.none())), (synced, answer_of(synced)))


def on_confirm(c: Client, tx16: Term, seq16: Term) -> tuple[Client, Frames]:
    """ADMIT(n, k, Q) answering this start: Q = q + 1 keeps the books settled up to k, a larger
    Q finds them behind (admitted afresh at k and Q, what the actuator used kept), a smaller one
    is ignored. A RESUME confirmed with k below ltx is followed by the counts: SYNCING under its
    nonce, the answer sent (``witnessed.resync``)."""
    q = sym.unwrap(seq16, c.return_seq, SEQ_BITS)
    ahead = q - c.return_seq
    closed = sym.unwrap(tx16, c.last_tx, TX_BITS)
    settled = z3.If(closed - c.last_tx > 0, closed, c.last_tx)
    confirmed = replace(
        c,
        last_tx=settled,
        outcome=z3.If(closed - c.last_tx > 0, sym.SETTLED, c.outcome),
        phase=sym.IDLE,
        nonce=_zero16(),
        return_seq=q,
        return_pending=z3.IntVal(0),
        pending_draw=z3.BoolVal(False),
    )
    zero = z3.IntVal(0)
    fresh = Client(
        usable=zero,
        credited=floor_of(c),  # a floor for its books only (``witnessed.on_confirm``)
        spent=c.spent,
        last_tx=z3.ZeroExt(sym.COUNTER - TX_BITS, tx16),
        outcome=sym.SETTLED,
        return_seq=q,
        return_pending=zero,
        credited_unknown=z3.BoolVal(True),
        held_tx=sym.counter(0),
        held_amount=zero,
        phase=sym.IDLE,
        nonce=_zero16(),
        pending_draw=z3.BoolVal(False),
    )
    resynced = replace(confirmed, phase=sym.SYNCING, nonce=c.nonce)
    behind_ltx = z3.And(ahead == 1, c.phase == sym.RESUMING, closed - c.last_tx < 0)
    state = sym.pick(ahead == 1, confirmed, sym.pick(ahead <= 0, c, fresh))
    beyond = z3.UGE(q, sym.counter(COUNTER_BOUND))  # no supervisor confirms there (capped)
    state = sym.pick(beyond, c, state)
    behind_ltx = z3.And(behind_ltx, z3.Not(beyond))
    return _choose(behind_ltx, (resynced, answer_of(resynced)), (state, one(Sent.none())))


def on_admit(
    c: Client, nonce16: Term, tx16: Term, seq16: Term, window: int = WINDOW
) -> tuple[Client, Frames]:
    """ADMIT(n, k, Q): joining, the hardened admission; booked, a SYNC (``answer_sync``); in a
    start, its confirmation (``on_confirm``; a SYNC's answer is confirmed with
    ``SYNC_CONFIRMED`` flipped in its nonce), the same SYNC again (the answer again), or another
    SYNC."""
    admitted = (sym.on_admit(c, nonce16, tx16, seq16)[0], one(Sent.none()))
    syncing = c.phase == sym.SYNCING
    expected = z3.If(syncing, c.nonce ^ SYNC_CONFIRMED, c.nonce)
    confirmed = on_confirm(c, tx16, seq16)
    again = z3.And(syncing, nonce16 == c.nonce)
    starting = _choose(
        nonce16 == expected,
        confirmed,
        _choose(again, (c, answer_of(c)), answer_sync(c, nonce16, window)),
    )
    in_start = z3.Or(c.phase == sym.RESUMING, syncing)
    return _choose(
        booked(c),
        answer_sync(c, nonce16, window),
        _choose(in_start, starting, admitted),
    )


def timeout_commit(c: Client) -> tuple[Client, Frames]:
    state, sent = sym.timeout_commit(c)
    return state, one(sent)


# -- the supervisor's session ----------------------------------------------------------------------

OPEN = (sym.WAIT_ACK, sym.ACKED, sym.WAIT_CONFIRM)


def in_start(s: Session) -> Term:
    """The supervisor waits for the node's answer to its SYNC."""
    return z3.Or(s.phase == sym.SYNCING, s.phase == sym.SYNC_BOOKS)


def _outside_start(s: Session, step: SessionStep) -> SessionStep:
    """A cell of IDLE and the open phases: a start's phases ignore the event."""
    return sym.choose(in_start(s), sym._unchanged(s), step)


def _witnessed(s: Session, taken: Term, k: Term, step: SessionStep) -> SessionStep:
    """A response that names transaction ``k`` and was taken: W moves up to ``k`` (W signed:
    counts whose ltx reads below 0 set it there, ``_ltx_of``)."""
    moved = replace(step.session, witness=z3.If(k > s.witness, k, s.witness))
    return sym.choose(taken, SessionStep(moved, step.sent, step.credit), step)


def _this_tx(s: Session, tx16: Term) -> Term:
    return z3.Not(sym._other_tx(s, tx16))


def on_ack(s: Session, tx16: Term) -> SessionStep:
    """ACK(tx): as the hardened rules; the node has persisted tx - 1 (W >= tx - 1)."""
    taken = z3.And(s.phase == sym.WAIT_ACK, _this_tx(s, tx16))
    return _witnessed(s, taken, s.tx - 1, sym.on_ack(s, tx16))


def on_committed(s: Session, tx16: Term) -> SessionStep:
    """COMMITTED(tx): as the hardened rules; the node has persisted tx (W >= tx)."""
    taken = z3.And(z3.Or(*(s.phase == p for p in OPEN)), _this_tx(s, tx16))
    return _witnessed(s, taken, s.tx, sym.on_committed(s, tx16))


def on_aborted(s: Session, tx16: Term) -> SessionStep:
    """ABORTED(tx) after an abort decision: as the hardened rules; W >= tx."""
    taken = z3.And(s.phase == sym.WAIT_CONFIRM, _this_tx(s, tx16), s.decision == sym.ABORT)
    return _witnessed(s, taken, s.tx, sym.on_aborted(s, tx16))


def credit_return(s: Session, seq16: Term, amount_mj: Term) -> SessionStep:
    """RETURN: the hardened cell, outside a start."""
    return _outside_start(s, sym.credit_return(s, seq16, amount_mj))


def may_begin(s: Session, window: int = WINDOW) -> Term:
    """Begin k = tx + 1 only within the window (k <= W + B, W signed: below 0 closes it) and
    the node's numbering."""
    return z3.And(s.tx + 1 <= s.witness + window, sym.may_begin(s))


def response_timeout(s: Session, gives_up: Term) -> SessionStep:
    """The response timer, due: hardened while open; in a start, SYNC(n) again."""
    return sym.choose(in_start(s), resend_sync(s), sym.response_timeout(s, gives_up))


def _sync(s: Session) -> Sent:
    """SYNC(n, tx, C): an ADMIT the node did not ask for."""
    return Sent.of(
        MsgType.ADMIT,
        s.sync_nonce,
        z3.BV2Int(sym.low(s.tx, TX_BITS)),
        z3.BV2Int(sym.low(s.returns_credited, SEQ_BITS)),
    )


def start(s: Session, nonce16: Term) -> SessionStep:
    """A start (after a power loss or from an older image): write off what is open, SYNCING
    with a new nonce (SYNC is sent by ``resend_sync``, its timer due at once); no re-sync."""
    open_ = z3.Or(*(s.phase == p for p in OPEN))
    step = sym.choose(open_, sym._resolve(s, z3.BoolVal(False)), sym._unchanged(s))
    nonce = sync_nonce_for(step.session, nonce16)
    waiting = replace(step.session, phase=sym.SYNCING, sync_nonce=nonce, resync=z3.BoolVal(False))
    return SessionStep(waiting, Sent.none(), step.credit)


def sync_nonce_for(s: Session, nonce16: Term) -> Term:
    """``witnessed.sync_nonce_for``: ``SYNC_CONFIRMED`` clear, and not the nonce of the last
    start answered (its lowest bit flipped then)."""
    nonce = nonce16 & (0xFFFF ^ SYNC_CONFIRMED)
    last = z3.And(s.resume_to != 0, z3.Extract(NONCE_BITS - 1, 0, s.resume_nonce) == nonce)
    return z3.If(last, nonce ^ 1, nonce)


def may_resync(s: Session) -> Term:
    """A re-sync starts only from IDLE (nothing open, no start waiting)."""
    return s.phase == sym.S_IDLE


def resync_session(s: Session, nonce16: Term) -> SessionStep:
    """``witnessed.resync_session`` (from IDLE, ``may_resync``): SYNCING under the fresh nonce
    (``SYNC_CONFIRMED`` cleared), ``resync`` set, SYNC(n, tx, C) sent at once; nothing else
    moves."""
    nonce = sync_nonce_for(s, nonce16)
    waiting = replace(s, phase=sym.SYNCING, sync_nonce=nonce, resync=z3.BoolVal(True))
    return SessionStep(waiting, _sync(waiting), z3.IntVal(0))


def resend_sync(s: Session) -> SessionStep:
    return SessionStep(s, _sync(s), z3.IntVal(0))


def is_books(flags: Term) -> Term:
    """A SYNC's books, Rc known or not."""
    return z3.Or(flags == BOOKS, flags == UNKNOWN_BOOKS)


def take_books(s: Session, nonce16: Term, flags: Term, seq16: Term, amount_mj: Term) -> SessionStep:
    """The SYNC's books (n, Rc): Gs moves up to Rc (never back), the difference out of Us;
    books with Rc unknown, or answering a re-sync, leave Gs alone."""
    credited_mj = z3.BV2Int(seq16) + amount_mj * (1 << 16)
    credited = sym.unwrap_int(credited_mj, s.delivered / QUANTUM_UJ, DELIVERED_BITS) * QUANTUM_UJ
    gain = z3.If(credited > s.delivered, credited - s.delivered, 0)
    taken = SessionStep(
        replace(s, phase=sym.SYNC_BOOKS, delivered=s.delivered + gain), Sent.none(), -gain
    )
    unknown = SessionStep(replace(s, phase=sym.SYNC_BOOKS), Sent.none(), z3.IntVal(0))
    ours = nonce16 == s.sync_nonce
    return sym.choose(
        z3.And(ours, flags == BOOKS, z3.Not(s.resync)),
        taken,
        sym.choose(z3.And(ours, is_books(flags)), unknown, sym._unchanged(s)),
    )


def take_counts(
    s: Session, nonce16: Term, flags: Term, seq16: Term, amount_mj: Term
) -> SessionStep:
    """The SYNC's counts (n, q, ltx) after its books: W = ltx, then as a RESUME (tx up to ltx,
    C = max(C, q) + 1, ADMIT(n ^ SYNC_CONFIRMED, tx, C)); its books again are taken again.
    Counts afresh (books unknown or a floor) with q above C + 1 move the most q - C - 1 debit
    numbers can draw from Us to Gs (``ahead_of_image``)."""
    settled = _ltx_of(amount_mj, s.tx)
    ahead = ahead_of_image(s, flags, seq16)
    idle = replace(s, phase=sym.S_IDLE, sync_nonce=_zero16(), witness=settled)
    idle = replace(idle, resync=z3.BoolVal(False))
    idle = replace(idle, delivered=idle.delivered + ahead)
    confirmed = confirm(idle, nonce16, z3.BoolVal(False), seq16, amount_mj, z3.BoolVal(True))
    counted = SessionStep(confirmed.session, confirmed.sent, confirmed.credit - ahead)
    step = sym.choose(
        is_books(flags),
        take_books(s, nonce16, flags, seq16, amount_mj),
        sym.choose(is_counts(flags), counted, sym._unchanged(s)),
    )
    return sym.choose(nonce16 == s.sync_nonce, step, sym._unchanged(s))


def is_counts(flags: Term) -> Term:
    """A SYNC's counts, afresh or not (``Debit.is_counts``)."""
    return z3.Or(flags == COUNTS, flags == AFRESH_COUNTS)


def ahead_of_image(s: Session, flags: Term, seq16: Term) -> Term:
    """``witnessed.ahead_of_image``: counts afresh with q above C + 1 (q unwrapped near C):
    (q - C - 1) * ``AMOUNT_MAX_MJ`` in µJ, else 0."""
    ahead = sym.unwrap(seq16, s.returns_credited, SEQ_BITS) - s.returns_credited
    draws = z3.BV2Int(ahead, is_signed=True) - 1
    afresh = flags == AFRESH_COUNTS
    # in quanta times Q: Gs stays a whole number of quanta for z3 by rewriting alone
    return QUANTUM_UJ * z3.If(z3.And(afresh, draws > 0), draws * AMOUNT_MAX_MJ, 0)


def hold_draw(s: Session, seq16: Term) -> SessionStep:
    """DRAW(q, x): hold q as the node's last debit (nothing to Us); re-ack an old q; ignore one
    beyond, and the next at the end of the numbering."""
    seq = sym.unwrap(seq16, s.returns_credited, SEQ_BITS)
    ahead = seq - s.returns_credited
    ack = Sent.of(MsgType.RETURN_ACK, seq16)
    held = SessionStep(replace(s, returns_credited=seq), ack, z3.IntVal(0))
    again = SessionStep(s, ack, z3.IntVal(0))
    next_one = z3.And(ahead == 1, z3.Not(sym.at_end(s.returns_credited)))
    return sym.choose(
        next_one, held, sym.choose(ahead <= 0, again, SessionStep(s, Sent.none(), z3.IntVal(0)))
    )


def _confirmation(s: Session, nonce16: Term) -> Sent:
    """ADMIT(n, k, C): k the last transaction closed, C the last debit number held."""
    closed = z3.If(s.phase == sym.S_IDLE, s.tx, s.tx - 1)
    return Sent.of(
        MsgType.ADMIT,
        nonce16,
        z3.BV2Int(sym.low(closed, TX_BITS)),
        z3.BV2Int(sym.low(s.returns_credited, SEQ_BITS)),
    )


def key_of(nonce16: Term, counts: Term) -> Term:
    """What the last answer remembers of a start: its nonce, and above it whether it was a
    SYNC's counts."""
    flag = z3.If(counts, z3.BitVecVal(1 << NONCE_BITS, sym.KEY_BITS), z3.BitVecVal(0, sym.KEY_BITS))
    return z3.ZeroExt(sym.KEY_BITS - NONCE_BITS, nonce16) | flag


def confirm(
    s: Session,
    nonce16: Term,
    is_draw: Term,
    seq16: Term,
    amount_mj: Term,
    counts: Term | None = None,
) -> SessionStep:
    """RESUME(n, q, x), or a SYNC's counts (n, q, ltx in ``amount_mj``; ``counts``): write off
    what is open; behind (q below C): lift as for a JOIN; a pending RETURN numbered C + 1
    credited (not at the end; counts carry none); counts move tx up to ltx (not W: late counts may
    be a record's the node no longer holds); C = max(C, q) + 1 (voided); ADMIT(n, k,
    C), n flipped for counts. A repeat (same key and q, C unchanged since; ``resume_to`` 0:
    none answered) gets the same answer (``repeat_counts``)."""
    counts = z3.BoolVal(False) if counts is None else counts
    seq = sym.unwrap(seq16, s.returns_credited, SEQ_BITS)
    key = key_of(nonce16, counts)
    answer_nonce = z3.If(counts, nonce16 ^ SYNC_CONFIRMED, nonce16)
    repeat = repeats(s, key, seq)
    behind = seq - s.returns_credited < 0
    lifted = admitted_afresh(s, nonce16)
    closed = sym.choose(
        s.phase != sym.S_IDLE, sym._resolve(s, z3.BoolVal(False)), sym._unchanged(s)
    )
    t = closed.session
    amount = amount_mj * QUANTUM_UJ
    room = z3.Not(sym.at_end(t.returns_credited))
    pending = z3.And(amount_mj != 0, z3.Not(counts))
    credits = z3.And(seq - t.returns_credited == 1, pending, z3.Not(is_draw), room)
    credited = SessionStep(
        replace(t, returns_credited=seq, returned=t.returned + amount),
        Sent.none(),
        closed.credit + amount,
    )
    kept = sym.choose(credits, credited, closed)
    step = sym.choose(behind, SessionStep(lifted.session, Sent.none(), lifted.credit), kept)
    t = step.session
    settled = _ltx_of(amount_mj, t.tx)
    t = sym.pick(
        counts,
        replace(t, tx=z3.If(settled - t.tx > 0, settled, t.tx)),
        t,
    )
    # behind: seq < C <= the lifted C (which may be 2**31 above seq: no signed comparison)
    later = z3.And(z3.Not(behind), seq - t.returns_credited > 0)
    void = sym.capped(z3.If(later, seq, t.returns_credited) + 1)
    t = replace(t, returns_credited=void, resume_nonce=key, resume_from=seq, resume_to=void)
    answered = SessionStep(t, _confirmation(t, answer_nonce), step.credit)
    return sym.choose(repeat, repeat_counts(s, counts, amount_mj, answer_nonce), answered)


def may_repeat(s: Session) -> Term:
    """A repeat of the last answer to a start can happen: one was given (``resume_to`` not 0)
    and C is where it left it."""
    return z3.And(s.resume_to != 0, s.resume_to == s.returns_credited)


def repeats(s: Session, key: Term, seq: Term) -> Term:
    """``witnessed.answered``: the start's frame (its ``key`` and number ``seq``) is the last
    one answered, and C has not moved since."""
    return z3.And(may_repeat(s), s.resume_nonce == key, s.resume_from == seq)


def _ltx_of(amount_mj: Term, tx: Term) -> Term:
    """``witnessed.ltx_of``: the counts' ltx (16 bits) widened against ``tx``, one ahead of it
    held below ``COUNTER_BOUND`` (one behind, below 0 too, as it is)."""
    settled = sym.unwrap(z3.Int2BV(amount_mj, 16), tx, TX_BITS)
    top = sym.counter(COUNTER_BOUND - 1)
    return z3.If(z3.And(settled - tx > 0, z3.UGE(settled, top)), top, settled)


def repeat_counts(s: Session, counts: Term, amount_mj: Term, answer_nonce: Term) -> SessionStep:
    """The same answer again; for counts (maybe another start of the node that answered a
    copy of the same SYNC), first what is open written off and tx moved up to their ltx
    (never back), and after the answer C + 1 voided."""
    settled = _ltx_of(amount_mj, s.tx)
    closed = sym.choose(
        s.phase != sym.S_IDLE, sym._resolve(s, z3.BoolVal(False)), sym._unchanged(s)
    )
    t = closed.session
    t = replace(t, tx=z3.If(settled - t.tx > 0, settled, t.tx))
    answer = _confirmation(t, answer_nonce)
    t = replace(t, returns_credited=sym.capped(t.returns_credited + 1))
    moved = SessionStep(t, answer, closed.credit)
    same = SessionStep(s, _confirmation(s, answer_nonce), z3.IntVal(0))
    return sym.choose(counts, moved, same)


def admitted_afresh(s: Session, nonce16: Term) -> SessionStep:
    """``witnessed.admitted_afresh``: the hardened admission; W stays (no evidence)."""
    return sym.admit(s, nonce16)


def admit(s: Session, nonce16: Term) -> SessionStep:
    """JOIN(n): outside a start, ``admit_idle``; at a start, ignored; in a re-sync
    (``join_while_syncing``), the re-sync ends (IDLE, no nonce, ``resync`` clear) and the JOIN
    is taken as in IDLE."""
    ended = replace(s, phase=sym.S_IDLE, sync_nonce=_zero16(), resync=z3.BoolVal(False))
    waits = sym.choose(s.resync, admit_idle(ended, nonce16), sym._unchanged(s))
    return sym.choose(in_start(s), waits, admit_idle(s, nonce16))


def admit_idle(s: Session, nonce16: Term) -> SessionStep:
    """JOIN(n) outside a start: the admission afresh with the number after C voided: C + 1,
    ADMIT(n, k, C), remembered (``join_*``); a copy of the last JOIN admitted (its nonce,
    ``join_seq`` not 0) gets the same ADMIT again and moves nothing."""
    lifted = admitted_afresh(s, nonce16)
    t = replace(lifted.session, returns_credited=sym.capped(lifted.session.returns_credited + 1))
    t = replace(t, join_nonce=nonce16, join_tx=t.tx, join_seq=t.returns_credited)
    sent = Sent.of(
        MsgType.ADMIT,
        nonce16,
        z3.BV2Int(sym.low(t.tx, TX_BITS)),
        z3.BV2Int(sym.low(t.returns_credited, SEQ_BITS)),
    )
    fresh = SessionStep(t, sent, lifted.credit)
    again = Sent.of(
        MsgType.ADMIT,
        nonce16,
        z3.BV2Int(sym.low(s.join_tx, TX_BITS)),
        z3.BV2Int(sym.low(s.join_seq, SEQ_BITS)),
    )
    copy = z3.And(s.join_seq != 0, s.join_nonce == nonce16)
    return sym.choose(copy, SessionStep(s, again, z3.IntVal(0)), fresh)


def counts_taken(s: Session, nonce16: Term, amount_mj: Term, window: int = WINDOW) -> Term:
    """``witnessed.counts_taken``: counts outside a start under the last start's nonce, or
    with an ltx from tx to tx + B."""
    last = z3.And(s.resume_to != 0, z3.Extract(NONCE_BITS - 1, 0, s.resume_nonce) == nonce16)
    ahead = _ltx_of(amount_mj, s.tx) - s.tx  # from -2^15 to 2^15 - 1: no wrap on 32 bits
    return z3.Or(last, z3.And(ahead >= 0, ahead <= window))


def on_debit(s: Session, nonce16: Term, flags: Term, seq16: Term, amount_mj: Term) -> SessionStep:
    """DEBIT (``flags`` an integer term): outside a start, a RESUME (START) or a SYNC's counts
    arriving late (``counts_taken``) is confirmed, a draw held, books and other counts ignored;
    in a start, the SYNC's books, then its counts."""
    resume = confirm(s, nonce16, flags % 2 == 1, seq16, amount_mj, is_counts(flags))
    earlier = z3.And(is_counts(flags), z3.Not(counts_taken(s, nonce16, amount_mj)))
    outside = sym.choose(
        z3.Or(is_books(flags), earlier),
        sym._unchanged(s),
        sym.choose((flags / START) % 2 == 1, resume, hold_draw(s, seq16)),
    )
    return sym.choose(
        s.phase == sym.SYNCING,
        take_books(s, nonce16, flags, seq16, amount_mj),
        sym.choose(
            s.phase == sym.SYNC_BOOKS, take_counts(s, nonce16, flags, seq16, amount_mj), outside
        ),
    )
