"""``canergy prove --rules witnessed``: the witnessed rules with both restore steps, the proof
as far as it goes (each step's obligations, the lemmas of the supervisor's DEBIT, and the
invariant's clauses each shown needed by a changed cell or clause that fails). Apart from
tests/test_prove.py so that the two halves run in parallel."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from canergy.messages import COUNTER_BOUND

z3 = pytest.importorskip("z3")  # the prove extra: in dev, so CI runs this
from support.prove_run import prove  # noqa: E402

from canergy.prove import CONFIRMED_BY, SOUND, rules  # noqa: E402
from canergy.prove import invariant as inv  # noqa: E402
from canergy.prove import symbolic as sym  # noqa: E402
from canergy.prove.obligations import cases, check_step  # noqa: E402

WITNESSED = rules.RULES["witnessed"]
NODE_START_STEPS = (
    "client: restored from an older image",
    "client: power loss (RESUME)",
    "client: spend (DRAW)",
    "client receives RETURN_ACK",
    "client receives ADMIT",
)


def _witnessed_outcomes(step: str) -> list[Any]:
    (case,) = [c for c in cases(WITNESSED) if c.name == step]
    return list(check_step(case, rules=WITNESSED))


def _assert_every_clause_kept(step: str, among: set[str]) -> None:
    """``step`` proves every obligation, ``among`` them, and can move what its rule moves (no
    vacuous proof)."""
    from canergy.prove.witnessed_proof import MOVES as W_MOVES

    outcomes = _witnessed_outcomes(step)
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes if not o.proved]
    assert not failed, failed[0]
    clauses = {o.clause for o in outcomes}
    assert {f"can move {e}" for e in W_MOVES.get(step, ())} | among <= clauses


@pytest.mark.parametrize("step", NODE_START_STEPS)
def test_the_witnessed_node_starts_draws_and_releases_keeping_the_invariant(step: str) -> None:
    """Under the witnessed rules a node's start, from its own record or from any older image,
    moves nothing by itself (the invariant speaks of the record at the start until the
    supervisor confirms it), and a draw reaches the actuator only through its RETURN_ACK: these
    steps keep every clause, and each can move what its rule moves (no vacuous proof)."""
    _assert_every_clause_kept(
        step, {"passivity", "energy identity", "can happen (changes the world or sends)"}
    )


SUPERVISOR_START_STEPS = (
    "supervisor: restored from an older image",
    "supervisor: power loss (SYNC)",
    "supervisor re-syncs a node",
)


@pytest.mark.parametrize("step", SUPERVISOR_START_STEPS)
def test_the_witnessed_supervisor_starts_keeping_the_invariant(step: str) -> None:
    """Under the witnessed rules a supervisor's start, from its own record or from any older
    image of it, and a re-sync of the node (a start of its session alone, from IDLE) keep every
    clause: while the start waits for the node's books and counts the invariant speaks of the
    session as it stood when the start began (``World.spre``), and the session grants nothing.
    Each step can move what its rule moves (no vacuous proof)."""
    _assert_every_clause_kept(step, {"passivity", "Gs = H", "P(INTENTION) in flight"})


def test_a_supervisor_restore_without_the_session_at_its_start_fails_the_witnessed_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The ghost carries the supervisor's restore: an invariant that speaks of the record the
    supervisor started from (an older image: tx, C and Gs behind the node's books and the
    frames in flight) fails the step, passivity and ``Gs = H`` among the clauses."""
    from canergy.prove import witnessed_proof as wp

    monkeypatch.setattr(wp, "spre", lambda w: w.s)
    failed = {
        o.clause
        for o in _witnessed_outcomes("supervisor: restored from an older image")
        if not o.proved
    }
    assert {"passivity", "Gs = H", "numbering"} <= failed


def test_a_node_that_releases_a_draw_while_its_start_waits_fails_the_witnessed_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The actuator gets a draw only once the node's books are confirmed: a node that takes a
    RETURN_ACK for its pending draw while RESUMING (its record may be an older image) fails."""
    from canergy.prove import witnessed as wit
    from canergy.prove.witnessed_proof import starting

    original = wit.on_debit_ack

    def releases_early(c: sym.Client, seq16: Any) -> Any:
        state, frames = original(c, seq16)
        early = z3.And(starting(c), c.pending_draw)
        released = replace(
            c, spent=c.spent + c.return_pending, return_pending=z3.IntVal(0),
            pending_draw=z3.BoolVal(False),
        )  # fmt: skip
        return sym.pick(early, released, state), frames

    step = "client receives RETURN_ACK"
    monkeypatch.setattr(wit, "on_debit_ack", releases_early)
    failed = {o.clause for o in _witnessed_outcomes(step) if not o.proved}
    assert "passivity" in failed


def test_a_node_that_keeps_its_books_when_found_behind_fails_the_witnessed_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The confirmation of a start: Q = q + 1 keeps the books, a larger Q finds the record
    behind (it lacks a debit the supervisor holds, which the actuator may have used). A node
    that keeps its books on any Q above its q fails the confirmation step."""
    from canergy.prove import witnessed as wit

    original = wit.on_confirm

    def keeps_behind(c: sym.Client, tx16: Any, seq16: Any) -> Any:
        q = sym.unwrap(seq16, c.return_seq, 16)
        ahead = z3.And(q - c.return_seq > 1, z3.Not(z3.UGE(q, sym.counter(COUNTER_BOUND))))
        one_past = replace(c, return_seq=q - 1)
        return wit._choose(ahead, original(one_past, tx16, seq16), original(c, tx16, seq16))

    step = "client receives ADMIT"
    monkeypatch.setattr(wit, "on_confirm", keeps_behind)
    failed = {o.clause for o in _witnessed_outcomes(step) if not o.proved}
    assert {"passivity", "received <= Rc"} & failed, failed


def test_a_start_that_hands_the_pending_draw_to_the_actuator_fails_the_witnessed_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A start drops a pending draw unreleased (its debit may be the supervisor's to void); a
    node that releases it to the actuator as it starts fails."""
    from canergy.prove import witnessed as wit

    original = wit.power_loss

    def releases_at_start(c: sym.Client, nonce16: Any) -> Any:
        state, frames = original(c, nonce16)
        drawn = z3.And(state.phase == sym.RESUMING, c.pending_draw)
        released = replace(
            state, spent=c.spent + c.return_pending, return_pending=z3.IntVal(0),
            pending_draw=z3.BoolVal(False),
        )  # fmt: skip
        return sym.pick(drawn, released, state), frames

    monkeypatch.setattr(wit, "power_loss", releases_at_start)
    failed = {o.clause for o in _witnessed_outcomes("client: power loss (RESUME)") if not o.proved}
    assert "passivity" in failed


def test_the_witnessed_proof_cut_short_is_undecided_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--rules witnessed`` is a sound set (the bounded checker finds no trace): cut short by
    ``--effort``, it fails on an obligation z3 did not decide, says so, and claims neither a
    gap of the invariant nor a trace."""
    assert "witnessed" in SOUND and "witnessed" not in CONFIRMED_BY
    code, results = prove(tmp_path, "--rules", "witnessed", "--effort", "1000000")
    out, err = capsys.readouterr()
    assert code == 1 and not results[-1]["proved"] and results[-1]["undecided"]
    assert "UNDECIDED" in out and "not decided within --effort 1,000,000" in err
    assert "not inductive" not in err and "the bounded checker finds a real trace" not in err


def test_a_whole_witnessed_pass_says_the_assumption_it_took(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pass of ``--rules witnessed`` (every obligation proved: the whole run takes about 40
    minutes here, so its outcomes are given) exits 0 and says it is under assumption 2
    narrowed, not dropped; a pass of the hardened rules says no such thing."""
    from canergy.prove import obligations
    from canergy.prove.obligations import Outcome

    def every_one_proved(rules: Any, *rest: Any) -> Any:
        return iter([Outcome("initial state", rules.name, True, 0.0)])

    monkeypatch.setattr(obligations, "check_all", every_one_proved)
    for name, narrowed in (("witnessed", True), ("hardened", False)):
        code, results = prove(tmp_path, "--rules", name)
        out = capsys.readouterr().out
        assert code == 0 and results[0]["clause"] == name
        assert "obligations proved" in out and "no step creates energy" in out
        assert ("under assumption 2 narrowed, not dropped" in out) is narrowed


def test_a_node_that_trusts_its_record_at_a_start_fails_the_witnessed_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The hardened start inside the witnessed rules: a node that goes on from the record it
    started from without waiting for the supervisor's confirmation (it may be an older image,
    from before a debit the actuator used) fails the restore step."""
    from canergy.prove import witnessed as wit

    def trusts(c: sym.Client, nonce16: Any) -> Any:
        state, _ = sym.client_power_loss(c)
        return state, wit.one(sym.Sent.none())

    step = "client: restored from an older image"
    assert not {o.clause for o in _witnessed_outcomes(step) if not o.proved}
    monkeypatch.setattr(wit, "power_loss", trusts)
    assert "passivity" in {o.clause for o in _witnessed_outcomes(step) if not o.proved}


def test_a_debit_of_the_current_start_carries_its_nonce_phase_and_ltx() -> None:
    """``P`` of a RESUME or a SYNC's counts of the node's current start ties it to that start:
    its nonce, a RESUME to RESUMING and counts to SYNCING, counts to the ltx of the record that
    answers. Without them the supervisor's DEBIT had counterexamples a real run never reaches
    (a RESUME of a start answering a SYNC, counts with another ltx)."""
    from canergy.prove import witnessed as wit
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.world import Kind, any_msg, any_world

    w, m = any_world("w"), any_msg(Kind.DEBIT, "m")
    this_start = [wp.starting(w.c), m.start == wp.starts(w)]
    resume = [m.flags == wit.START]
    counts = [wit.is_counts(m.flags)]  # afresh or not
    impossible = {
        "a RESUME of a start answering a SYNC": [*resume, w.c.phase == sym.SYNCING],
        "counts of a resuming start": [*counts, w.c.phase == sym.RESUMING],
        "a RESUME under another nonce": [*resume, m.nonce != w.c.nonce],
        "counts with another ltx": [*counts, z3.Int2BV(m.amount, 16) != inv.low16(w.c.last_tx)],
    }
    for name, facts in impossible.items():
        solver = z3.Solver()
        solver.add(wp.p_debit(m, w), *this_start, *facts)
        assert solver.check() == z3.unsat, name


def test_a_begin_keeps_the_window_and_a_begin_past_it_breaks_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The window (a) is a clause: a begin keeps W at most the node's ltx and tx at most that
    ltx + B, and every other clause. A supervisor that begins past W + B (the hardened begin,
    no window) fails ``window``: the clause is what the begin's rule gives, not a tautology."""
    from canergy.prove import witnessed as wit

    step = "supervisor: begin"
    outcomes = _witnessed_outcomes(step)
    assert {"window", "witness", "window at a start"} <= {o.clause for o in outcomes}
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes if not o.proved]
    assert not failed, failed[0]
    monkeypatch.setattr(wit, "may_begin", lambda s, window=wit.WINDOW: sym.may_begin(s))
    assert "window" in {o.clause for o in _witnessed_outcomes(step) if not o.proved}


def test_late_counts_keep_the_window_on_the_transactions_begun(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Counts taken outside a start (``counts_taken``) move tx up to their ltx over numbers no
    transaction took, and W not when they find the node behind: the window bounds the highest
    transaction begun (``World.begun``), which they keep. Read on tx, as it was, the window
    fails there."""
    from canergy.prove import witnessed as wit
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.obligations import StepCase

    (case,) = [c for c in cases(WITNESSED) if c.name == "supervisor receives DEBIT"]

    def late_counts(w: Any) -> Any:
        step, hyps, d = case.build(w)
        late = z3.And(
            z3.Not(wit.in_start(w.s)),
            d.flags == wit.COUNTS,
            wit.counts_taken(w.s, d.nonce, d.amount),
        )
        return step, [*hyps, late], d

    late = StepCase(f"{case.name} (late counts)", late_counts)
    (outcome,) = [o for o in check_step(late, None, WITNESSED, ("window",)) if o.clause == "window"]
    assert outcome.proved, outcome.counterexample

    def on_tx(w: Any) -> Any:
        return z3.Implies(wp.known(w), inv.ule(wp.view(w).tx, wp.reach(w) + wp.B))

    state = tuple((n, on_tx if n == "window" else c) for n, c in wp.STATE)
    monkeypatch.setattr(wp, "STATE", state)
    outcomes = list(check_step(late, None, WITNESSED, ("window",)))
    assert "window" in {o.clause for o in outcomes if not o.proved}


def test_a_confirmation_below_the_record_at_the_start_keeps_intentions_by_what_was_taken(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A start confirmed with k below the ltx of the record at the start (settled ahead for
    SYNCs whose counts were never taken, or started from an older image) is safe because k is
    at least every transaction the node took (``World.taken``): ``P`` of an INTENTION in flight
    says "the node may still take it" against what was taken, which the confirmation keeps.
    Read against the node's ltx, as the hardened ``P`` is, the confirmation breaks it."""
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.world import Kind

    clause = "P(INTENTION) in flight"
    (case,) = [c for c in cases(WITNESSED) if c.name == "client receives ADMIT"]
    outcomes = list(check_step(case, None, WITNESSED, (clause,)))
    (outcome,) = [o for o in outcomes if o.clause == clause]
    assert outcome.proved, outcome.counterexample

    def on_ltx(m: Any, w: Any) -> Any:
        return z3.And(inv.p_intention(m, wp.view(w)), inv.ule(m.k, wp.begun(w)))

    monkeypatch.setitem(wp.MESSAGE, Kind.INTENTION, on_ltx)
    outcomes = list(check_step(case, None, WITNESSED, (clause,)))
    assert [o.clause for o in outcomes if not o.proved] == [clause]  # and only it


def test_the_supervisors_debit_proves_that_its_counters_never_go_back() -> None:
    """The supervisor's DEBIT proves first that C and tx, in the proof's numbering, never go
    back (lifts, voids, credits, a draw held, counts), and that counts ending a start leave tx
    at or above every transaction begun and above the last of a node that waits for the
    start's SYNC, then takes them as facts (its slowest obligations,
    ``client books`` and ``numbering``, went from 87 s and 101 s to 27 s and 12 s; ``P`` of an
    INTENTION in flight at counts ending a start from an image, from z3's 200 s limit to
    24 s)."""
    (case,) = [c for c in cases(WITNESSED) if c.name == "supervisor receives DEBIT"]
    lemmas = []
    for outcome in check_step(case, rules=WITNESSED):
        if outcome.clause.startswith("lemma: "):
            lemmas.append(outcome)
        elif lemmas:
            break  # the goals follow the lemmas
    assert {o.clause for o in lemmas} == {
        "lemma: counts afresh pay whole quanta",
        "lemma: counts a start takes move Gs by what they pay",
        "lemma: C does not go back",
        "lemma: tx does not go back",
        "lemma: counts that end a start leave tx at or above begun",
        "lemma: counts that end a start leave tx at or above a syncing node's last",
        "lemma: the books' fields read as their low bits",
        "lemma: the books' Rc unwrapped",
        "lemma: a repeat sends the last answer's Q",
        "lemma: the last answer confirms as it did",
    }
    assert all(o.proved for o in lemmas), [o.counterexample for o in lemmas if not o.proved]


def test_the_answer_remembered_at_counts_that_end_a_resync_found_behind_proves(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The supervisor's DEBIT, in its branch "counts that end a re-sync, found behind": the
    answer it remembers keeps its ``P`` (at 100 million of z3's steps a check it failed once in
    one worker of a parallel run after other tests, and passed alone: the default limit).
    Before the lemma that such counts leave tx at or above a syncing node's
    last, its conjunct 27 of 53 took 61 million to over 1,500 million steps by seed and by what
    the process had built before: a whole run on its own proved it, one after the hardened
    proof did not."""
    from canergy.prove import obligations

    monkeypatch.setattr(obligations, "WHOLE_FIRST", 1)  # straight to the branch
    branch = "counts that end a re-sync, found behind"
    (case,) = [c for c in cases(WITNESSED) if c.name == "supervisor receives DEBIT"]

    def build(w: Any) -> Any:
        step, hyps, delivered = case.build(w)
        only = tuple(b for b in step.branches if b[0] == branch)
        return replace(step, branches=only), hyps, delivered

    one = obligations.StepCase(case.name, build)
    clause = "remembered answer"
    outcomes = list(check_step(one, None, WITNESSED, (clause,)))
    (answer,) = [o for o in outcomes if o.clause == clause]
    assert answer.proved, answer.counterexample
    (lemma,) = [o for o in outcomes if o.clause.endswith("above a syncing node's last")]
    assert lemma.proved, lemma.counterexample


def _debit_clause(clause: str) -> Any:
    """One obligation of the supervisor's DEBIT (the step's checks stop once it is reached)."""
    (case,) = [c for c in cases(WITNESSED) if c.name == "supervisor receives DEBIT"]
    for outcome in check_step(case, None, WITNESSED, (clause,)):
        if outcome.clause == clause:
            return outcome
    raise AssertionError(f"no obligation {clause!r}")


def test_counts_ending_a_supervisor_start_keep_returned_within_given(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Counts that end a supervisor's start from an older image bring the image's ``returned``
    back into ``returned <= given``: the invariant says it is at most the session at the
    start's while the start waits (``credited_back``). Without that clause z3 finds an image
    that credited back more than the node gave."""
    from canergy.prove import witnessed_proof as wp

    outcome = _debit_clause("returned <= given")
    assert outcome.proved, outcome.counterexample
    monkeypatch.setattr(wp, "credited_back", lambda w: z3.BoolVal(True))
    assert not _debit_clause("returned <= given").proved


def test_only_the_counts_of_the_supervisors_current_start_end_it() -> None:
    """A SYNC carries the supervisor's start it was sent in (``World.sstarts``), the node's
    books and counts the start whose SYNC they answer: counts or books a start takes (its nonce)
    are of that start (assumption 5 for the supervisor's nonces), and they carry its nonce."""
    from canergy.prove import witnessed as wit
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.world import Kind, any_msg, any_world

    w, m = any_world("w"), any_msg(Kind.DEBIT, "m")
    for phase, flags in ((sym.SYNC_BOOKS, wit.COUNTS), (sym.SYNCING, wit.BOOKS)):
        ends = [w.s.phase == phase, m.nonce == w.s.sync_nonce, m.flags == flags]
        solver = z3.Solver()
        solver.add(wp.deliverable(m, w), *ends, m.sstart != wp.sstarts(w))
        assert solver.check() == z3.unsat, (phase, flags)
    solver = z3.Solver()
    solver.add(wp.p_debit(m, w), wp.current_sync(m, w), m.nonce != w.s.sync_nonce)
    assert solver.check() == z3.unsat


def test_no_record_of_the_node_holds_a_number_above_top() -> None:
    """``top`` is the highest return number any record of the node held: the invariant says
    the node's record (not joining) holds none above it, so a draw or a RESUME that moves it
    leaves counts in flight at or above it (the window's (b), docs/protocol.md)."""
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.world import any_world

    w = any_world("w")
    solver = z3.Solver()
    solver.add(wp.client_books(w), w.c.phase != sym.JOINING, inv.ult(wp.top(w), w.seq))
    assert solver.check() == z3.unsat


def test_a_node_put_back_below_top_while_a_start_behind_in_c_waits_is_the_residual() -> None:
    """Residual (d) in return numbers: while a start of the supervisor's from an image behind
    in C waits, the node is not put back to an image more than one number below the highest
    any record of it held (``far_behind_c``, a hypothesis of the node's restore): counts from
    such an image would end the start with C below numbers a RETURN in flight may carry. The
    restore without that hypothesis breaks ``window at a start``, which says so."""
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.obligations import StepCase
    from canergy.prove.world import any_image

    nonce = z3.BitVec("restore.nonce", 16)

    def tx_only(w: Any) -> Any:
        image = any_image("image")
        step = wp.restore(w, image, nonce)
        return step, [wp.p_image(image, w), z3.Not(wp.far_behind(step.after))], None

    case = StepCase("client: restored from an older image (tx only)", tx_only)
    outcomes = list(check_step(case, None, WITNESSED, ("window at a start",)))
    (window,) = [o for o in outcomes if o.clause == "window at a start"]
    assert not window.proved and "counterexample" in window.counterexample


def test_counts_ending_a_supervisor_start_begin_an_epoch_of_h(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Counts that end a supervisor's start may leave a Gs (an older image's, raised by the
    books) below the one the discarded history fixed for the numbers taken again: they begin
    an epoch of ``H`` (``World.epoch``), equal to that Gs up to one past the tx they leave, and
    ``Gs = H`` holds after them. With one ``H`` over the whole run (the epoch kept) z3 finds
    the discarded history's ``H`` above that Gs."""
    from canergy.prove import witnessed_proof as wp
    from canergy.prove.world import epoch_of

    outcome = _debit_clause("Gs = H")
    assert outcome.proved, outcome.counterexample
    monkeypatch.setattr(wp, "next_epoch", lambda w, ends: epoch_of(w))
    one_h = _debit_clause("Gs = H")
    assert not one_h.proved and "counterexample" in one_h.counterexample


def test_a_repeat_of_late_counts_sends_the_last_answer_again() -> None:
    """Late counts answered again (the same key and number, C where the last answer left it)
    send that answer's Q again to the start it answered: ``P`` of the ADMIT sent holds in that
    branch of the supervisor's DEBIT, from the remembered answer (two lemmas carry its Q and
    how it confirms)."""
    from canergy.prove import obligations

    (case,) = [c for c in cases(WITNESSED) if c.name == "supervisor receives DEBIT"]

    def build(w: Any) -> Any:
        step, hyps, delivered = case.build(w)
        branches = tuple(b for b in step.branches if b[0] == "late counts, again")
        assert len(branches) == 1
        return replace(step, branches=branches), hyps, delivered

    restricted = obligations.StepCase(case.name, build)
    outcomes = list(check_step(restricted, None, WITNESSED, ("P(ADMIT) sent",)))
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes if not o.proved]
    # the branches cover the step no longer: that one obligation fails, as it must
    assert [f.split("\n")[0] for f in failed] == ["its branches cover it"], failed
    assert {"lemma: a repeat sends the last answer's Q", "P(ADMIT) sent"} <= {
        o.clause for o in outcomes if o.proved
    }


COPY_CLAUSES = (
    "copies the node wrote",
    "copies the supervisor wrote",
    "a record fits",
    "a start from the supervisor's own record",
)


def _copy_outcomes(step: str) -> dict[str, Any]:
    """The outcomes of ``step`` for the clauses on copies only (its lemmas still proved)."""
    (case,) = [c for c in cases(WITNESSED) if c.name == step]
    return {o.clause: o for o in check_step(case, None, WITNESSED, COPY_CLAUSES)}


@pytest.mark.parametrize("step", [c.name for c in cases(WITNESSED)])
def test_every_step_keeps_the_copies_each_side_wrote_older_images_of_the_kind_restored(
    step: str,
) -> None:
    """Assumption 2 narrowed less: a copy of the node's record, or of the supervisor's state
    file, written while no start of that side waits (or while a start from its own record
    waits, as ``copy_covered`` and ``session_copy_covered`` say) and since its record last
    went back is, at every later step, an older image of the kind the restore steps take
    (``p_image``, ``p_session_image``). Every step keeps the two clauses that say so, the
    steps that write a copy among them, what a record holds fits a record, and a start of
    the supervisor's from its own record holds every counter at least where it stood (why
    such a start ends neither side's copies)."""
    outcomes = _copy_outcomes(step)
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes.values() if not o.proved]
    assert not failed, failed[0]
    assert set(COPY_CLAUSES) <= set(outcomes)


def test_copies_the_node_wrote_before_its_record_went_back_are_outside_the_theorem(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Copies of the node's record end when it goes back: kept over a new life alone, a copy
    from before a confirmation that kept an older image's books (ADMIT), or from before the
    node learned its Rc (INTENTION), is no image of the kind the restore step takes."""
    from canergy.prove import witnessed_proof as wp

    for step in ("client receives ADMIT", "client receives INTENTION"):
        assert _copy_outcomes(step)["copies the node wrote"].proved
    monkeypatch.setattr(wp, "went_back", lambda before, after: before.life != after.life)
    for step in ("client receives ADMIT", "client receives INTENTION"):
        outcome = _copy_outcomes(step)["copies the node wrote"]
        assert not outcome.proved and "counterexample" in outcome.counterexample, step


def _possible_after(step: str, waits: Any, covered: Any) -> bool:
    """Whether the invariant allows ``step`` from a world where ``waits`` holds, leaving a
    world where ``covered`` holds (the copies' clauses are not kept vacuously)."""
    from canergy.prove.obligations import proof_of

    proof = proof_of(WITNESSED)
    w, s = _step_of(step)
    solver = z3.Solver()
    solver.add(proof.invariant(w), proof.bounded(w), s.enabled, waits(w), covered(s.after))
    return bool(solver.check() == z3.sat)


def test_a_copy_of_the_node_written_while_its_own_start_waits_is_inside_the_theorem(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A copy written while a start of the node's waits holding the books it began from (its
    own after a power loss, RESUMING, or its answer to a SYNC, SYNCING), the supervisor not
    behind it, is an image of the kind the restore step takes, and such a copy can be written
    in either. Covering any start, or one with the supervisor behind the node (a restore of
    the supervisor's), fails the step: the copy may then be an older image, or ahead of the
    supervisor's books."""
    from canergy.prove import witnessed_proof as wp

    assert _copy_outcomes(wp.WRITE_COPY)[wp.COPIES].proved
    for phase in (sym.RESUMING, sym.SYNCING):
        waits = lambda w, p=phase: w.c.phase == p  # noqa: E731
        assert _possible_after(wp.WRITE_COPY, waits, lambda w: w.copied)
    covered = wp.copy_covered

    def behind_too(w: Any) -> Any:
        return z3.Or(covered(w), wp._same_books(w.c, wp.pre(w)))

    for wider in (lambda w: z3.BoolVal(True), behind_too):
        monkeypatch.setattr(wp, "copy_covered", wider)
        outcome = _copy_outcomes(wp.WRITE_COPY)[wp.COPIES]
        assert not outcome.proved and "counterexample" in outcome.counterexample


def test_a_copy_of_the_supervisor_written_while_its_own_start_waits_is_inside_the_theorem(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A nightly copy of the state file while a start from the supervisor's own record waits
    for a node that is off (its books not taken) is an image of the kind the restore step
    takes, and such a copy can be written. Covering any start, or one whose books raised Gs
    (the node's books taken), fails the step: the copy is then ahead of the session at the
    start the invariant speaks of, or an older image the start went on from."""
    from canergy.prove import witnessed_proof as wp

    assert _copy_outcomes(wp.WRITE_SESSION_COPY)[wp.SESSION_COPIES].proved
    waits = lambda w: wp.wit.in_start(w.s)  # noqa: E731
    assert _possible_after(wp.WRITE_SESSION_COPY, waits, lambda w: w.scopied)

    def books_taken_too(w: Any) -> Any:
        return z3.Or(z3.Not(waits(w)), z3.Not(wp.forked(w)))

    for wider in (lambda w: z3.BoolVal(True), books_taken_too):
        monkeypatch.setattr(wp, "session_copy_covered", wider)
        outcome = _copy_outcomes(wp.WRITE_SESSION_COPY)[wp.SESSION_COPIES]
        assert not outcome.proved and "counterexample" in outcome.counterexample


def _step_of(name: str) -> tuple[Any, Any]:
    """A world of fresh constants and ``name``'s step from it (the copies' ghosts kept)."""
    from canergy.prove.world import any_world

    (case,) = [c for c in cases(WITNESSED) if c.name == name]
    w = any_world("w")
    step, _, _ = case.build(w)
    return w, step


def _always(claim: Any) -> bool:
    solver = z3.Solver()
    solver.add(z3.Not(claim))
    return bool(solver.check() == z3.unsat)


@pytest.mark.parametrize("step", ["supervisor: power loss (SYNC)", "supervisor re-syncs a node"])
def test_a_start_of_the_supervisor_from_its_own_record_keeps_the_copies_it_wrote(
    step: str,
) -> None:
    """A nightly copy of the state file, then a reboot (or a re-sync): the start goes on from
    the supervisor's own record, so the copy is still one the restore step takes; once the
    start's counts end it (a new epoch of ``H``) it still is."""
    from canergy.prove import witnessed_proof as wp

    w, s = _step_of(step)
    idle = z3.And(w.scopied, z3.Not(wp.wit.in_start(w.s)))
    assert _always(z3.Implies(z3.And(idle, s.enabled), s.after.scopied))
    from_idle = z3.And(s.enabled, z3.Not(wp.wit.in_start(w.s)))
    assert _always(z3.Implies(from_idle, z3.Not(wp.forked(s.after))))
    w, counts = _step_of("supervisor receives DEBIT")
    own = z3.And(w.scopied, wp.wit.in_start(w.s), z3.Not(wp.forked(w)), counts.enabled)
    solver = z3.Solver()
    solver.add(own, wp.epoch_of(w) != wp.epoch_of(counts.after), counts.after.scopied)
    assert solver.check() == z3.sat


def test_a_restore_of_the_supervisor_ends_the_copies_it_wrote_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A start from an older image, from idle or in place of a start from its own record,
    ends the copies written before (a copy newer than the image is ahead of what the start
    confirms); were a restore during its own start's wait to keep them, the clause on the
    supervisor's copies would fail at that step."""
    from canergy.prove import witnessed_proof as wp

    w, s = _step_of("supervisor: restored from an older image")
    unforked = z3.Not(z3.And(wp.wit.in_start(w.s), wp.forked(w)))  # as session_copies says
    assert _always(z3.Implies(unforked, z3.Not(s.after.scopied)))
    assert _copy_outcomes("supervisor: restored from an older image")[wp.SESSION_COPIES].proved
    went_back = wp.session_went_back

    def not_when_a_restore_takes_over_a_start(before: Any, after: Any) -> Any:
        waiting = z3.And(wp.wit.in_start(before.s), wp.wit.in_start(after.s))
        takes_over = z3.And(waiting, z3.Not(wp.forked(before)), wp.forked(after))
        return z3.And(went_back(before, after), z3.Not(takes_over))

    monkeypatch.setattr(wp, "session_went_back", not_when_a_restore_takes_over_a_start)
    outcome = _copy_outcomes("supervisor: restored from an older image")[wp.SESSION_COPIES]
    assert not outcome.proved and "counterexample" in outcome.counterexample


def test_the_witnessed_invariant_holds_of_two_new_nodes() -> None:
    """The base case: every clause, the copies' among them, holds of the initial world (a
    ghost left out of ``initial_world`` fails here, not 35 minutes into ``canergy prove``)."""
    from canergy.prove.obligations import check_initial, proof_of

    outcomes = list(check_initial(proof_of(WITNESSED)))
    assert [o.clause for o in outcomes if not o.proved] == []
    assert {"copies the node wrote", "copies the supervisor wrote"} <= {o.clause for o in outcomes}


def test_counts_ending_a_start_of_the_supervisor_keep_a_nodes_copies_unless_it_was_forked() -> None:
    """A copy of the node's record, then a reboot of the supervisor: the counts that end its
    start (a new epoch of ``H``) keep the node's copies when the start went on from the
    supervisor's own record, and end them when it went on from an older image."""
    from canergy.prove import witnessed_proof as wp

    w, counts = _step_of("supervisor receives DEBIT")
    new_epoch = z3.And(counts.enabled, wp.epoch_of(w) != wp.epoch_of(counts.after))
    solver = z3.Solver()
    solver.add(new_epoch, w.copied, z3.Not(wp.forked(w)), counts.after.copied)
    assert solver.check() == z3.sat
    assert _always(
        z3.Implies(z3.And(new_epoch, wp.forked(counts.after)), z3.Not(counts.after.copied))
    )
