"""The proof obligations and their check by z3.

For every step (each message delivered to its receiver, each local request and timer) and every
clause (each clause of the invariant, ``P`` of each kind of message already in flight, ``P`` of
what the step sends, the budget the session moves): from the invariant, ``P`` of the delivered
message, the step's enabling condition and the theorem's assumptions, the clause holds after the
step. z3 answers ``unsat`` for the negation (proved) or gives a model: a counterexample to
induction, printed as a state, a message and a step.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass, fields, replace

from canergy.prove import EFFORT
from canergy.prove import invariant as inv
from canergy.prove import steps as st
from canergy.prove.invariant import ule
from canergy.prove.rules import HARDENED, RULES, Rules
from canergy.prove.symbolic import Term, z3
from canergy.prove.world import (
    BASE_GS,
    BASE_TX,
    TO_CLIENT,
    H,
    Kind,
    Msg,
    World,
    any_image,
    any_msg,
    any_session_image,
    any_world,
    epoch_of,
    initial_world,
)


@dataclass(frozen=True)
class Outcome:
    step: str
    clause: str
    proved: bool
    seconds: float
    counterexample: str = ""
    undecided: bool = False
    """z3 reached its limit (or gave up): failed, with no counterexample."""


def _apps(terms: Iterable[Term], wanted: Callable[[Term], bool]) -> list[Term]:
    """Every application in ``terms`` that ``wanted`` picks, each once."""
    seen: set[int] = set()
    found: list[Term] = []
    stack = list(terms)
    while stack:
        e = stack.pop()
        if e.get_id() in seen:
            continue
        seen.add(e.get_id())
        if z3.is_app(e) and wanted(e):
            found.append(e)
        stack.extend(e.children())
    return found


def _h_apps(terms: Iterable[Term]) -> list[tuple[Term, Term]]:
    """Every (epoch, number) ``H`` is applied to in ``terms``."""
    return [(e.arg(0), e.arg(1)) for e in _apps(terms, lambda e: bool(e.decl().eq(H)))]


def _int2bv_apps(terms: Iterable[Term]) -> list[Term]:
    """Every ``Int2BV`` application in ``terms``."""
    return _apps(terms, lambda e: bool(z3.is_app_of(e, z3.Z3_OP_INT2BV)))


def bridges(terms: Iterable[Term]) -> list[Term]:
    """What an ``Int2BV`` in ``terms`` reads as an integer: its argument modulo 2^n (z3's own
    definition, stated for each application so that the solver need not find it)."""
    return [z3.BV2Int(b) == b.arg(0) % (1 << b.size()) for b in _int2bv_apps(terms)]


def monotone(terms: Iterable[Term]) -> list[Term]:
    """``H`` is monotone within an epoch, instantiated at every pair of its applications, and
    its epoch's base Gs up to one past the base tx (each application whose epoch is not 0's
    literal: the hardened rules have no other)."""
    apps = _h_apps(terms)
    pairs = [
        z3.Implies(z3.And(e == f, ule(a, b)), H(e, a) <= H(f, b))
        for e, a in apps
        for f, b in apps
        if (e, a) != (f, b)
    ]
    based = [
        z3.Implies(ule(a, inv.one(BASE_TX(e))), H(e, a) == BASE_GS(e))
        for e, a in apps
        if not (z3.is_int_value(e) and e.as_long() == 0)
    ]
    return pairs + based


def drawn(w: World) -> Term:
    """What the supervisor's books count the session as holding: Ts + Gs - returned."""
    return w.s.reserved + w.s.delivered - w.s.returned


def resolved_consistently(before: World, after: World) -> Term:
    """The prophecy agrees with the run: when a transaction closes, Gs is H of the next."""
    closes = z3.And(before.open, z3.Not(after.open))
    return z3.Implies(closes, after.s.delivered == H(epoch_of(after), inv.one(after.tx)))


def _terms(w: World) -> list[Term]:
    records: list[object] = [w.s, w.c, w]
    records += [r for r in (w.pre, w.spre, w.copy, w.scopy) if r is not None]
    return [
        getattr(r, f.name)
        for r in records
        for f in fields(r)  # type: ignore[arg-type]
        if z3.is_expr(getattr(r, f.name))
    ] + [*(w.scopy_join or ()), *(w.scopy_answer or ())]


def changes(before: World, step: st.Step) -> Term:
    """The step changes some field of the world, or sends something."""
    moved = [a != b for a, b in zip(_terms(before), _terms(step.after), strict=True)]
    return z3.Or(*moved, *(cond for cond, _ in step.sent))


@dataclass(frozen=True)
class Goal:
    clause: str
    holds: Term
    assuming: Term | None = None


@dataclass(frozen=True)
class Proof:
    """The invariant a rule set is checked against: its clauses, ``P`` of each kind of message,
    the assumptions on a message delivered, and what each step can move."""

    state: tuple[tuple[str, inv.Clause], ...]
    message: dict[Kind, inv.MsgClause]
    deliverable: Callable[[Msg, World], Term]
    moves: dict[str, tuple[str, ...]]
    bounded: Callable[[World], Term] = inv.bounded
    """Bounded life (assumption 4), of the world before and after each step."""
    resolved: Callable[[World, World], Term] = resolved_consistently
    """How the prophecy ``H`` agrees with a step of the run."""

    def invariant(self, w: World) -> Term:
        return z3.And(*(clause(w) for _, clause in self.state))


HARDENED_PROOF = Proof(inv.STATE, inv.MESSAGE, inv.deliverable, st.MOVES)


def proof_of(rules: Rules) -> Proof:
    if not rules.witnessed:
        return HARDENED_PROOF
    from canergy.prove import witnessed_proof as wp

    return Proof(wp.STATE, wp.MESSAGE, wp.deliverable, wp.MOVES, wp.bounded, wp.resolved)


def goals(before: World, step: st.Step, proof: Proof = HARDENED_PROOF) -> Iterator[Goal]:
    after = step.after
    for name, clause in proof.state:
        yield Goal(name, clause(after))
    for kind, p in proof.message.items():
        m = any_msg(kind, "other")
        yield Goal(f"P({kind.name}) in flight", p(m, after), p(m, before))
    for cond, msg in step.sent:
        p = proof.message[msg.kind]
        yield Goal(f"P({msg.kind.name}) sent", z3.Implies(cond, p(msg, after)))
    yield Goal("budget moved = books moved", step.credit == drawn(before) - drawn(after))


@dataclass(frozen=True)
class StepCase:
    name: str
    build: Callable[[World], Built]


Built = tuple[st.Step, list[Term], Msg | None]
"""A step, its hypotheses beyond the invariant, and the message it delivers (if any)."""


def _delivery(
    kind: Kind, deliver: st.Deliver, proof: Proof = HARDENED_PROOF
) -> Callable[[World], Built]:
    def build(w: World) -> Built:
        d = any_msg(kind, "delivered")
        return deliver(w, d), [proof.message[kind](d, w), proof.deliverable(d, w)], d

    return build


def _local(local: st.Local) -> Callable[[World], Built]:
    return lambda w: (local(w), [], None)


def _restore(rules: Rules) -> Callable[[World], Built]:
    def build(w: World) -> Built:
        image = any_image("image")
        return st.restore(w, image, rules), [inv.p_image(image, w)], None

    return build


def _restore_supervisor(rules: Rules) -> Callable[[World], Built]:
    def build(w: World) -> Built:
        image = any_session_image("session_image")
        return st.restore_supervisor(w, image, rules), [inv.p_session_image(image, w)], None

    return build


RULES_WITNESSED = RULES["witnessed"]
RESTORE = "client: restored from an older image"
RESTORE_SUPERVISOR = "supervisor: restored from an older image"


def _witnessed_cases() -> list[StepCase]:
    from canergy.prove import witnessed_proof as wp

    proof = proof_of(RULES_WITNESSED)
    nonce = z3.BitVec("restore.nonce", 16)

    def restore(w: World) -> Built:
        image = any_image("image")
        step = wp.restore(w, image, nonce)
        after = step.after
        behind = z3.Or(wp.far_behind(after), wp.far_behind_c(after), wp.far_behind_rc(after))
        return step, [wp.p_image(image, w), z3.Not(behind)], None

    def restore_supervisor(w: World) -> Built:
        image = any_session_image("session_image")
        step = wp.restore_supervisor(w, image, nonce, wp.IMAGE_JOIN, wp.IMAGE_ANSWER)
        hyps = [
            wp.p_session_image(image, w),
            wp.not_from_an_image(w),
            wp.reported(image, w),
        ]
        return step, hyps, None

    out = [StepCase(RESTORE, restore), StepCase(RESTORE_SUPERVISOR, restore_supervisor)]
    for kind, deliver in wp.deliveries().items():
        receiver = "client" if kind in TO_CLIENT else "supervisor"
        out.append(StepCase(f"{receiver} receives {kind.name}", _delivery(kind, deliver, proof)))
    for name, local in wp.local().items():
        out.append(StepCase(name, _local(local)))
    return [StepCase(case.name, _keeping_copies(case.build)) for case in out]


def _keeping_copies(build: Callable[[World], Built]) -> Callable[[World], Built]:
    """``build`` with each side's copies kept while its record does not go back."""
    from canergy.prove import witnessed_proof as wp

    def kept(w: World) -> Built:
        step, hyps, delivered = build(w)
        return wp.keep_copies(w, step), hyps, delivered

    return kept


def cases(rules: Rules = HARDENED) -> list[StepCase]:
    """Every step: each message delivered, each local request and timer (and, when the rules
    say so, a start of either side from an older image of its record, first)."""
    if rules.witnessed:
        return _witnessed_cases()
    out = []
    if rules.restores:
        out += [
            StepCase(RESTORE, _restore(rules)),
            StepCase(RESTORE_SUPERVISOR, _restore_supervisor(rules)),
        ]
    for kind, deliver in st.deliveries(rules).items():
        receiver = "client" if kind in TO_CLIENT else "supervisor"
        out.append(StepCase(f"{receiver} receives {kind.name}", _delivery(kind, deliver)))
    for name, local in st.local(rules).items():
        out.append(StepCase(name, _local(local)))
    return out


def _describe(model: z3.ModelRef, label: str, record: object) -> str:
    parts = []
    for f in fields(record):  # type: ignore[arg-type]
        value = getattr(record, f.name)
        if f.name == "kind":
            parts.append(value.name)
            continue
        if not z3.is_expr(value):
            continue
        parts.append(f"{f.name}={model.eval(value, model_completion=True)}")
    return f"  {label}: " + ", ".join(parts)


def counterexample(model: z3.ModelRef, before: World, step: st.Step, delivered: Msg | None) -> str:
    lines = ["  a counterexample to induction: the invariant holds before, not after the step"]
    for label, w in (("before", before), ("after", step.after)):
        lines.append(_describe(model, f"{label}: session", w.s))
        lines.append(_describe(model, f"{label}: client", w.c))
        if w.pre is not None:
            lines.append(_describe(model, f"{label}: record at the start", w.pre))
        if w.spre is not None:
            lines.append(_describe(model, f"{label}: session at its start", w.spre))
        if w.copy is not None:
            lines.append(_describe(model, f"{label}: the node's copy", w.copy))
        if w.scopy is not None:
            lines.append(_describe(model, f"{label}: the supervisor's copy", w.scopy))
        skip = ("s", "c", "pre", "spre", "copy", "scopy", "scopy_join", "scopy_answer")
        ghost = {
            f.name: getattr(w, f.name)
            for f in fields(w)
            if f.name not in skip and getattr(w, f.name) is not None
        }
        lines.append(
            f"  {label}: ghost "
            + ", ".join(f"{k}={model.eval(v, model_completion=True)}" for k, v in ghost.items())
        )
    if delivered is not None:
        lines.insert(4, _describe(model, "delivered", delivered))
    for cond, msg in step.sent:
        if z3.is_true(model.eval(cond, model_completion=True)):
            lines.append(_describe(model, "sent", msg))
    return "\n".join(lines)


def check_step(
    case: StepCase,
    timeout_ms: int | None = None,
    rules: Rules = HARDENED,
    clauses: Collection[str] = (),
    effort: int = EFFORT,
) -> Iterator[Outcome]:
    """Every obligation of one step (given ``clauses``, only the goals named: the step's
    lemmas are still proved first and taken as facts). Each z3 check stops at ``effort`` (z3's
    ``rlimit``: the same on every machine) or after ``timeout_ms`` if given, whichever comes
    first."""
    proof = proof_of(rules)
    before = any_world("before", rules.witnessed)
    step, hyps, delivered = case.build(before)
    base = [
        proof.invariant(before),
        proof.bounded(before),
        proof.bounded(step.after),
        step.enabled,
        proof.resolved(before, step.after),
        *hyps,
    ]
    todo = [g for g in goals(before, step, proof) if not clauses or g.clause in clauses]
    solver = _solver(timeout_ms, effort)
    solver.add(*base)
    yield _possible(
        solver,
        (case.name, "can happen (changes the world or sends)"),
        [*monotone(base), changes(before, step)],
        "  the invariant and assumptions rule this step out entirely",
    )
    for energy in proof.moves.get(case.name, ()):
        yield _witness(solver, case.name, energy, before, step)
    limits = (timeout_ms, effort)
    for name, lemma in step.lemmas:
        # in the step's solver with the whole effort; undecided, branch by branch alone
        goal = Goal(name, lemma)
        yield _by_branch(solver, case.name, goal, before, step, delivered, limits, effort)
        solver.add(lemma)  # a failed lemma fails the proof; the rest are still checked
    for valid in step.valid:
        alone = _solver(timeout_ms, effort)
        yield _check(alone, case.name, valid.name, valid.schema(), None, before, step, delivered)
        solver.add(valid.instance())
    if step.branches:
        cover = z3.Or(*(cond for _, cond in step.branches))
        yield _check(
            solver, case.name, "its branches cover it", cover, None, before, step, delivered
        )
    for goal in todo:
        yield _by_branch(solver, case.name, goal, before, step, delivered, limits)


WHOLE_FIRST = 30_000_000
"""The effort z3 is given for ``goal`` on a step with branches as a whole before it is taken
branch by branch (most goals prove whole in a second; the branches multiply the time)."""


def _solver(timeout_ms: int | None, effort: int, seed: int | None = None) -> z3.Solver:
    """A solver whose checks stop at ``effort`` or after ``timeout_ms`` (None: no wall-clock
    limit), its search drawn from ``seed`` when one is given."""
    solver = z3.Solver()
    if timeout_ms is not None:
        solver.set("timeout", timeout_ms)
    solver.set("rlimit", effort)
    if seed is not None:
        solver.set("random_seed", seed)
    return solver


def _by_branch(
    solver: z3.Solver,
    step_name: str,
    goal: Goal,
    before: World,
    step: st.Step,
    delivered: Msg | None,
    limits: tuple[int | None, int],
    whole_first: int | None = None,
) -> Outcome:
    """``goal`` after the step: as a whole, and where z3 does not decide it so within
    ``whole_first`` (None: ``WHOLE_FIRST``; a step that names no branches: within ``limits``),
    in each branch in turn (a step without branches: as one, "the step"), each check in a new
    solver begun again with other seeds (``RESTARTS``), proved when every branch is, the first
    that fails named in its counterexample."""
    started = time.perf_counter()
    effort = limits[1]
    whole = (goal.clause, goal.holds, goal.assuming, before, step, delivered)
    first = WHOLE_FIRST if whole_first is None else whole_first
    if step.branches:
        solver.set("rlimit", min(first, effort))
    outcome = _check(solver, step_name, *whole)
    solver.set("rlimit", effort)
    if outcome.proved or not outcome.undecided:
        return replace(outcome, seconds=time.perf_counter() - started)
    for name, cond in step.branches or (("the step", z3.BoolVal(True)),):
        # each conjunct in a solver of its own checked once: z3 then simplifies and bit-blasts
        # the whole problem (a solver pushed and popped cannot), and forgets what it learnt on
        # the step's other goals ('a RESUME, found behind': P of the ADMIT sent, undecided
        # after 1,500 million steps in the step's solver, 48 million for its 51 conjuncts so)
        outcome = _check(solver, step_name, *whole, alone=(limits, cond))
        if not outcome.proved:
            where = f"  in its branch {name!r}\n" if step.branches else ""
            seconds = time.perf_counter() - started
            return replace(outcome, seconds=seconds, counterexample=where + outcome.counterexample)
    return Outcome(step_name, goal.clause, True, time.perf_counter() - started)


def _witness(
    solver: z3.Solver, step_name: str, energy: str, before: World, step: st.Step
) -> Outcome:
    """The step can move ``energy`` from a state where the invariant holds."""
    value = st.ENERGY[energy]
    moved = value(before) != value(step.after)
    return _possible(
        solver,
        (step_name, f"can move {energy}"),
        [*monotone([*solver.assertions(), moved]), moved],
        "  no state where the invariant holds lets this step move it",
    )


def _possible(
    solver: z3.Solver, name: tuple[str, str], facts: list[Term], impossible: str
) -> Outcome:
    """``facts`` can hold together with ``solver``'s (``name``: the step and the clause):
    proved by a model; failed, saying ``impossible``, when z3 shows none; undecided, with z3's
    reason, when it reaches its limit."""
    started = time.perf_counter()
    solver.push()
    solver.add(*facts)
    result = solver.check()
    text = {"sat": "", "unsat": impossible}.get(str(result), f"  z3: {solver.reason_unknown()}")
    solver.pop()
    seconds = time.perf_counter() - started
    return Outcome(*name, result == z3.sat, seconds, text, result == z3.unknown)


def _check(
    solver: z3.Solver,
    step_name: str,
    clause: str,
    holds: Term,
    assuming: Term | None,
    before: World,
    step: st.Step,
    delivered: Msg | None,
    alone: tuple[tuple[int | None, int], Term] | None = None,
) -> Outcome:
    """One obligation: ``holds`` after the step (``assuming`` of a message in flight before).
    ``P`` of a frame sent or remembered is checked conjunct by conjunct (z3 takes each in
    seconds where it gives up on their conjunction), the obligation proved when every one is.
    Given ``alone`` (limits and a condition), each check is made in a new solver holding
    ``solver``'s assertions and the condition."""
    started = time.perf_counter()
    facts = [holds] if assuming is None else [holds, assuming]
    held = [*solver.assertions(), *([] if alone is None else [alone[1]])]
    known = [*monotone([*held, *facts]), *bridges(facts)]
    split = clause.endswith(" sent") or clause in SPLIT
    parts = _conjuncts(holds) if split else [holds]
    at = (before, step, delivered)
    facts_known = [*known, *facts[1:]]
    for i, part in enumerate(parts):
        if alone is None:
            outcome = _check_part(solver, step_name, clause, part, facts_known, at)
        else:
            outcome = _restarts(alone[0], held, (step_name, clause, part, facts_known, at))
        if not outcome.proved:
            if len(parts) > 1:
                where = f"  its conjunct {i + 1} of {len(parts)}: {str(part)[-400:]}\n"
                outcome = replace(outcome, counterexample=where + outcome.counterexample)
            break
    return replace(outcome, seconds=time.perf_counter() - started)


RESTARTS = (8, 8, 4, 2)
"""A check made in a solver of its own is tried with random seeds 1, 2, ... in turn, the n-th
given ``effort // RESTARTS[n]`` of z3's steps (an eighth, an eighth, a quarter, a half: at most
``effort`` in all) until one decides it. How long z3 takes on one problem varies widely with the
seed and with what the process built before (the witnessed DEBIT's "remembered answer",
conjunct 27 of 53 in the branch "counts that end a re-sync, found behind": 61 to 123 million
steps with seeds 1 to 4 in a process of its own; after the hardened proof in the same process
158 to 250 million with four seeds of eight, within 300 million with a fifth, over 300 million
with three, over 1,500 million with seed 1 in a whole run): a search cut short and begun again
with another seed decides where one long search may not."""


def _restarts(
    limits: tuple[int | None, int],
    held: list[Term],
    check: tuple[str, str, Term, list[Term], tuple[World, st.Step, Msg | None]],
) -> Outcome:
    """``check`` (the step, the clause, the goal, facts and where) in a new solver holding
    ``held``, once per share of ``RESTARTS`` until one decides it (each attempt its own
    ``timeout_ms`` when one is given); undecided when none does."""
    timeout_ms, effort = limits
    step_name, clause, holds, known, where = check
    seconds = 0.0
    for seed, share in enumerate(RESTARTS, 1):
        checker = _solver(timeout_ms, max(1, effort // share), seed)
        checker.add(*held)
        outcome = _check_part(checker, step_name, clause, holds, known, where, once=True)
        seconds += outcome.seconds
        if not outcome.undecided:
            break
    return replace(outcome, seconds=seconds)


SPLIT = ("remembered JOIN", "remembered answer", "copies the node wrote")
"""Clauses checked conjunct by conjunct as ``P`` of a frame sent is: ``P`` of a frame the
supervisor may send again, and the node's copies as older images (``p_image``)."""


def _conjuncts(holds: Term) -> list[Term]:
    """``c => a1 & ... & an`` as ``c => a1``, ..., ``c => an``, and so each ``ai`` in turn;
    ``If(c, a, b)`` as ``c => a`` and ``not c => b`` (any other form: itself)."""
    if z3.is_and(holds):
        return [part for a in holds.children() for part in _conjuncts(a)]
    if z3.is_app_of(holds, z3.Z3_OP_IMPLIES):
        cond, body = holds.arg(0), holds.arg(1)
        return [z3.Implies(cond, part) for part in _conjuncts(body)]
    if z3.is_app_of(holds, z3.Z3_OP_ITE):  # If(c, a, b): c => a and not c => b
        cond, yes, no = holds.arg(0), holds.arg(1), holds.arg(2)
        both = (z3.Implies(cond, yes), z3.Implies(z3.Not(cond), no))
        return [part for half in both for part in _conjuncts(half)]
    return [holds]


def _check_part(
    solver: z3.Solver,
    step_name: str,
    clause: str,
    holds: Term,
    known: list[Term],
    where: tuple[World, st.Step, Msg | None],
    once: bool = False,
) -> Outcome:
    """``holds`` after the step, given the facts ``known`` (the instances of ``H``'s monotony
    and of ``Int2BV``, the message in flight's ``P``). ``once``: ``solver`` is new and checked
    once, never pushed, and left so (z3 then takes the whole problem at once)."""
    before, step, delivered = where
    started = time.perf_counter()
    if not once:
        solver.push()
    solver.add(*known)
    solver.add(z3.Not(holds))
    result = solver.check()
    seconds = time.perf_counter() - started
    if result == z3.unsat:
        outcome = Outcome(step_name, clause, True, seconds)
    elif result == z3.sat:
        text = counterexample(solver.model(), before, step, delivered)
        outcome = Outcome(step_name, clause, False, seconds, text)
    else:
        text = f"  z3: {solver.reason_unknown()}"
        outcome = Outcome(step_name, clause, False, seconds, text, undecided=True)
    if not once:
        solver.pop()
    return outcome


def check_initial(proof: Proof = HARDENED_PROOF) -> Iterator[Outcome]:
    """The invariant holds for two new nodes (H starts at 0: nothing delivered before; the
    first epoch begins at transaction 0 with Gs 0)."""
    w = initial_world()
    zero = z3.IntVal(0)
    facts = [H(zero, inv.one(w.tx)) == 0, BASE_TX(zero) == 0, BASE_GS(zero) == 0]
    for name, clause in proof.state:
        yield _prove("initial state", name, facts, clause(w))


def check_conclusion(rules: Rules = HARDENED) -> Iterator[Outcome]:
    """The invariant gives the ledger: the session's books hold at least what the node holds
    and used (dissipation >= 0; under the witnessed rules what counts for the node)."""
    w = any_world("w", rules.witnessed)
    hyps = [proof_of(rules).invariant(w), proof_of(rules).bounded(w)]
    if not rules.witnessed:
        held = w.c.usable + w.spent
        yield _prove("invariant", "usable >= 0", hyps, w.c.usable >= 0)
        yield _prove("invariant", "dissipation >= 0", hyps, drawn(w) - held >= 0)
        return
    from canergy.prove.witnessed import in_start
    from canergy.prove.witnessed_proof import counted, view

    held = counted(w) + w.spent
    outside, waits = z3.Not(in_start(w.s)), in_start(w.s)
    yield _prove("invariant", "usable >= 0", hyps, counted(w) >= 0)
    yield _prove("invariant", "dissipation >= 0", [*hyps, outside], drawn(w) - held >= 0)
    # a start from an older image: the session's books are behind until its counts; the
    # supervisor grants nothing to any node meanwhile (both cores refuse a begin while any
    # node is unconfirmed), and the books at the start cover what the node holds
    yield _prove(
        "invariant",
        "dissipation >= 0 (a start's books)",
        [*hyps, waits],
        drawn(view(w)) - held >= 0,
    )


def _prove(step: str, clause: str, hyps: list[Term], goal: Term) -> Outcome:
    solver = z3.Solver()
    solver.add(*hyps, *monotone([*hyps, goal]), z3.Not(goal))
    started = time.perf_counter()
    result = solver.check()
    seconds = time.perf_counter() - started
    if result == z3.unsat:
        return Outcome(step, clause, True, seconds)
    text = f"  {solver.model()}" if result == z3.sat else f"  z3: {solver.reason_unknown()}"
    return Outcome(step, clause, False, seconds, text)


def check_all(
    rules: Rules = HARDENED,
    timeout_ms: int | None = None,
    steps: Iterable[str] = (),
    effort: int = EFFORT,
) -> Iterator[Outcome]:
    """Every obligation, in order: the initial state, each step, the conclusion; or, given
    ``steps`` (names of ``cases``), only those steps' obligations (limits: ``check_step``)."""
    only = set(steps)
    unknown = only - {case.name for case in cases(rules)}
    if unknown:
        raise ValueError(f"no step named {sorted(unknown)[0]!r} in the {rules.name} rules")
    if not only:
        yield from check_initial(proof_of(rules))
    for case in cases(rules):
        if not only or case.name in only:
            yield from check_step(case, timeout_ms, rules, effort=effort)
    if not only:
        yield from check_conclusion(rules)
