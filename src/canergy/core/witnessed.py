"""The witnessed rules: the hardened rules (H1) with a node record that its supervisor witnesses.

A node's record put back from an older copy is a valid record; only the supervisor, who saw what
came after it, can tell that it is old. So every debit of the node's budget is numbered and held
by the supervisor before it takes effect (a return as before, and now a *draw* for the actuator,
which the actuator gets only once the supervisor has acknowledged it), and every start of the
node is confirmed by the supervisor before the node moves energy: RESUME(n, q) carries the
node's last debit number, and a node behind the supervisor's count is admitted afresh, as one
without books. ``docs/protocol.md`` ("Records restored from older copies") argues it; the
bounded checker checks it (``canergy check --variant witnessed --old-copies 1``).
"""

from __future__ import annotations

from canergy.core import common
from canergy.core import hardened as h
from canergy.core.actions import Admitted, AheadOfImage, ReturnCredited, Send
from canergy.core.common import (
    at_end,
    capped,
    check_amount,
    reply_for,
    resolve,
    start_return,
    wire_tx,
)
from canergy.core.errors import LocalProtocolError, WindowClosed
from canergy.core.inputs import (
    RETURN_TIMEOUT,
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    PowerLoss,
    ResponseTimeout,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import SYNC_PHASES, ClientState, Outcome, Phase, Session
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.table import ANY, STAY, ClientTable, SupervisorTable, cell
from canergy.core.timing import Timing
from canergy.frozen import evolve
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    DELIVERED_BITS,
    NONCE_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    SYNC_CONFIRMED,
    TX_BITS,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    Intention,
    Join,
    Return,
    ReturnAck,
)
from canergy.seqnum import unwrap, wrap

IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM = Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM
HOLDING, JOINING, RESUMING = Phase.AWAIT_COMMAND, Phase.JOINING, Phase.RESUMING
SYNCING, SYNC_BOOKS = Phase.SYNCING, Phase.SYNC_BOOKS

# -- supervisor, per node --------------------------------------------------------------------


def begin(t: Timing, s: Session, event: Begin, now: int) -> SessionStep:
    """Begin k = tx + 1 only within the window: k <= W + B (W: the highest transaction the
    node has shown it persisted), so every transaction of a discarded history is at most the
    node's ltx + B. Refused otherwise (``WindowClosed``): a re-sync of the node
    (``resync_session``) opens the window again."""
    if window_closed(t, s):
        raise WindowClosed(
            f"node {s.node}: transaction {s.tx + 1} is beyond the window: the node has shown "
            f"transaction {s.witness} persisted, and no transaction begins more than "
            f"{t.window} past it (a re-sync of the node opens it again)"
        )
    return common.begin(t, s, event, now)


def window_closed(t: Timing, s: Session) -> bool:
    """The next transaction is beyond the window: tx + 1 > W + B."""
    return s.tx + 1 > s.witness + t.window


def _witnessed(s: Session, k: int, step: SessionStep) -> SessionStep:
    """The step of a response that names transaction ``k``: W moves up to ``k``."""
    if step.session is s or k <= s.witness:
        return step
    return SessionStep(evolve(step.session, witness=k), step.actions, step.credit)


def on_ack(t: Timing, s: Session, msg: Ack, now: int) -> SessionStep:
    """ACK(tx): as the hardened rules; the node has persisted tx - 1 (W >= tx - 1)."""
    return _witnessed(s, s.tx - 1, h.on_ack(t, s, msg, now))


def on_committed(t: Timing, s: Session, msg: Committed, now: int) -> SessionStep:
    """COMMITTED(tx): as the hardened rules; the node has persisted tx (W >= tx)."""
    return _witnessed(s, s.tx, h.on_committed(t, s, msg, now))


def on_aborted(t: Timing, s: Session, msg: Aborted, now: int) -> SessionStep:
    """ABORTED(tx) after an abort decision: as the hardened rules; W >= tx."""
    return _witnessed(s, s.tx, h.on_aborted(t, s, msg, now))


def on_debit(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """DEBIT: a draw is held as the node's last debit; a RESUME confirms the node's start, and
    so do a SYNC's counts arriving after the start they answer (``counts_taken``); books
    outside a start are ignored."""
    if msg.is_books or (msg.is_counts and not counts_taken(t, s, msg)):
        return SessionStep(s)
    return confirm(t, s, msg, now) if msg.is_resume else hold_draw(t, s, msg, now)


def counts_taken(t: Timing, s: Session, msg: Debit) -> bool:
    """A SYNC's counts outside a start are taken under the nonce of the last start answered
    (``resume_to`` 0: none), whatever their ltx: the last counts again (their answer lost, or a
    later start of the node answering a copy of the same SYNC: ``repeat_counts``) or those a
    RESUME's answer asks for under its nonce (``resync``); under another nonce only with an ltx
    from tx to tx + B: a node with books answering an ADMIT it took for a SYNC (a late copy, or
    a JOIN's answer) settled B past its ltx, and its ltx is at least W, which is at least
    tx - B. Other counts are an earlier start's: with a key they verify for the whole epoch
    (their FV is their nonce), and their 16-bit ltx, widened against a tx moved on by more than
    2^15, lands up to 2^15 - 1 ahead of it (taken, each moved tx and W there and wrote off what
    was open) or behind it (taken, found behind: written off, C lifted). They are ignored."""
    if s.resume_to != 0 and wrap(s.resume_nonce, NONCE_BITS) == msg.nonce:
        return True
    return s.tx <= ltx_of(s, msg) <= s.tx + t.window


def hold_draw(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """DRAW(q, x): hold q as the node's last debit and ack it (nothing to Us); re-ack an old q;
    ignore one beyond, and the next at the end of the numbering (as ``h.credit_return``)."""
    seq = unwrap(msg.seq, s.returns_credited, SEQ_BITS)
    ack = (Send(ReturnAck(s.node, msg.seq)),)
    if seq == s.returns_credited + 1 and not at_end(s.returns_credited):
        return SessionStep(evolve(s, returns_credited=seq), ack)
    if seq <= s.returns_credited:
        return SessionStep(s, ack)
    return SessionStep(s)


def confirm(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """RESUME(n, q): write off what is open; behind (q below the last debit held): admit; a
    pending RETURN numbered next is credited (not at the end of the numbering); the number after
    max(C, q) is voided; answer ADMIT(n, k, C) with k the last transaction closed, which the node
    takes as settled.

    A re-sent copy (same nonce and q, nothing held since) gets the same answer. A SYNC's counts
    also carry the node's ltx: tx moves up to it (never back); their ADMIT carries n with
    ``SYNC_CONFIRMED`` flipped. Counts that repeat the last answered may come from another
    start of the node with the same SYNC's nonce (a copy of the SYNC reached it after a
    restart): what is open is written off and tx moves up to an ltx above it first, C stays
    (``repeat_counts``). Counts here move
    no W (``repeat_counts`` says why)."""
    seq, key = unwrap(msg.seq, s.returns_credited, SEQ_BITS), _answered(msg)
    nonce = msg.nonce ^ SYNC_CONFIRMED if msg.is_counts else msg.nonce
    if answered(s, key, seq):
        return repeat_counts(s, msg, nonce) if msg.is_counts else _repeat(s, nonce)
    behind = seq < s.returns_credited
    if behind:  # the record lacks a debit the supervisor holds: the node starts afresh
        step = admitted_afresh(s)
    else:  # the older record may not hold how the node resolved it
        step = resolve(s, Outcome.WRITTEN_OFF) if s.phase is not IDLE else SessionStep(s)
        s = step.session
        credits = msg.pending_mj and not msg.flags & Debit.DRAW and not at_end(s.returns_credited)
        if seq == s.returns_credited + 1 and credits:
            amount = msg.pending_mj * QUANTUM_UJ
            s = evolve(s, returns_credited=seq, returned=s.returned + amount)
            credited = (ReturnCredited(s.node, seq, amount),)
            step = SessionStep(s, (*step.actions, *credited), step.credit + amount)
    s = step.session
    if msg.is_counts:  # the node settled up to its ltx: no transaction begins at or below it
        s = evolve(s, tx=max(s.tx, ltx_of(s, msg)))  # W stays: see ``repeat_counts``
    void = capped(max(s.returns_credited, seq) + 1)  # any debit in flight from an old history
    s = evolve(s, returns_credited=void, resume_nonce=key, resume_from=seq, resume_to=void)
    admitted = (Admitted(s.node, s.tx, void),) if behind else ()
    answer = Send(_confirmation(s, nonce))
    return SessionStep(s, (*step.actions, *admitted, answer), step.credit)


def _repeat(s: Session, nonce: int) -> SessionStep:
    return SessionStep(s, (Send(_confirmation(s, nonce)),))


def repeat_counts(s: Session, msg: Debit, nonce: int) -> SessionStep:
    """The last answered counts again (same nonce and q, C unchanged): the same answer, but with
    what is open written off first and tx moved up to their ltx when it is above tx: the ltx of
    a later start of the node that answered a copy of the same SYNC. Without the move that start
    took the old answer, its ltx stayed B above tx, and the next B intentions were written off
    as old. Without the write-off, counts of a start from an older image (same q, an ltx at
    most tx) were answered with k = tx - 1 while tx was open, though the node's earlier record
    may have taken tx: the image took INTENTION(tx) again, received twice what was delivered
    once (``canergy prove --rules witnessed``: ``P`` of the ADMIT sent). An honest node's
    retry that crosses its confirmation so costs the grant begun since: written off, which the
    node, holding it, still commits by its timeout.

    The number after C is voided too (C + 1, the answer's Q unchanged): the later record may
    have adopted the first answer and numbered a RETURN C + 1, still in flight when the image,
    confirmed by the repeat, holds what it returned; credited, it gave the supervisor back
    what the image still spends (1 mJ in
    ``test_a_return_of_the_record_an_image_repeats_the_counts_of_is_not_credited``). The next
    repeat is none (C moved): counts again are answered afresh, found behind. An honest node
    whose two answers both arrived so loses its first RETURN after the confirmation
    (acknowledged, not credited); its draw is acknowledged as ever.

    Counts outside a start move no W, here or in ``confirm``: they may come from a record the
    node no longer holds (a life before a JOIN whose number the admission voided to C, a start
    since found behind, another start of an earlier life answering the same SYNC, or a late
    RESUME of an earlier life answered after the JOIN, whose nonce its counts then carry), and
    on the wire nothing tells them apart. W moved to such an
    ltx let begins run past the node's own ltx + B (``canergy prove --rules witnessed`` found
    it: clause ``witness``). A window so used up is opened by a re-sync of the node
    (``resync_session``), whose counts come under its own fresh nonce (``take_counts``)."""
    step = resolve(s, Outcome.WRITTEN_OFF) if s.phase is not IDLE else SessionStep(s)
    s = evolve(step.session, tx=max(step.session.tx, ltx_of(s, msg)))
    answer = Send(_confirmation(s, nonce))
    s = evolve(s, returns_credited=capped(s.returns_credited + 1))  # a debit in flight voided
    return SessionStep(s, (*step.actions, answer), step.credit)


def ltx_of(s: Session, msg: Debit) -> int:
    """The counts' ltx (16 bits) widened against tx, held below ``COUNTER_BOUND`` (``capped``):
    up to 2^15 - 1 ahead each, counts repeated without a key walked tx and W past the bound."""
    return capped(unwrap(msg.amount_mj, s.tx, TX_BITS))


def _answered(msg: Debit) -> int:
    """What the last answer remembers of a start: its nonce, and above it whether the start was
    a SYNC's counts (a stale ADMIT a node took for a SYNC does not replay a RESUME's answer)."""
    return msg.nonce | (1 << NONCE_BITS if msg.is_counts else 0)


def answered(s: Session, nonce: int, seq: int) -> bool:
    """RESUME(nonce, seq) is the last one answered and nothing was held since (``resume_to`` 0:
    none answered yet; a real answer's is at least 1)."""
    last = (s.resume_to, s.resume_nonce, s.resume_from)
    return s.resume_to != 0 and last == (s.returns_credited, nonce, seq)


def admitted_afresh(s: Session) -> SessionStep:
    """A node admitted without books (a JOIN, or a RESUME found behind): the hardened write-off
    and lift; W stays where it is. The admission is no evidence of what the node holds: its
    ADMIT may be lost, or the JOIN or RESUME may be a late frame of an earlier start, and the
    node then holds an ltx below tx. Moving W up to tx let the supervisor begin past that
    ltx + B, and a supervisor image from before those begins, started, created energy from
    their late INTENTIONs. A lift that leaves tx + 1 beyond W + B closes the window until a
    re-sync of the node (``resync_session``)."""
    return h.write_off_and_lift(s)


def admit(t: Timing, s: Session, msg: Join, now: int) -> SessionStep:
    """JOIN(n): the hardened admission, and the number after C voided as at a RESUME (C + 1 held,
    ADMIT(n, k, C + 1)): a debit the lost record left in flight under it is behind, and no number
    is issued by both the node's old record and its new life. The admission is remembered
    (``join_*``).

    A JOIN with the nonce of the last one admitted (``join_seq`` 0: none) is a copy of it (the
    node re-sent it, its ADMIT lost, or a duplicate): it gets the same ADMIT again (same n, k
    and C) and nothing moves, as if the first ADMIT had been duplicated on the bus (a second
    admission would void another number and lift tx again, for a node that may hold the
    first)."""
    if s.join_seq != 0 and s.join_nonce == msg.nonce:
        again = Admit(s.node, msg.nonce, wire_tx(s.join_tx), wrap(s.join_seq, SEQ_BITS))
        return SessionStep(s, (Send(again),))
    step = admitted_afresh(s)
    s = evolve(step.session, returns_credited=capped(step.session.returns_credited + 1))
    s = evolve(s, join_nonce=msg.nonce, join_tx=s.tx, join_seq=s.returns_credited)
    answer = Admit(s.node, msg.nonce, wire_tx(s.tx), wrap(s.returns_credited, SEQ_BITS))
    admitted = Admitted(s.node, s.tx, s.returns_credited)
    return SessionStep(s, (*step.actions, admitted, Send(answer)), step.credit)


def _confirmation(s: Session, nonce: int) -> Admit:
    """ADMIT(n, k, C): k the last transaction closed, C the last debit number held."""
    closed = s.tx if s.phase is IDLE else s.tx - 1
    return Admit(s.node, nonce, wire_tx(closed), wrap(s.returns_credited, SEQ_BITS))


def _sync(s: Session) -> Admit:
    """SYNC(n, tx, C): an ADMIT the node did not ask for."""
    return Admit(s.node, s.sync_nonce, wire_tx(s.tx), wrap(s.returns_credited, SEQ_BITS))


def start(t: Timing, s: Session, event: PowerLoss, now: int) -> SessionStep:
    """A start (after a power loss or from an older copy: the supervisor cannot tell): write
    off what is open and send SYNC(n) at once (its timer is due), re-sent every response
    timeout without end; grant nothing until the node has answered with its books
    (``Supervisor.unconfirmed``). The SYNC's nonce: ``sync_nonce_for``."""
    step = SessionStep(s)
    if s.phase not in (IDLE, *SYNC_PHASES):
        step = resolve(s, Outcome.WRITTEN_OFF)
    nonce = sync_nonce_for(step.session, event.nonce)
    s = evolve(step.session, phase=SYNCING, sync_nonce=nonce, deadline=now, resync=False)
    return SessionStep(s, step.actions, step.credit)


def sync_nonce_for(s: Session, nonce: int) -> int:
    """The nonce of a start's or a re-sync's SYNC, from the caller's fresh one:
    ``SYNC_CONFIRMED`` clear (a node takes no ADMIT with it set as a SYNC: ``answer_sync``),
    and never the nonce of the last start answered (``resume_nonce``; its lowest bit flipped
    then): counts under it with the same q would read as a repeat of that answer and get it
    again instead of being taken."""
    nonce &= 0xFFFF & ~SYNC_CONFIRMED
    if s.resume_to != 0 and nonce == wrap(s.resume_nonce, NONCE_BITS):
        nonce ^= 1
    return nonce


def resync_session(t: Timing, s: Session, nonce: int, now: int) -> SessionStep:
    """A re-sync of this one node: what a start does for it (SYNC(n) sent at once and re-sent
    every response timeout, its books then its counts taken under n whatever their ltx: tx =
    max(tx, ltx), W = ltx, C voided, ADMIT(n ^ ``SYNC_CONFIRMED``)), with nothing restored,
    nothing written off (only from IDLE) and no other session waiting for it (``resync`` set:
    ``Supervisor.unconfirmed`` skips it). For a node whose window is used up (tx + 1 > W + B:
    an admission lifted tx, or its answers were ignored) or whose counts are ignored: the SYNC
    only makes the node settle B further and void its pending debit, a loss, never a gain.
    ``nonce``: fresh and random, from the caller (the core draws none)."""
    if s.phase is not IDLE:
        raise LocalProtocolError(
            f"node {s.node}: a re-sync starts only with no transaction open and no start waiting"
        )
    nonce = sync_nonce_for(s, nonce)
    deadline = now + t.response_timeout_us
    s = evolve(s, phase=SYNCING, sync_nonce=nonce, deadline=deadline, resync=True)
    return SessionStep(s, (Send(_sync(s)),))


def join_while_syncing(t: Timing, s: Session, msg: Join, now: int) -> SessionStep:
    """JOIN while a SYNC waits: ignored at a start (a node without books cannot bound what a
    restored supervisor's discarded history sent); a re-sync ends (counts the node sent before
    it lost its books would show an ltx it no longer holds) and the JOIN is taken as in IDLE
    (``admit``): with nothing restored, every transaction the node can see is at most tx, at or
    below the k it is admitted at. Without it a node whose ADMIT was lost re-sent its JOIN,
    ignored, while it ignored the SYNC (not its nonce), for ever."""
    if not s.resync:
        return SessionStep(s)
    idle = evolve(s, phase=IDLE, sync_nonce=0, deadline=None, resync=False)
    return admit(t, idle, msg, now)


def resend_sync(t: Timing, s: Session, event: ResponseTimeout, now: int) -> SessionStep:
    """Re-send SYNC(n): the node may be off; the supervisor waits (it says for whom)."""
    if s.deadline is None or s.deadline > now:
        return SessionStep(s)
    s = evolve(s, deadline=now + t.response_timeout_us)
    return SessionStep(s, (Send(_sync(s)),))


def take_books(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """The SYNC's books (n, Rc): Gs moves up to Rc and the difference leaves Us (which may go
    below zero: a debt, no grant until it is covered); then the counts are awaited. Books with
    Rc unknown leave Gs as it is: that node holds nothing and takes its next fresh intention's
    Gs as its Rc, paying nothing back.

    Books answering a re-sync leave Gs as it is too: nothing was restored, so Gs holds what
    the node received already (a higher Rc only pays the node back less), and a JOIN that ends
    the re-sync takes no transaction number past the one whose ``H`` was fixed at that Gs
    (``canergy prove --rules witnessed``, the supervisor's JOIN).

    The counts before the books are ignored (the node re-sends both), other frames too."""
    if msg.nonce != s.sync_nonce or not msg.is_books:
        return SessionStep(s)
    if msg.rc_unknown or s.resync:
        return SessionStep(evolve(s, phase=SYNC_BOOKS))
    credited = unwrap(msg.credited_mj, s.delivered // QUANTUM_UJ, DELIVERED_BITS) * QUANTUM_UJ
    gain = max(0, credited - s.delivered)
    s = evolve(s, phase=SYNC_BOOKS, delivered=s.delivered + gain)
    return SessionStep(s, (), -gain)


def take_counts(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """The SYNC's counts (n, q, ltx) after its books: tx = max(tx, ltx), W = ltx (every
    transaction of a discarded history is at or below it: the node settled B ahead), then as a
    RESUME: C = max(C, q) + 1 voids any debit in flight, ADMIT(n, tx, C) answers.

    Counts of a node admitted afresh that has taken no fresh intention since (``Debit.afresh``:
    it holds nothing, and its books are unknown or a floor its record kept, maybe an older
    copy's) with q above C + 1 show a start from an image older than that admission: no debit
    runs past C + 1 without the supervisor holding it, so it held q - C - 1 debits and the
    admission after this image, and the node may have drawn from grants this image still
    counts in Us (received after it, then its books lost or found behind). Those draws are at
    most q - C - 1, each at most ``AMOUNT_MAX_MJ``: so much moves from Us to Gs
    (``ahead_of_image``), a loss (a debt until returns cover it) where the image would
    otherwise grant again what the node used. With q at most C + 1 the node drew nothing since
    the image, and Gs is left as it is."""
    if msg.nonce != s.sync_nonce:
        return SessionStep(s)
    if msg.is_books:
        return take_books(t, s, msg, now)
    if not msg.is_counts:
        return SessionStep(s)
    ahead = ahead_of_image(s, msg)
    moved = ahead.amount if ahead is not None else 0
    settled = ltx_of(s, msg)
    s = evolve(s, phase=IDLE, sync_nonce=0, deadline=None, witness=settled, resync=False)
    s = evolve(s, delivered=s.delivered + moved)
    step = confirm(t, s, msg, now)
    report = () if ahead is None else (ahead,)
    return SessionStep(step.session, (*report, *step.actions), step.credit - moved)


def ahead_of_image(s: Session, msg: Debit) -> AheadOfImage | None:
    """What the counts ``msg`` move from Us to Gs (``take_counts``), or None: nothing unless
    they are ``afresh`` with q above C + 1."""
    numbers = unwrap(msg.seq, s.returns_credited, SEQ_BITS) - s.returns_credited - 1
    if not msg.afresh or numbers <= 0:
        return None
    return AheadOfImage(s.node, numbers)


def supervisor_record(s: Session) -> tuple[object, ...]:
    """The hardened record, the last RESUME answered and the last JOIN admitted (a start's
    phases are stored as IDLE: every start is one)."""
    stored = evolve(s, phase=IDLE) if s.phase in SYNC_PHASES else s
    answered = (s.resume_nonce, s.resume_from, s.resume_to)
    return (*h.supervisor_record(stored), *answered, s.join_nonce, s.join_tx, s.join_seq)


OPEN = (WAIT_ACK, ACKED, WAIT_CONFIRM)
SUPERVISOR = SupervisorTable(
    "witnessed",
    (IDLE, WAIT_ACK, ACKED, WAIT_CONFIRM, SYNCING, SYNC_BOOKS),
    [
        cell(IDLE, Begin, begin, to=WAIT_ACK),
        cell(ACKED, Decide, common.decide, to=WAIT_CONFIRM),
        cell(WAIT_ACK, Ack, on_ack, to=(ACKED, STAY)),
        cell(OPEN, Committed, on_committed, to=(IDLE, STAY)),
        cell(WAIT_CONFIRM, Aborted, on_aborted, to=(IDLE, STAY)),
        cell((IDLE, *OPEN), Return, h.credit_return),
        cell((IDLE, *OPEN), Join, admit, to=(IDLE, STAY)),
        cell((WAIT_ACK, WAIT_CONFIRM), ResponseTimeout, h.resend_or_write_off, to=(IDLE, STAY)),
        cell((IDLE, *OPEN), Debit, on_debit, to=(IDLE, STAY)),
        cell(ANY, PowerLoss, start, to=SYNCING),
        cell((SYNCING, SYNC_BOOKS), ResponseTimeout, resend_sync),
        cell(SYNCING, Debit, take_books, to=(SYNC_BOOKS, STAY)),
        cell(SYNC_BOOKS, Debit, take_counts, to=(IDLE, STAY)),
        cell((SYNCING, SYNC_BOOKS), Join, join_while_syncing, to=(IDLE, STAY)),
    ],
    supervisor_record,
)

# -- client ----------------------------------------------------------------------------------


def on_intention(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """INTENTION(k, a, Gs): as the hardened rules, but Gs pays back only from a fresh
    intention (k > ltx): an intention of a discarded supervisor history (at or below the ltx
    a SYNC settled) carries a Gs nobody holds."""
    tx = unwrap(msg.tx, c.last_tx, TX_BITS)
    if tx <= c.last_tx and not c.credited_unknown:
        return ClientStep(c, reply_for(c, tx, c.outcome) if tx == c.last_tx else ())
    return h.on_intention(t, c, msg, now)


def can_debit(c: ClientState) -> bool:
    """One numbered debit at a time (a return or a draw), none before the supervisor has
    confirmed the node's books, and none numbered at the end of the numbering."""
    return c.return_pending == 0 and c.phase in BOOKED and not at_end(c.return_seq)


def draw_of(c: ClientState) -> Debit:
    """DRAW(q, x): the pending draw."""
    return Debit(
        c.node, 0, Debit.DRAW, wrap(c.return_seq, SEQ_BITS), c.return_pending // QUANTUM_UJ
    )


def resume_of(c: ClientState) -> Debit:
    """RESUME(n, q, x): the node's start, its last debit number and what of it is pending."""
    flags = Debit.START | (Debit.DRAW if c.pending_draw else 0)
    pending = c.return_pending // QUANTUM_UJ
    return Debit(c.node, c.nonce, flags, wrap(c.return_seq, SEQ_BITS), pending)


def _check_debit(c: ClientState) -> None:
    """``can_debit``, or a LocalProtocolError saying why not."""
    if at_end(c.return_seq):
        raise LocalProtocolError(
            f"node {c.node}: debit {c.return_seq} is the last below {COUNTER_END:,}: its books "
            "must start again"
        )
    if not can_debit(c):
        raise LocalProtocolError("a debit is still waiting for its acknowledgement")


def draw(t: Timing, c: ClientState, event: Spend, now: int) -> ClientStep:
    """Uc -= x as debit q + 1, persist, send DRAW(q + 1, x); the actuator gets x on its ack."""
    _check_debit(c)
    check_amount(event.amount)
    step = start_return(t, c, event.amount, now)
    c = evolve(step.client, pending_draw=True)
    return ClientStep(c, (Send(draw_of(c)),))


def give_back(t: Timing, c: ClientState, event: GiveBack, now: int) -> ClientStep:
    """Uc -= x, q += 1, persist, send RETURN(q, x); re-sent until RETURN_ACK(q)."""
    _check_debit(c)
    return start_return(t, c, event.amount, now)


def on_debit_ack(t: Timing, c: ClientState, msg: ReturnAck, now: int) -> ClientStep:
    """RETURN_ACK(q) for the pending debit: done; a draw goes to the actuator (spent += x)."""
    step = h.on_return_ack(t, c, msg, now)
    if step.client is c or not c.pending_draw:
        return step
    released = evolve(step.client, spent=c.spent + c.return_pending, pending_draw=False)
    return ClientStep(released, step.actions)


def resend_debit(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Re-send the pending RETURN or DRAW under the same number."""
    step = h.resend_return(t, c, event, now)
    if not c.pending_draw or step.client is c:
        return step
    return ClientStep(step.client, (Send(draw_of(c)),))


def resume(t: Timing, c: ClientState, event: PowerLoss, now: int) -> ClientStep:
    """A start with a record (after a power loss or from an older copy: the node cannot tell):
    lose the held intention, send RESUME(n, q, pending) and move nothing until ADMIT(n)."""
    c = evolve(h._drop_hold(c), phase=RESUMING, nonce=event.nonce, return_deadline=now)
    return resend_resume(t, c, RETURN_TIMEOUT, now)


def resend_resume(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Re-send RESUME(n, q, pending) with the same nonce."""
    if c.return_deadline is None or c.return_deadline > now:
        return ClientStep(c)
    c = evolve(c, return_deadline=now + t.return_retry_us)
    return ClientStep(c, (Send(resume_of(c)),))


def resume_again(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """An intention before the books are confirmed: it moves nothing; RESUME is re-sent."""
    return ClientStep(c, (Send(resume_of(c)),))


RECORD_MJ = 1 << 32
"""A record keeps Rc in mJ modulo this (the C client's u32): its books read it so."""
ZERO_FLOOR_UJ = (1 << DELIVERED_BITS) * QUANTUM_UJ
"""A known Rc of 0 mJ modulo ``RECORD_MJ`` kept as a floor: 2^24 mJ, the same 24 bits on the
wire, where 0 would read as no floor (``floor_of``)."""


def books_of(c: ClientState) -> int | None:
    """The Rc a node's books report, in mJ: its Rc; after an admission afresh and until a fresh
    intention, the Rc its record held when it was found behind (a floor: only what it took), or
    unknown (``None``) without one (after a JOIN, 0 mJ: it would be unwrapped near Gs, above it
    when Gs mod 2^24 mJ >= 2^23 mJ)."""
    if c.credited_unknown and (c.credited // QUANTUM_UJ) % RECORD_MJ == 0:
        return None
    return c.credited // QUANTUM_UJ


def floor_of(c: ClientState) -> int:
    """The Rc a record found behind keeps for its books (``books_of``): its Rc or its floor. A
    known Rc of 0 mJ (modulo ``RECORD_MJ``: a node admitted where Gs was a multiple of 2^24 mJ,
    or one that received 2^32 mJ) is kept as ``ZERO_FLOOR_UJ`` more, or its books would say
    unknown and leave a restored supervisor's Gs below what the node received."""
    if c.credited_unknown or (c.credited // QUANTUM_UJ) % RECORD_MJ:
        return c.credited
    return c.credited + ZERO_FLOOR_UJ


def answer_of(c: ClientState) -> tuple[Send, Send]:
    """The answer to SYNC(n): the books (n, Rc: ``books_of``), then the counts (n, q, ltx)."""
    books = Debit.books(c.node, c.nonce, books_of(c))
    counts = Debit.counts(
        c.node, c.nonce, wrap(c.return_seq, SEQ_BITS), wire_tx(c.last_tx), c.credited_unknown
    )
    return Send(books), Send(counts)


def answer_sync(t: Timing, c: ClientState, msg: Admit, now: int) -> ClientStep:
    """SYNC(n) (an ADMIT not answering this node's start): the supervisor started, maybe from an
    older copy. Settle the next B transactions (ltx += B: none of a discarded history can be
    above), drop the held intention, persist, answer with the books and the counts, and move
    nothing until ADMIT(n) (a pending debit is voided: dropped on the answer, never credited).

    An ADMIT with ``SYNC_CONFIRMED`` set is no SYNC (a supervisor's SYNC has it clear) and is
    ignored: it may confirm counts this node sent earlier, and taking it as a SYNC answered it
    with counts whose confirmation came back as a SYNC again, without end."""
    if msg.nonce & SYNC_CONFIRMED:
        return ClientStep(c)
    c = evolve(
        h._drop_hold(c),
        phase=SYNCING,
        nonce=msg.nonce,
        last_tx=capped(c.last_tx + t.window),
        outcome=Outcome.SETTLED,
        return_deadline=now + t.return_retry_us,
    )
    return ClientStep(c, answer_of(c))


def resend_answer(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Re-send the books and the counts answering SYNC(n)."""
    if c.return_deadline is None or c.return_deadline > now:
        return ClientStep(c)
    return ClientStep(evolve(c, return_deadline=now + t.return_retry_us), answer_of(c))


def answer_again(t: Timing, c: ClientState, msg: Intention, now: int) -> ClientStep:
    """An intention while the answer waits for its ADMIT: it moves nothing; the answer is
    re-sent."""
    return ClientStep(c, answer_of(c))


def on_start_answer(t: Timing, c: ClientState, msg: Admit, now: int) -> ClientStep:
    """ADMIT while a start waits: the answer to it (``on_confirm``; a SYNC's answer is
    confirmed with ``SYNC_CONFIRMED`` flipped in its nonce), the same SYNC again (the answer is
    re-sent), or another nonce: a supervisor's SYNC (``answer_sync``)."""
    expected = c.nonce ^ SYNC_CONFIRMED if c.phase is SYNCING else c.nonce
    if msg.nonce == expected:
        return on_confirm(t, c, msg, now)
    if c.phase is SYNCING and msg.nonce == c.nonce:
        return ClientStep(c, answer_of(c))
    return answer_sync(t, c, msg, now)


def on_confirm(t: Timing, c: ClientState, msg: Admit, now: int) -> ClientStep:
    """ADMIT(n, k, Q) answering this start: Q = q + 1 confirms the books (everything up to k
    settled, the pending debit settled: a return credited, a draw dropped unreleased); a larger
    Q finds them behind: admitted afresh at k and Q, as after JOIN (what the actuator used
    stays counted), but its Rc kept as a floor its books report (``books_of``): a supervisor
    started from a copy older than the admission moves Gs up to what the node took.

    A RESUME confirmed with k below ltx (the node settled ahead for a SYNC whose counts never
    arrived) is followed by the counts, as a SYNC's answer under the RESUME's nonce: without
    them the supervisor's tx and W stay behind, the node ignores its next intentions as old and
    the window closes for good (``resync``)."""
    q = unwrap(msg.seq, c.return_seq, SEQ_BITS)
    if q >= COUNTER_BOUND:  # no supervisor confirms a number there (``capped``)
        return ClientStep(c)
    if q == c.return_seq + 1:
        closed = unwrap(msg.tx, c.last_tx, TX_BITS)
        if closed > c.last_tx:  # resolved by the supervisor: never again by this record
            c = evolve(c, last_tx=closed, outcome=Outcome.SETTLED)
        confirmed = evolve(
            c,
            phase=IDLE,
            nonce=0,
            return_seq=q,
            return_pending=0,
            pending_draw=False,
            return_deadline=None,
        )
        if c.phase is RESUMING and closed < c.last_tx:
            return resync(t, evolve(confirmed, nonce=c.nonce), now)
        return ClientStep(confirmed)
    if q < c.return_seq + 1:
        return ClientStep(c)
    fresh = ClientState(
        c.node,
        credited=floor_of(c),  # a floor for the books only (``books_of``): nothing paid back
        spent=c.spent,
        last_tx=msg.tx,
        outcome=Outcome.SETTLED,
        return_seq=q,
        credited_unknown=True,
    )
    return ClientStep(fresh)


def resync(t: Timing, c: ClientState, now: int) -> ClientStep:
    """Confirmed books whose ltx is above the supervisor's tx: SYNCING under nonce n, the counts
    (n, q, ltx) sent (with the books, ignored outside a start) until ADMIT(n ^ SYNC_CONFIRMED),
    which moves the supervisor's tx and W up to ltx. Nothing moves meanwhile."""
    c = evolve(c, phase=SYNCING, return_deadline=now + t.return_retry_us)
    return ClientStep(c, answer_of(c))


def client_record(c: ClientState) -> tuple[object, ...]:
    """The hardened record and whether the pending debit is a draw."""
    record = h.client_record(c)
    return (*record, c.pending_draw) if record else ()


BOOKED = (IDLE, HOLDING)

CLIENT = ClientTable(
    "witnessed",
    (IDLE, HOLDING, JOINING, RESUMING, SYNCING),
    [
        cell(IDLE, Intention, on_intention, to=(HOLDING, STAY)),
        cell(HOLDING, Intention, on_intention),
        cell(BOOKED, Commit, h.on_command, to=(IDLE, STAY)),
        cell(BOOKED, Abort, h.on_command, to=(IDLE, STAY)),
        cell(BOOKED, ReturnAck, on_debit_ack),
        cell(HOLDING, CommandTimeout, h.timeout_commit, to=(IDLE, STAY)),
        cell(BOOKED, ReturnTimeout, resend_debit),
        cell(BOOKED, Spend, draw),
        cell(BOOKED, GiveBack, give_back),
        cell(BOOKED, PowerLoss, resume, to=RESUMING),
        cell(ANY, BooksLost, h.join, to=JOINING),
        cell(JOINING, ReturnTimeout, h.resend_join),
        cell(JOINING, Intention, h.join_again),
        cell(JOINING, PowerLoss, h.rejoin),
        cell(JOINING, Admit, h.on_admit, to=(IDLE, STAY)),
        cell(BOOKED, Admit, answer_sync, to=(SYNCING, STAY)),
        cell(RESUMING, ReturnTimeout, resend_resume),
        cell(RESUMING, Intention, resume_again),
        cell(RESUMING, PowerLoss, resume),
        cell(RESUMING, Admit, on_start_answer, to=(IDLE, SYNCING, STAY)),
        cell(SYNCING, ReturnTimeout, resend_answer),
        cell(SYNCING, Intention, answer_again),
        cell(SYNCING, PowerLoss, resume, to=RESUMING),
        cell(SYNCING, Admit, on_start_answer, to=(IDLE, STAY)),
    ],
    client_record,
    can_debit,
    can_debit,
)

__all__ = ["CLIENT", "SUPERVISOR"]
