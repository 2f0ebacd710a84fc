"""Every cell of the hardened tables as a step of a world: the symbolic handler moves the session
or the client, and the ghost state follows (it never changes what a node does).

A step gives the next world, the messages it may send (each with the condition under which it is
that kind), when it is enabled (local requests the core would refuse are not steps) and, for the
supervisor, what it moves into or out of the usable budget.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from canergy.messages import AMOUNT_MAX_MJ, DELIVERED_BITS, QUANTUM_UJ
from canergy.prove import symbolic as sym
from canergy.prove.invariant import COMMITTED
from canergy.prove.rules import Rules
from canergy.prove.symbolic import Term, z3
from canergy.prove.world import (
    BV16,
    BV32,
    INT,
    TO_CLIENT,
    TO_SUPERVISOR,
    H,
    Kind,
    Msg,
    World,
    epoch_of,
    msg_epoch,
)


@dataclass(frozen=True)
class Valid:
    """A schema ``fact`` over terms and the terms of one instance (``Step.valid``)."""

    name: str
    fact: Callable[..., Term]
    terms: tuple[Term, ...]

    def schema(self) -> Term:
        """``fact`` on fresh constants of the terms' sorts."""
        fresh = (z3.FreshConst(t.sort(), "v") for t in self.terms)
        return self.fact(*fresh)

    def instance(self) -> Term:
        return self.fact(*self.terms)


@dataclass(frozen=True)
class Step:
    after: World
    sent: tuple[tuple[Term, Msg], ...]
    enabled: Term
    credit: Term
    lemmas: tuple[tuple[str, Term], ...] = ()
    """Facts about the step proved first (each an obligation), then assumed for the rest."""
    valid: tuple[Valid, ...] = ()
    """Facts true whatever their terms (arithmetic, e.g. a sum of whole numbers of quanta is
    whole): each proved once on fresh constants in a solver holding nothing else, then its
    instance assumed with the lemmas (z3 takes in milliseconds alone what it does not decide
    beside the whole world)."""
    branches: tuple[tuple[str, Term], ...] = ()
    """The step's branches, named conditions on the state before and the frame delivered: that
    one of them holds is an obligation, and each goal is then proved branch by branch (z3 takes
    each branch in seconds where it gives up on the whole step)."""


_ZERO = {BV16: z3.BitVecVal(0, 16), BV32: z3.BitVecVal(0, 32), INT: z3.IntVal(0)}


def _msg(kind: Kind, **given: Term) -> Msg:
    zero = {
        "w": _ZERO[BV16],
        "amount": _ZERO[INT],
        "gs": _ZERO[INT],
        "nonce": _ZERO[BV16],
        "admit_tx": _ZERO[BV16],
        "admit_seq": _ZERO[BV16],
        "k": _ZERO[BV32],
        "q": _ZERO[BV32],
        "life": _ZERO[INT],
        "flags": _ZERO[INT],
        "start": z3.IntVal(-1),
        "sstart": z3.IntVal(-1),
        "epoch": _ZERO[INT],
        "rc": _ZERO[INT],
        "rcl": _ZERO[INT],
    }
    return Msg(kind, **{**zero, **given})


def _is(sent: sym.Sent, kind: Kind) -> Term:
    return z3.And(sent.present, sent.kind == int(kind.value))


def client_sent(w: World, sent: sym.Sent) -> tuple[tuple[Term, Msg], ...]:
    """What a client step sent, each kind with its ghosts read from the world after it."""
    c, life = w.c, w.life
    out: list[tuple[Term, Msg]] = []
    for kind in (Kind.ACK, Kind.COMMITTED, Kind.ABORTED):
        k = sym.unwrap(sent.a, c.last_tx, 16) + w.off_tx
        out.append((_is(sent, kind), _msg(kind, w=sent.a, k=k, life=life)))
    k = sym.unwrap(sent.a, c.return_seq, 16) + w.off_seq
    out.append((_is(sent, Kind.RETURN), _msg(Kind.RETURN, w=sent.a, amount=sent.b, k=k, life=life)))
    out.append((_is(sent, Kind.JOIN), _msg(Kind.JOIN, nonce=sent.a, life=life)))
    return tuple(out)


def supervisor_sent(w: World, sent: sym.Sent, life: Term) -> tuple[tuple[Term, Msg], ...]:
    """What a supervisor step sent, with its ghosts (``life``: of the JOIN an ADMIT answers)."""
    s, e = w.s, epoch_of(w)
    k = sym.unwrap(sent.a, s.tx, 16) - w.shift_tx
    out: list[tuple[Term, Msg]] = [
        (_is(sent, kind), _msg(kind, w=sent.a, amount=sent.b, gs=sent.c, k=k, epoch=e))
        for kind in (Kind.INTENTION, Kind.COMMIT, Kind.ABORT)
    ]
    q = sym.unwrap(sent.a, s.returns_credited, 16) - w.shift_seq
    out.append((_is(sent, Kind.RETURN_ACK), _msg(Kind.RETURN_ACK, w=sent.a, k=q)))
    admit = _msg(
        Kind.ADMIT,
        nonce=sent.a,
        admit_tx=z3.Int2BV(sent.b, 16),
        admit_seq=z3.Int2BV(sent.c, 16),
        k=w.tx,
        q=w.rc,
        life=life,
        epoch=e,
    )
    out.append((_is(sent, Kind.ADMIT), admit))
    return tuple(out)


# -- the client's steps ----------------------------------------------------------------------------


def _client_moved(
    w: World, c: sym.Client, gave: Term = 0, from_below: Term = 0, **ghost: Term
) -> World:
    """The world after a client step that kept its books: energy into its usable budget is
    ``received``; what the actuator used is ``spent`` and never comes back, except what a
    gateway takes back from below (``from_below``, its one move that lowers spent); ``cc``
    once it resolved the open transaction as committed."""
    grown = c.spent - w.c.spent
    used = z3.If(grown > 0, grown, 0)
    received = w.received + (c.usable - w.c.usable) + used + gave - from_below
    after = replace(
        w,
        c=c,
        received=received,
        spent=w.spent + used - from_below,
        given=w.given + gave,
        **ghost,
    )
    committed = z3.And(after.booked, after.last == after.tx, c.outcome == COMMITTED)
    return replace(after, cc=z3.Or(w.cc, committed))


def _client_step(w: World, result: tuple[sym.Client, sym.Sent], **ghost: Term) -> Step:
    c, sent = result
    after = _client_moved(w, c, **ghost)
    return Step(after, client_sent(after, sent), z3.BoolVal(True), z3.IntVal(0))


def on_intention(w: World, m: Msg) -> Step:
    c, sent = sym.on_intention(w.c, m.w, m.amount, m.gs)
    learned = z3.And(w.c.credited_unknown, z3.Not(c.credited_unknown))
    roff = z3.If(learned, H(msg_epoch(m, w), m.k) - c.credited, w.roff)
    step = _client_step(w, (c, sent), roff=roff)
    known = z3.And(w.booked, z3.Not(w.c.credited_unknown))
    paid_to = sym.unwrap_int(m.gs, w.c.credited / QUANTUM_UJ, DELIVERED_BITS) * QUANTUM_UJ
    names_h = z3.Implies(known, paid_to + w.roff == H(msg_epoch(m, w), m.k))
    return replace(step, lemmas=(("lemma: the wire's Gs names H(k)", names_h),))


def on_commit(w: World, m: Msg) -> Step:
    return _client_step(w, sym.on_command(w.c, True, m.w, m.amount))


def on_abort(w: World, m: Msg) -> Step:
    return _client_step(w, sym.on_command(w.c, False, m.w, m.amount))


def on_return_ack(w: World, m: Msg) -> Step:
    return _client_step(w, sym.on_return_ack(w.c, m.w))


def on_admit(w: World, m: Msg) -> Step:
    c, sent = sym.on_admit(w.c, m.nonce, m.admit_tx, m.admit_seq)
    taken = z3.And(z3.Not(w.booked), m.nonce == w.c.nonce)
    off_tx = z3.If(taken, m.k - z3.ZeroExt(16, m.admit_tx), w.off_tx)
    off_seq = z3.If(taken, m.q - z3.ZeroExt(16, m.admit_seq), w.off_seq)
    roff = z3.If(taken, z3.IntVal(0), w.roff)
    return _client_step(w, (c, sent), off_tx=off_tx, off_seq=off_seq, roff=roff)


def timeout_commit(w: World) -> Step:
    return _client_step(w, sym.timeout_commit(w.c))


def spend(w: World, amount: Term, rules: Rules) -> Step:
    c, allowed = rules.spend(w.c, amount)
    return Step(_client_moved(w, c), (), allowed, z3.IntVal(0))


def give_back(w: World, amount: Term) -> Step:
    c, sent, allowed = sym.give_back(w.c, amount)
    after = _client_moved(w, c, gave=amount)
    return Step(after, client_sent(after, sent), allowed, z3.IntVal(0))


def forward(w: World) -> Step:
    c, allowed = sym.forward(w.c)
    return Step(_client_moved(w, c), (), allowed, z3.IntVal(0))


def give_back_from_below(w: World, amount: Term) -> Step:
    c, sent, allowed = sym.give_back_from_below(w.c, amount)
    after = _client_moved(w, c, gave=amount, from_below=amount)
    return Step(after, client_sent(after, sent), allowed, z3.IntVal(0))


def resend_return(w: World) -> Step:
    return _client_step(w, sym.resend_return(w.c))


def client_power_loss(w: World, rules: Rules) -> Step:
    return _client_step(w, rules.client_power_loss(w.c))


def restore(w: World, image: sym.Client, rules: Rules) -> Step:
    """The node's record put back to an older ``image`` and the node started from it, as a
    start after a power loss (it cannot tell the two apart). What its usable budget gains is
    received; what the actuator used stays used (the ghost ``spent`` never goes back)."""
    c, sent = rules.client_power_loss(image)
    grown = c.usable - w.c.usable
    after = replace(w, c=c, received=w.received + grown)
    return Step(after, client_sent(after, sent), z3.BoolVal(True), z3.IntVal(0))


def restore_supervisor(w: World, image: sym.Session, rules: Rules) -> Step:
    """The supervisor's state file put back to an older ``image`` and the supervisor started
    from it, as after a power loss. Its usable budget Us comes back with the file: the session
    moves into Us what its books count less in the image (Ts + Gs - returned)."""
    step = rules.supervisor_power_loss(image)
    after = replace(w, s=step.session, cc=z3.And(w.cc, step.session.tx == w.s.tx))
    books = image.reserved + image.delivered - image.returned
    now = w.s.reserved + w.s.delivered - w.s.returned
    sent = supervisor_sent(after, step.sent, z3.IntVal(0))
    return Step(after, sent, z3.BoolVal(True), now - books + step.credit)


def books_lost(w: World, nonce: Term, rules: Rules) -> Step:
    """No valid record at start: a new life (JOINING, hardened); its usable budget is lost."""
    c, sent = rules.books_lost(w.c, nonce)
    zero32 = sym.counter(0)
    after = replace(
        w,
        c=c,
        lost=w.lost + w.c.usable,
        life=w.life + 1,
        admitted=z3.BoolVal(False),
        off_tx=zero32,
        off_seq=zero32,
        roff=z3.IntVal(0),
    )
    return Step(after, client_sent(after, sent), z3.BoolVal(True), z3.IntVal(0))


# -- the supervisor's steps ----------------------------------------------------------------------


def _session_step(w: World, step: sym.SessionStep, life: Term | None = None, **ghost: Term) -> Step:
    after = replace(w, s=step.session, **ghost)
    answers = z3.IntVal(0) if life is None else life
    return Step(after, supervisor_sent(after, step.sent, answers), z3.BoolVal(True), step.credit)


def on_ack(w: World, m: Msg) -> Step:
    return _session_step(w, sym.on_ack(w.s, m.w))


def on_committed(w: World, m: Msg) -> Step:
    return _session_step(w, sym.on_committed(w.s, m.w))


def on_aborted(w: World, m: Msg) -> Step:
    return _session_step(w, sym.on_aborted(w.s, m.w))


def on_return(w: World, m: Msg, rules: Rules) -> Step:
    return _session_step(w, rules.credit_return(w.s, m.w, m.amount))


def on_join(w: World, m: Msg) -> Step:
    step = sym.admit(w.s, m.nonce)
    s = step.session
    shift_tx = w.shift_tx + (s.tx - w.s.tx)
    shift_seq = w.shift_seq + (s.returns_credited - w.s.returns_credited)
    first = z3.And(m.life == w.life, z3.Not(w.admitted))
    admitted_at = z3.If(first, s.tx - shift_tx, w.admitted_at)
    return _session_step(
        w,
        step,
        m.life,
        shift_tx=shift_tx,
        shift_seq=shift_seq,
        admitted=z3.Or(w.admitted, first),
        admitted_at=admitted_at,
    )


def begin(w: World, amount: Term) -> Step:
    step = _session_step(w, sym.begin(w.s, amount), cc=z3.BoolVal(False))
    most = AMOUNT_MAX_MJ * QUANTUM_UJ
    valid = z3.And(amount % QUANTUM_UJ == 0, amount >= QUANTUM_UJ, amount <= most)
    return replace(step, enabled=z3.And(w.s.phase == sym.S_IDLE, valid, sym.may_begin(w.s)))


def decide(commit: bool) -> Callable[[World], Step]:
    def decided(w: World) -> Step:
        step = _session_step(w, sym.decide(w.s, commit))
        return replace(step, enabled=w.s.phase == sym.ACKED)

    return decided


def response_timeout(w: World, gives_up: Term) -> Step:
    return _session_step(w, sym.response_timeout(w.s, gives_up))


def supervisor_power_loss(w: World, rules: Rules) -> Step:
    return _session_step(w, rules.supervisor_power_loss(w.s))


# -- what each step can move ---------------------------------------------------------------------

ENERGY: dict[str, Callable[[World], Term]] = {
    "Ts": lambda w: w.s.reserved,
    "Gs": lambda w: w.s.delivered,
    "returned": lambda w: w.s.returned,
    "Uc": lambda w: w.c.usable,
    "received": lambda w: w.received,
    "spent": lambda w: w.spent,
    "given": lambda w: w.given,
    "lost": lambda w: w.lost,
}
"""The energies of a world, by name."""

MOVES: dict[str, tuple[str, ...]] = {
    "client receives INTENTION": ("Uc", "received"),
    "client receives COMMIT": ("Uc", "received"),
    "supervisor receives COMMITTED": ("Ts", "Gs"),
    "supervisor receives ABORTED": ("Ts",),
    "supervisor receives RETURN": ("returned",),
    "supervisor receives JOIN": ("Ts", "Gs"),
    "client: command timer (timeout-commit)": ("Uc", "received"),
    "client: spend": ("Uc", "spent"),
    "client: give back": ("Uc", "given"),
    "client: books lost (JOIN)": ("Uc", "lost"),
    "gateway: forward its usable budget below": ("Uc", "spent"),
    "gateway: give back from below": ("spent", "given"),
    "client: restored from an older image": ("Uc", "received"),
    "supervisor: restored from an older image": ("Ts", "Gs"),
    "supervisor: begin": ("Ts",),
    "supervisor: response timer (re-send or write off)": ("Ts", "Gs"),
}
"""The energies each step's rule moves: the proof shows each can move under the invariant (a
too strong invariant that ruled the branch out would prove that step vacuously)."""


# -- the table of steps ----------------------------------------------------------------------------

Deliver = Callable[[World, Msg], Step]
Local = Callable[[World], Step]


def deliveries(rules: Rules) -> dict[Kind, Deliver]:
    """Each message delivered to its receiver."""
    table: dict[Kind, Deliver] = {
        Kind.INTENTION: on_intention,
        Kind.COMMIT: on_commit,
        Kind.ABORT: on_abort,
        Kind.RETURN_ACK: on_return_ack,
        Kind.ADMIT: on_admit,
        Kind.ACK: on_ack,
        Kind.COMMITTED: on_committed,
        Kind.ABORTED: on_aborted,
        Kind.RETURN: lambda w, m: on_return(w, m, rules),
        Kind.JOIN: on_join,
    }
    assert set(table) == set(TO_CLIENT) | set(TO_SUPERVISOR)
    return table


def local(rules: Rules) -> dict[str, Local]:
    """Each local request and timer (amounts and choices are free constants)."""
    return {
        "client: command timer (timeout-commit)": timeout_commit,
        "client: spend": lambda w: spend(w, z3.Int("spend.amount"), rules),
        "client: give back": lambda w: give_back(w, z3.Int("give_back.amount")),
        "client: return timer (RETURN or JOIN again)": resend_return,
        "client: power loss": lambda w: client_power_loss(w, rules),
        "client: books lost (JOIN)": lambda w: books_lost(
            w, z3.BitVec("books_lost.nonce", 16), rules
        ),
        "gateway: forward its usable budget below": forward,
        "gateway: give back from below": lambda w: give_back_from_below(
            w, z3.Int("from_below.amount")
        ),
        "supervisor: begin": lambda w: begin(w, z3.Int("begin.amount")),
        "supervisor: decide commit": decide(True),
        "supervisor: decide abort": decide(False),
        "supervisor: response timer (re-send or write off)": lambda w: response_timeout(
            w, z3.Bool("response_timeout.gives_up")
        ),
        "supervisor: power loss": lambda w: supervisor_power_loss(w, rules),
    }
