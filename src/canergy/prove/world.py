"""What the proof reasons about: one supervisor session, its client, ghost state, and messages.

The ghost state is what an observer outside the protocol could keep and no node stores:
- **canonical counters**: the supervisor lifts its counters at an admission (by a multiple of
  2**16, invisible on the wire) and an admitted client counts from the wire's 16 bits, so each
  side's counters are mapped to one numbering (``shift_*`` on the supervisor, ``off_*`` on the
  client, both multiples of 2**16); a message carries its counter in that numbering;
- **energy over every life of the client**: ``received`` (all energy credited into its usable
  budget), ``given`` (all it debited to return), ``spent`` and ``lost`` (usable budgets lost with
  its books); ``roff`` maps its Rc to the supervisor's Gs after an admission (the wire carries Gs
  modulo 2**24 mJ);
- **lives**: ``life`` counts the client's losses of its books; ``admitted``/``admitted_at`` say
  whether, and at which transaction, the supervisor has admitted the current life;
- ``cc``: the client has committed the supervisor's open transaction;
- ``H`` (a function, shared by every world of one run): ``H(e, k)`` is the supervisor's Gs when
  transaction ``k`` began in its epoch ``e``, for the whole run (a prophecy: fixed once the run
  is, monotone within an epoch since Gs only grows there). Messages carry no Gs of their own; an
  INTENTION's Gs is ``H`` of its epoch and transaction. The hardened rules have one epoch, 0.
  Under the witnessed rules counts that end a supervisor's start begin a new epoch
  (``World.epoch``): the session may go on from an older image, below the Gs the discarded
  history fixed for the numbers it takes again, so each epoch has its own ``H``, equal below
  its base (``BASE_TX``, ``BASE_GS``: the tx and Gs it began at).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import Enum
from itertools import count
from typing import Any

from canergy.messages import MsgType
from canergy.prove import symbolic as sym
from canergy.prove.symbolic import COUNTER, Term, z3

H = z3.Function("H", z3.IntSort(), z3.BitVecSort(COUNTER), z3.IntSort())
"""Gs at the start of each transaction (epoch, canonical number), the run's prophecy."""
BASE_TX = z3.Function("base_tx", z3.IntSort(), z3.BitVecSort(COUNTER))
"""The tx an epoch began at (canonical): ``H`` of the epoch is its ``BASE_GS`` up to one past it."""
BASE_GS = z3.Function("base_gs", z3.IntSort(), z3.IntSort())

_names = count()


def _fresh(prefix: str, sort: Any) -> Term:
    return z3.Const(f"{prefix}{next(_names)}", sort)


BV32, BV16 = z3.BitVecSort(COUNTER), z3.BitVecSort(16)
INT, BOOL = z3.IntSort(), z3.BoolSort()


@dataclass(frozen=True)
class World:
    """A session, its client and the ghost state (see the module's docstring)."""

    s: sym.Session
    c: sym.Client
    shift_tx: Term
    shift_seq: Term
    off_tx: Term
    off_seq: Term
    roff: Term
    received: Term
    given: Term
    spent: Term
    lost: Term
    cc: Term
    life: Term
    admitted: Term
    admitted_at: Term
    pre: sym.Client | None = None
    """Witnessed rules: the node's record as it stood when its start began (the held intention
    dropped). While the start waits for the supervisor's confirmation this record, not the one
    the node started from (which may be an older image), is what the invariant speaks of
    (hardened: unused)."""
    starts: Term | None = None
    """Witnessed rules: how many starts the node has made (each draws a nonce: a power loss, a
    restore, a SYNC answered, a confirmation followed by the counts), a pure function of the
    history; a frame of a start carries its number (``Msg.start``). Hardened: unused."""
    top: Term | None = None
    """Witnessed rules: the highest return number any record of the node has held (canonical,
    over every life and image), a pure function of the history: no debit is numbered above it.
    Hardened: unused."""
    spre: sym.Session | None = None
    """Witnessed rules: the supervisor's session record as it stood when its current start
    (or re-sync) began (what was open written off). While the start waits for the node's books
    and counts this record, not the one it started from (which may be an older image), is what
    the invariant speaks of (hardened: unused)."""
    sstarts: Term | None = None
    """Witnessed rules: how many starts the supervisor has made (each draws a SYNC nonce: a
    power loss, a restore, a re-sync of the node), a pure function of the history; a SYNC
    carries the start it was sent in, a SYNC's books and counts the start whose SYNC they
    answer (``Msg.sstart``). Hardened: unused."""
    answering: Term | None = None
    """Witnessed rules: the supervisor's start whose SYNC the node's answer (while SYNCING)
    answers; -1: none (counts that follow a RESUME's confirmation). Hardened: unused."""
    jk: Term | None = None
    """Witnessed rules: the ghosts of the ADMIT of the last JOIN admitted (``Session.join_*``),
    which a copy of that JOIN gets again: its k and q in canonical numbering (``jk``, ``jq``)
    and the life of the JOIN it answers (``jlife``). Hardened: unused."""
    jq: Term | None = None
    jlife: Term | None = None
    lhi: Term | None = None
    """Witnessed rules: the highest ltx of the records of the node's current start (canonical):
    the record at the start and every record it answered from since (a SYNC's answer settles B
    ahead); outside a start, the ltx of the record it holds. Hardened: unused."""
    rk: Term | None = None
    """Witnessed rules: the ghosts of the supervisor's last answer to a start (a RESUME or a
    SYNC's counts; ``Session.resume_*``), which a repeat of that start's frame gets again with
    the same or a later k: its k in canonical numbering (``rk``) and the node's start it
    answered (``rstart``). Hardened: unused."""
    rstart: Term | None = None
    begun: Term | None = None
    """Witnessed rules: the highest transaction begun (canonical) in any history of the
    supervisor's, a pure function of the run: every INTENTION, COMMIT and ABORT names one at
    most it (a SYNC's counts move tx over numbers no transaction took). Hardened: unused."""
    taken: Term | None = None
    """Witnessed rules: the highest transaction the node has taken (canonical, over every life
    and image), a pure function of the history: an INTENTION it held, a COMMIT, an ABORT or a
    timeout-commit it resolved. Settling ahead (a SYNC's answer, a confirmation, an admission)
    moves its ltx and not this. Hardened: unused."""
    took: Term | None = None
    """Witnessed rules: how the node resolved ``taken`` (COMMITTED or ABORTED; NONE while it
    holds its intention). Hardened: unused."""
    sbegan: Term | None = None
    """Witnessed rules: the first of the node's starts (``starts``) that began after the
    supervisor's current start (or re-sync) did: a start answering its SYNC is one of them,
    and no confirmation of one is sent while it waits. Hardened: unused."""
    epoch: Term | None = None
    """Witnessed rules: the epoch of ``H`` the session is in (counts that end a start begin the
    next). Hardened: None, epoch 0 throughout."""
    copy: sym.Client | None = None
    """Witnessed rules: a copy of its record the node wrote (a backup), as a restore would
    start from it (the held intention dropped), any one of those it wrote, kept while
    ``copied``. Hardened: unused."""
    copied: Term | None = None
    """Witnessed rules: ``copy`` was written since the node's record last went back (its life,
    its Rc's scale or its numbering changed, or a confirmation kept books behind the record at
    the start): the copies the theorem's restore step takes. Hardened: unused."""
    scopy: sym.Session | None = None
    """Witnessed rules: a copy of its state file the supervisor wrote (a backup), any one of
    those it wrote, kept while ``scopied``, with the ghosts of the answers it remembers
    (``scopy_join``: ``jk``, ``jq``, ``jlife``; ``scopy_answer``: ``rk``, ``rstart``).
    Hardened: unused."""
    scopied: Term | None = None
    """Witnessed rules: ``scopy`` was written since the supervisor's record of the node last
    went back (``witnessed_proof.session_went_back``). Hardened: unused."""
    scopy_join: tuple[Term, Term, Term] | None = None
    scopy_answer: tuple[Term, Term] | None = None
    sforked: Term | None = None
    """Witnessed rules: the supervisor's start in progress, or its last, went on from an older
    image of its record (a restore) rather than its own (a power loss, a re-sync): its counts
    then end the copies written before. Hardened: unused."""

    # canonical views
    @property
    def tx(self) -> Term:
        """The supervisor's transaction."""
        return self.s.tx - self.shift_tx

    @property
    def rc(self) -> Term:
        """The supervisor's last credited return."""
        return self.s.returns_credited - self.shift_seq

    @property
    def last(self) -> Term:
        """The client's last resolved transaction."""
        return self.c.last_tx + self.off_tx

    @property
    def held(self) -> Term:
        return self.c.held_tx + self.off_tx

    @property
    def seq(self) -> Term:
        """The client's last return number."""
        return self.c.return_seq + self.off_seq

    @property
    def rc_true(self) -> Term:
        """The client's Rc on the supervisor's scale."""
        return self.c.credited + self.roff

    @property
    def open(self) -> Term:
        """A transaction is open (a witnessed start's two phases are not)."""
        return z3.Or(*(self.s.phase == p for p in (sym.WAIT_ACK, sym.ACKED, sym.WAIT_CONFIRM)))

    @property
    def booked(self) -> Term:
        return self.c.phase != sym.JOINING


_SESSION = {
    "phase": INT,
    "tx": BV32,
    "reserved": INT,
    "delivered": INT,
    "decision": INT,
    "returns_credited": BV32,
    "returned": INT,
    "resume_nonce": z3.BitVecSort(sym.KEY_BITS),
    "resume_from": BV32,
    "resume_to": BV32,
    "witness": BV32,
    "sync_nonce": BV16,
    "join_nonce": BV16,
    "join_tx": BV32,
    "join_seq": BV32,
    "resync": BOOL,
}
_CLIENT = {
    "usable": INT,
    "credited": INT,
    "spent": INT,
    "last_tx": BV32,
    "outcome": INT,
    "return_seq": BV32,
    "return_pending": INT,
    "credited_unknown": BOOL,
    "held_tx": BV32,
    "held_amount": INT,
    "phase": INT,
    "nonce": BV16,
    "pending_draw": BOOL,
}
_GHOST = {
    "shift_tx": BV32,
    "shift_seq": BV32,
    "off_tx": BV32,
    "off_seq": BV32,
    "roff": INT,
    "received": INT,
    "given": INT,
    "spent": INT,
    "lost": INT,
    "cc": BOOL,
    "life": INT,
    "admitted": BOOL,
    "admitted_at": BV32,
}


def any_world(name: str = "w", with_pre: bool = True) -> World:
    """A world of fresh constants: any state at all (``with_pre``: with the node's record at
    its start, which only the witnessed rules use)."""
    s = sym.Session(**{f: _fresh(f"{name}.s.{f}.", sort) for f, sort in _SESSION.items()})
    c = sym.Client(**{f: _fresh(f"{name}.c.{f}.", sort) for f, sort in _CLIENT.items()})
    ghost = {f: _fresh(f"{name}.{f}.", sort) for f, sort in _GHOST.items()}
    pre = any_image(f"{name}.pre") if with_pre else None
    starts = _fresh(f"{name}.starts.", INT) if with_pre else None
    top = _fresh(f"{name}.top.", BV32) if with_pre else None
    spre = any_session_image(f"{name}.spre") if with_pre else None
    sstarts = _fresh(f"{name}.sstarts.", INT) if with_pre else None
    answering = _fresh(f"{name}.answering.", INT) if with_pre else None
    jk = _fresh(f"{name}.jk.", BV32) if with_pre else None
    jq = _fresh(f"{name}.jq.", BV32) if with_pre else None
    jlife = _fresh(f"{name}.jlife.", INT) if with_pre else None
    lhi = _fresh(f"{name}.lhi.", BV32) if with_pre else None
    rk = _fresh(f"{name}.rk.", BV32) if with_pre else None
    rstart = _fresh(f"{name}.rstart.", INT) if with_pre else None
    begun = _fresh(f"{name}.begun.", BV32) if with_pre else None
    taken = _fresh(f"{name}.taken.", BV32) if with_pre else None
    took = _fresh(f"{name}.took.", INT) if with_pre else None
    sbegan = _fresh(f"{name}.sbegan.", INT) if with_pre else None
    epoch = _fresh(f"{name}.epoch.", INT) if with_pre else None
    copy = any_image(f"{name}.copy") if with_pre else None
    copied = _fresh(f"{name}.copied.", BOOL) if with_pre else None
    scopy = any_session_image(f"{name}.scopy") if with_pre else None
    scopied = _fresh(f"{name}.scopied.", BOOL) if with_pre else None
    sj = (_fresh(f"{name}.scopy.jk.", BV32), _fresh(f"{name}.scopy.jq.", BV32))
    scopy_join = (*sj, _fresh(f"{name}.scopy.jlife.", INT)) if with_pre else None
    sa = (_fresh(f"{name}.scopy.rk.", BV32), _fresh(f"{name}.scopy.rstart.", INT))
    scopy_answer = sa if with_pre else None
    sforked = _fresh(f"{name}.sforked.", BOOL) if with_pre else None
    return World(
        s, c, **ghost, pre=pre, starts=starts, top=top, spre=spre, sstarts=sstarts,
        answering=answering, jk=jk, jq=jq, jlife=jlife, lhi=lhi, rk=rk, rstart=rstart,
        begun=begun, taken=taken, took=took, sbegan=sbegan, epoch=epoch, copy=copy,
        copied=copied, scopy=scopy, scopied=scopied, scopy_join=scopy_join,
        scopy_answer=scopy_answer, sforked=sforked,
    )  # fmt: skip


def any_image(name: str = "image") -> sym.Client:
    """A record of fresh constants: any image the node's NV could be put back to (what the
    restore step may take is said by ``invariant.p_image``)."""
    return sym.Client(**{f: _fresh(f"{name}.{f}.", sort) for f, sort in _CLIENT.items()})


def any_session_image(name: str = "session_image") -> sym.Session:
    """A session record of fresh constants: any image the supervisor's state file could be put
    back to (``invariant.p_session_image`` says which)."""
    return sym.Session(**{f: _fresh(f"{name}.{f}.", sort) for f, sort in _SESSION.items()})


def initial_world() -> World:
    """Both sides new: nothing granted, no message sent, the client's first life admitted."""
    zero, zero32, no = z3.IntVal(0), sym.counter(0), z3.BoolVal(False)
    zero16 = z3.BitVecVal(0, 16)
    zero_key = z3.BitVecVal(0, sym.KEY_BITS)
    s = sym.Session(
        sym.S_IDLE, zero32, zero, zero, sym.NO_DECISION, zero32, zero, zero_key, zero32, zero32,
        zero32, zero16, zero16, zero32, zero32, no,
    )  # fmt: skip
    c = sym.Client(
        zero,
        zero,
        zero,
        zero32,
        z3.IntVal(0),
        zero32,
        zero,
        no,
        zero32,
        zero,
        sym.IDLE,
        zero16,
        no,
    )
    return World(
        s, c, zero32, zero32, zero32, zero32, zero, zero, zero, zero, zero, no, zero,
        z3.BoolVal(True), zero32, c, zero, zero32, s, zero, z3.IntVal(-1), zero32, zero32, zero,
        zero32, zero32, z3.IntVal(-1), zero32, zero32, zero, zero, zero, c, no, s, no,
        (zero32, zero32, zero), (zero32, zero), no,
    )  # fmt: skip


class Kind(Enum):
    """The messages of the hardened protocol."""

    INTENTION = MsgType.INTENTION
    COMMIT = MsgType.COMMIT
    ABORT = MsgType.ABORT
    RETURN_ACK = MsgType.RETURN_ACK
    ADMIT = MsgType.ADMIT
    ACK = MsgType.ACK
    COMMITTED = MsgType.COMMITTED
    ABORTED = MsgType.ABORTED
    RETURN = MsgType.RETURN
    JOIN = MsgType.JOIN
    DEBIT = MsgType.DEBIT


TO_CLIENT = (Kind.INTENTION, Kind.COMMIT, Kind.ABORT, Kind.RETURN_ACK, Kind.ADMIT)
TO_SUPERVISOR = (Kind.ACK, Kind.COMMITTED, Kind.ABORTED, Kind.RETURN, Kind.JOIN)
W_TO_SUPERVISOR = (*TO_SUPERVISOR, Kind.DEBIT)
"""The witnessed rules add DEBIT (a draw, a RESUME, a SYNC's books or counts)."""


@dataclass(frozen=True)
class Msg:
    """A message in flight: its wire fields and its ghosts.

    Wire: ``w`` the 16-bit counter (tx or return number; a JOIN's or ADMIT's nonce is
    ``nonce``), ``amount`` in mJ, ``gs`` an INTENTION's Gs in mJ modulo 2**24, ``admit_tx`` and
    ``admit_seq`` an ADMIT's counters. Ghost: ``k`` the counter in canonical numbering (an
    ADMIT's transaction), ``q`` an ADMIT's return number, ``life`` the sender's life (client
    messages, and the JOIN an ADMIT answers). A DEBIT (witnessed) has its number or first
    field in ``w``, its second in ``amount``, its ``flags`` and ``nonce``."""

    kind: Kind
    w: Term
    amount: Term
    gs: Term
    nonce: Term
    admit_tx: Term
    admit_seq: Term
    k: Term
    q: Term
    life: Term
    flags: Term
    start: Term
    """Ghost (witnessed rules): the node's start a DEBIT was sent in, or an ADMIT answers
    (``World.starts``; -1: no start's, a SYNC or a JOIN's answer)."""
    sstart: Term
    """Ghost (witnessed rules): the supervisor's start a SYNC was sent in, or whose SYNC a
    DEBIT (books or counts) answers (``World.sstarts``; -1: none)."""
    epoch: Term
    """Ghost (witnessed rules): the epoch of ``H`` a supervisor's frame was sent in
    (``World.epoch``); hardened: unused (epoch 0)."""
    rc: Term
    """Ghost (witnessed rules): a SYNC's books, the sender's Rc on the supervisor's scale
    (``World.rc_true`` of the record that sent them). Hardened: unused."""
    rcl: Term
    """Ghost (witnessed rules): a SYNC's books, the low 24 bits of the sender's Rc in mJ as it
    put them on the wire. Hardened: unused."""


_MSG = {
    "w": BV16,
    "amount": INT,
    "gs": INT,
    "nonce": BV16,
    "admit_tx": BV16,
    "admit_seq": BV16,
    "k": BV32,
    "q": BV32,
    "life": INT,
    "flags": INT,
    "start": INT,
    "sstart": INT,
    "epoch": INT,
    "rc": INT,
    "rcl": INT,
}


def any_msg(kind: Kind, name: str = "m") -> Msg:
    """A message of ``kind`` with every field a fresh constant: any message at all."""
    return Msg(kind, **{f: _fresh(f"{name}.{kind.name}.{f}.", sort) for f, sort in _MSG.items()})


def msg_fields(m: Msg) -> dict[str, Term]:
    return {f.name: getattr(m, f.name) for f in fields(m) if f.name != "kind"}


def epoch_of(w: World) -> Term:
    """The world's epoch of ``H`` (0 under the hardened rules)."""
    return z3.IntVal(0) if w.epoch is None else w.epoch


def msg_epoch(m: Msg, w: World) -> Term:
    """The epoch of ``H`` a message was sent in (0 under the hardened rules: ``w`` has none)."""
    return z3.IntVal(0) if w.epoch is None else m.epoch
