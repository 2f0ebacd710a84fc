"""The witnessed rules (``canergy.core.witnessed``) as z3 terms: the cells they add to or change
in the hardened tables, and a start from an older image of the node's record.

Each handler dispatches as the witnessed tables do (an event a phase has no cell for leaves the
state as it is) and reuses the hardened terms of ``symbolic`` for the cells the two share.
``tests/test_prove_symbolic.py`` compares every handler with the Python tables on concrete
states drawn by hypothesis, as it does the hardened ones.

A DEBIT is sent as ``Sent.of(DEBIT, q, amount_mj, flags, nonce)``.

Not modelled (the comparison draws none of them): the supervisor side of a start, SYNC and its
answers (the session phases SYNCING and SYNC_BOOKS, the books and counts, a supervisor power
loss, the window on BEGIN) and the node's answer to a SYNC (its phase SYNCING, and an ADMIT
that does not answer the node's own start: a SYNC, answered with two frames, which ``Sent``
cannot carry). The terms cover the node's draws, starts (RESUME) and their confirmation, and
the supervisor's DRAW, RESUME and JOIN cells.
"""

from __future__ import annotations

from dataclasses import replace

from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, SEQ_BITS, TX_BITS, Debit, MsgType
from canergy.prove import symbolic as sym
from canergy.prove.symbolic import Client, Sent, Session, SessionStep, Term, z3

BOOKED_PHASES = (sym.IDLE, sym.HOLDING)
DRAW, START = Debit.DRAW, Debit.START


def booked(c: Client) -> Term:
    return z3.Or(*(c.phase == p for p in BOOKED_PHASES))


def _zero16() -> Term:
    return z3.BitVecVal(0, 16)


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


def on_intention(c: Client, tx16: Term, amount_mj: Term, delivered_mj: Term) -> tuple[Client, Sent]:
    """INTENTION: hardened while booked or joining, but Gs pays back only from a fresh one
    (k > ltx; an old one only re-replies); RESUMING: RESUME again, nothing moves."""
    taken = sym.on_intention(c, tx16, amount_mj, delivered_mj)
    tx = sym.unwrap(tx16, c.last_tx, TX_BITS)
    old = z3.And(booked(c), z3.Not(c.credited_unknown), tx - c.last_tx <= 0)
    replied = sym.pick(tx == c.last_tx, sym._reply_for(c, tx, c.outcome), Sent.none())
    taken = (sym.pick(old, c, taken[0]), sym.pick(old, replied, taken[1]))
    resuming = c.phase == sym.RESUMING
    return sym.pick(resuming, c, taken[0]), sym.pick(resuming, resume_of(c), taken[1])


def on_command(c: Client, commit: bool, tx16: Term, amount_mj: Term) -> tuple[Client, Sent]:
    """COMMIT or ABORT: hardened while booked; ignored while joining or resuming."""
    state, sent = sym.on_command(c, commit, tx16, amount_mj)
    ignored = z3.Not(booked(c))
    return sym.pick(ignored, c, state), sym.pick(ignored, Sent.none(), sent)


def on_debit_ack(c: Client, seq16: Term) -> tuple[Client, Sent]:
    """RETURN_ACK(q) for the pending debit: done; a draw goes to the actuator (spent += x)."""
    state, sent = sym.on_return_ack(c, seq16)
    done = z3.And(booked(c), sym.unwrap(seq16, c.return_seq, SEQ_BITS) == c.return_seq)
    done = z3.And(done, c.return_pending != 0)
    released = replace(state, spent=c.spent + c.return_pending, pending_draw=z3.BoolVal(False))
    state = sym.pick(z3.And(done, c.pending_draw), released, state)
    return sym.pick(booked(c), state, c), sent


def resend(c: Client) -> tuple[Client, Sent]:
    """The retry timer, due: the pending RETURN or DRAW, JOIN, or RESUME again."""
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
    return c, sent


def power_loss(c: Client, nonce16: Term) -> tuple[Client, Sent]:
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
    return sym.pick(joining, c, resumed), sym.pick(joining, Sent.none(), resume_of(resumed))


def books_lost(c: Client, nonce16: Term) -> tuple[Client, Sent]:
    """No valid record: the hardened JOIN (any phase)."""
    return sym.books_lost(c, nonce16)


def on_admit(c: Client, nonce16: Term, tx16: Term, seq16: Term) -> tuple[Client, Sent]:
    """ADMIT(n, k, Q): joining, the hardened admission; resuming, the confirmation: Q = q + 1
    keeps the books settled up to k, a larger Q finds them behind (admitted afresh at k and Q,
    what the actuator used kept), a smaller one is ignored."""
    admitted = sym.on_admit(c, nonce16, tx16, seq16)[0]
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
        credited=zero,
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
    answer = sym.pick(ahead == 1, confirmed, sym.pick(ahead <= 0, c, fresh))
    ours = z3.And(c.phase == sym.RESUMING, nonce16 == c.nonce)
    return sym.pick(ours, answer, admitted), Sent.none()


def timeout_commit(c: Client) -> tuple[Client, Sent]:
    return sym.timeout_commit(c)


# -- the supervisor's session ----------------------------------------------------------------------


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


def confirm(s: Session, nonce16: Term, is_draw: Term, seq16: Term, amount_mj: Term) -> SessionStep:
    """RESUME(n, q, x): write off what is open; behind (q below C): lift as for a JOIN; a
    pending RETURN numbered C + 1 credited (not at the end); C = max(C, q) + 1 (voided);
    ADMIT(n, k, C). A repeat (same nonce and q, C unchanged since; ``resume_to`` 0: none
    answered) gets the same answer."""
    seq = sym.unwrap(seq16, s.returns_credited, SEQ_BITS)
    repeat = z3.And(
        s.resume_to != 0,
        s.resume_to == s.returns_credited,
        s.resume_nonce == nonce16,
        s.resume_from == seq,
    )
    behind = seq - s.returns_credited < 0
    lifted = sym.admit(s, nonce16)
    closed = sym.choose(
        s.phase != sym.S_IDLE, sym._resolve(s, z3.BoolVal(False)), sym._unchanged(s)
    )
    t = closed.session
    amount = amount_mj * QUANTUM_UJ
    room = z3.Not(sym.at_end(t.returns_credited))
    credits = z3.And(seq - t.returns_credited == 1, amount_mj != 0, z3.Not(is_draw), room)
    credited = SessionStep(
        replace(t, returns_credited=seq, returned=t.returned + amount),
        Sent.none(),
        closed.credit + amount,
    )
    kept = sym.choose(credits, credited, closed)
    step = sym.choose(behind, SessionStep(lifted.session, Sent.none(), lifted.credit), kept)
    t = step.session
    # behind: seq < C <= the lifted C (which may be 2**31 above seq: no signed comparison)
    later = z3.And(z3.Not(behind), seq - t.returns_credited > 0)
    void = z3.If(later, seq, t.returns_credited) + 1
    t = replace(t, returns_credited=void, resume_nonce=nonce16, resume_from=seq, resume_to=void)
    answered = SessionStep(t, _confirmation(t, nonce16), step.credit)
    return sym.choose(repeat, SessionStep(s, _confirmation(s, nonce16), z3.IntVal(0)), answered)


def admit(s: Session, nonce16: Term) -> SessionStep:
    """JOIN(n): the hardened admission with the number after C voided: C + 1, ADMIT(n, k, C)."""
    lifted = sym.admit(s, nonce16)
    t = replace(lifted.session, returns_credited=lifted.session.returns_credited + 1)
    sent = Sent.of(
        MsgType.ADMIT,
        nonce16,
        z3.BV2Int(sym.low(t.tx, TX_BITS)),
        z3.BV2Int(sym.low(t.returns_credited, SEQ_BITS)),
    )
    return SessionStep(t, sent, lifted.credit)


def on_debit(s: Session, nonce16: Term, flags: Term, seq16: Term, amount_mj: Term) -> SessionStep:
    """DEBIT in any phase (``flags`` an integer term): a RESUME (START) is confirmed, a draw
    held."""
    resume = confirm(s, nonce16, flags % 2 == 1, seq16, amount_mj)
    return sym.choose((flags / START) % 2 == 1, resume, hold_draw(s, seq16))
