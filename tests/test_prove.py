"""``canergy prove``: the hardened rules prove, every unsound rule set and a changed cell fail
with a counterexample, and the bounded checker finds a real trace for each unsound set."""

from __future__ import annotations

import shlex
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.cli import main
from canergy.core import common, paper
from canergy.core.inputs import POWER_LOSS, BooksLost
from canergy.core.state import ClientState, Decision, Phase, Session
from canergy.core.timing import Timing
from canergy.messages import Return

z3 = pytest.importorskip("z3")  # the prove extra: in dev, so CI runs this
from support.prove_run import prove  # noqa: E402
from support.sym_states import sym_client, sym_session  # noqa: E402

from canergy.prove import (  # noqa: E402
    CONFIRMED_BY,
    RULE_NAMES,
    SOUND,
    TRACE_IN_TESTS,
    rules,
)
from canergy.prove import invariant as inv  # noqa: E402
from canergy.prove import symbolic as sym  # noqa: E402
from canergy.prove.obligations import cases, check_step  # noqa: E402
from canergy.prove.steps import MOVES  # noqa: E402

T = Timing()


def test_the_hardened_rules_prove_every_obligation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, results = prove(tmp_path)
    assert code == 0, capsys.readouterr().out
    assert all(r["proved"] for r in results)
    steps = {c.name for c in cases()}
    by_step: dict[str, set[str]] = {}
    for r in results:
        by_step.setdefault(r["step"], set()).add(r["clause"])
    assert steps <= set(by_step)  # every cell of both tables is a step
    for step in steps:  # every clause, every message in flight, the budget, the step possible
        clauses = by_step[step]
        assert {name for name, _ in inv.STATE} <= clauses
        assert {f"P({k.name}) in flight" for k in inv.MESSAGE} <= clauses
        assert {"budget moved = books moved", "can happen (changes the world or sends)"} <= clauses
        assert {f"can move {e}" for e in MOVES.get(step, ())} <= clauses
    assert {"usable >= 0", "dissipation >= 0"} <= by_step["invariant"]
    assert "proved in" in capsys.readouterr().out


FAILS_AT = {
    "paper": "supervisor receives RETURN",
    "trusting-nv": "client: books lost (JOIN)",
    "early-grant": "client: spend",
    "split-save": "client: power loss",
    "old-image": "client: restored from an older image",
}
"""The step where each unsound set's proof fails first (measured by whole runs: 1-60 s each)."""


@pytest.mark.parametrize("name", [n for n in RULE_NAMES if n not in SOUND])
def test_each_unsound_rule_set_fails_with_a_counterexample(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, results = prove(tmp_path, "--rules", name, "--step", FAILS_AT[name])
    out, err = capsys.readouterr()
    assert code == 1
    assert not results[-1]["proved"] and all(r["proved"] for r in results[:-1])  # stops there
    assert "a counterexample to induction" in out and "  before: client:" in out
    for command in CONFIRMED_BY[name] or (TRACE_IN_TESTS,):
        assert f"the bounded checker finds a real trace: {command}" in err


@pytest.mark.parametrize(
    "command", sorted({c for commands in CONFIRMED_BY.values() for c in commands}), ids=str
)
def test_the_bounded_checker_finds_a_real_trace_for_each(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The teeth are real hazards: each is a trace the bounded checker finds (the blank-record
    rule's is tests/test_check.py's TRUSTING test)."""
    argv = shlex.split(command)
    assert argv[:2] == ["canergy", "check"]
    assert main([*argv[1:], "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "VIOLATION" in out or "violations: 1" in out, out


def _first_failure(step: str, rule_set: rules.Rules = rules.HARDENED) -> Any:
    (case,) = [c for c in cases(rule_set) if c.name == step]
    return next((o for o in check_step(case, rules=rule_set) if not o.proved), None)


def _failed_clauses(step: str, rule_set: rules.Rules) -> set[str]:
    (case,) = [c for c in cases(rule_set) if c.name == step]
    return {o.clause for o in check_step(case, rules=rule_set) if not o.proved}


def test_a_client_that_commits_a_duplicate_again_fails_the_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Hazard (a) of the paper: a duplicated COMMIT of the last transaction credits again."""
    original = sym.on_command

    def recommits(c: sym.Client, commit: bool, tx16: Any, amount_mj: Any) -> Any:
        state, sent = original(c, commit, tx16, amount_mj)
        amount = amount_mj * 1000
        again = replace(c, usable=c.usable + amount, credited=c.credited + amount)
        duplicate = z3.And(c.phase != sym.JOINING, sym.unwrap(tx16, c.last_tx, 16) == c.last_tx)
        return (sym.pick(duplicate, again, state), sent) if commit else (state, sent)

    assert _first_failure("client receives COMMIT") is None
    monkeypatch.setattr(sym, "on_command", recommits)
    failure = _first_failure("client receives COMMIT")
    assert failure is not None and "counterexample to induction" in failure.counterexample


def test_a_supervisor_that_credits_a_return_twice_fails_the_proof() -> None:
    original = sym.credit_return

    def credits_again(s: sym.Session, seq16: Any, amount_mj: Any) -> Any:
        """The window off by one: the last credited number is credited again."""
        return original(replace(s, returns_credited=s.returns_credited - 1), seq16, amount_mj)

    assert _first_failure("supervisor receives RETURN") is None
    mutated = rules.Rules("mutated", credit_return=credits_again)
    assert "returned <= given" in _failed_clauses("supervisor receives RETURN", mutated)


def test_a_write_off_that_credits_the_budget_back_fails_the_proof(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Giving up on a transaction must count it as delivered (the client may have committed
    it); crediting Ts back to Us instead creates energy."""
    original = sym.response_timeout

    def credits_back(s: sym.Session, gives_up: Any) -> Any:
        step = original(s, gives_up)
        refund = z3.And(gives_up, z3.Or(s.phase == sym.WAIT_ACK, s.phase == sym.WAIT_CONFIRM))
        delivered = z3.If(refund, s.delivered, step.session.delivered)
        credit = z3.If(refund, s.reserved, step.credit)
        return sym.SessionStep(replace(step.session, delivered=delivered), step.sent, credit)

    step = "supervisor: response timer (re-send or write off)"
    assert _first_failure(step) is None
    monkeypatch.setattr(sym, "response_timeout", credits_back)
    assert _first_failure(step) is not None


# -- the unsound cells are the Python cells they are named after --------------------------------


def _value(term: Any) -> int:
    return int(z3.simplify(term).as_long())


@settings(max_examples=200)
@given(
    st.integers(0, 1 << 20),
    st.integers(0, 0xFFFF),
    st.integers(1, 0xFFFF),
    st.integers(0, 10**9),
)
def test_credit_any_return_is_the_papers(rc: int, seq: int, amount: int, returned: int) -> None:
    s = Session(1, returns_credited=rc, returned=returned)
    py = paper.SUPERVISOR.step(T, s, Return(1, seq, amount), 0)
    step = rules.credit_any_return(sym_session(s), z3.BitVecVal(seq, 16), z3.IntVal(amount))
    assert _value(step.session.returns_credited) == py.session.returns_credited
    assert _value(step.session.returned) == py.session.returned
    assert _value(step.credit) == py.credit
    assert not z3.is_true(z3.simplify(step.sent.present))


@settings(max_examples=100)
@given(
    st.sampled_from([Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM]),
    st.integers(0, 1 << 20),
    st.integers(1, 0xFFFF),
    st.integers(0, 10**9),
)
def test_reset_session_is_the_papers(phase: Phase, tx: int, amount: int, delivered: int) -> None:
    reserved = 0 if phase is Phase.IDLE else amount * 1000
    decision = Decision.COMMIT if phase is Phase.WAIT_CONFIRM else Decision.NONE
    s = Session(1, phase, tx, reserved, delivered, decision)
    py = paper.SUPERVISOR.step(T, s, POWER_LOSS, 0)
    step = rules.reset_session(sym_session(s))
    for name in ("phase", "tx", "reserved", "delivered", "decision"):
        assert _value(getattr(step.session, name)) == int(getattr(py.session, name))


@given(st.integers(0, 10**9), st.integers(0, 1 << 20), st.integers(0, 0xFFFF))
def test_start_blank_is_the_shared_cell(usable: int, last_tx: int, nonce: int) -> None:
    c = ClientState(1, usable=usable, credited=usable, last_tx=last_tx)
    py = common.start_blank(T, c, BooksLost(nonce), 0).client
    blank, sent = rules.start_blank(sym_client(c), z3.BitVecVal(nonce, 16))
    for name in ("usable", "credited", "last_tx", "phase", "nonce", "return_seq"):
        assert _value(getattr(blank, name)) == int(getattr(py, name))
    assert not z3.is_true(z3.simplify(blank.credited_unknown)) and not py.credited_unknown
    assert not z3.is_true(z3.simplify(sent.present))


def test_energy_the_actuator_used_cannot_come_back() -> None:
    """A reset that puts what was spent back into the usable budget (books 'restored' from
    the actuator's counter) fails the proof: spent energy is gone, only a gateway takes back
    what it passed below, in its own step."""

    def restores_spent(c: sym.Client) -> Any:
        state, sent = sym.client_power_loss(c)
        return replace(state, usable=c.usable + c.spent, spent=z3.IntVal(0)), sent

    mutated = rules.Rules("mutated", client_power_loss=restores_spent)
    assert "passivity" in _failed_clauses("client: power loss", mutated)


def test_a_restored_image_creates_energy_under_the_hardened_rules_by_what_was_debited_since(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Assumption 2 dropped: the restore step fails the hardened rules on the node's books, and
    it does so because of a debit since the image: an image that differs only in credits (all
    of them counted by Rc) keeps the ledger's clauses. (It still fails those on transactions:
    an image older in its ltx may take again what it resolved, which is why the witnessed
    confirmation settles the node up to the supervisor's last closed transaction.)"""
    step = "client: restored from an older image"
    assert step not in {c.name for c in cases()}  # the hardened theorem keeps assumption 2
    failed = _failed_clauses(step, rules.RULES["old-image"])
    assert {"received <= Rc", "passivity"} <= failed
    original = inv.p_image

    def nothing_debited_since(r: sym.Client, w: Any) -> Any:
        return z3.And(original(r, w), w.c.usable == r.usable + w.c.credited - r.credited)

    monkeypatch.setattr(inv, "p_image", nothing_debited_since)
    ledger = {"energy identity", "received <= Rc", "passivity", "budget moved = books moved"}
    assert not ledger & _failed_clauses(step, rules.RULES["old-image"])


def test_a_restored_supervisor_image_creates_energy_under_the_hardened_rules(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The supervisor's side of assumption 2: an older state file counts in Us what the node
    received since (the +4 J of issue 40). It fails passivity even for an image with no
    transaction open, where whether the node committed one plays no part."""
    step = "supervisor: restored from an older image"
    assert step not in {c.name for c in cases()}
    assert "passivity" in _failed_clauses(step, rules.RULES["old-image"])
    original = inv.p_session_image

    def idle(r: sym.Session, w: Any) -> Any:
        return z3.And(original(r, w), r.phase == sym.S_IDLE)

    monkeypatch.setattr(inv, "p_session_image", idle)
    assert "passivity" in _failed_clauses(step, rules.RULES["old-image"])


def test_a_report_that_cannot_be_written_fails_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["prove", "--json", str(tmp_path / "no" / "such" / "dir.json")]) == 2
    out, err = capsys.readouterr()
    assert err.startswith("canergy prove: error: ") and "proved" not in out


def _with_branches(step_name: str, branches: Any) -> Any:
    """A hardened step's case with the named ``branches`` (conditions on the world before)."""
    from canergy.prove.obligations import StepCase

    (case,) = [c for c in cases() if c.name == step_name]

    def build(w: Any) -> Any:
        step, hyps, delivered = case.build(w)
        return replace(step, branches=branches(w)), hyps, delivered

    return StepCase(case.name, build)


def test_a_step_proved_branch_by_branch_needs_branches_that_cover_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A step that names branches proves each goal in each branch in turn once z3 does not
    decide it whole (here at once: one step of z3's), each in a solver of its own, and "its
    branches cover it" is an obligation: the phases of the session cover the supervisor's ACK;
    one phase alone does not."""
    from canergy.prove import obligations

    monkeypatch.setattr(obligations, "WHOLE_FIRST", 1)
    checked: list[str] = []
    real = obligations._check

    def spy(solver: Any, step_name: str, clause: str, *rest: Any, **kw: Any) -> Any:
        checked.append(clause + (" alone" if kw.get("alone") else ""))
        return real(solver, step_name, clause, *rest, **kw)

    monkeypatch.setattr(obligations, "_check", spy)
    step = "supervisor receives ACK"
    idle = lambda w: w.s.phase == sym.S_IDLE  # noqa: E731
    cover = lambda w: (("idle", idle(w)), ("not idle", z3.Not(idle(w))))  # noqa: E731
    outcomes = list(check_step(_with_branches(step, cover)))
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes if not o.proved]
    assert not failed, failed[0]
    assert "its branches cover it" in {o.clause for o in outcomes}
    # some goal z3 did not decide whole in one step was checked again in each of the two
    # branches, each in a solver of its own
    assert max(checked.count(c) for c in set(checked) if c.endswith(" alone")) == 2
    alone = lambda w: (("idle", idle(w)),)  # noqa: E731
    outcomes = list(check_step(_with_branches(step, alone)))
    assert {o.clause for o in outcomes if not o.proved} == {"its branches cover it"}


def _attempts(monkeypatch: pytest.MonkeyPatch, undecided: Callable[[int], bool]) -> list[Any]:
    """The supervisor's ACK proved branch by branch, each check alone made undecided for the
    seeds ``undecided`` picks: its outcomes and the limits of each solver made alone."""
    from canergy.prove import obligations

    monkeypatch.setattr(obligations, "WHOLE_FIRST", 1)
    made: list[tuple[int | None, int, int | None]] = []
    real_solver, real_part = obligations._solver, obligations._check_part

    def solver(timeout_ms: int | None, effort: int, seed: int | None = None) -> Any:
        made.append((timeout_ms, effort, seed))
        return real_solver(timeout_ms, effort, seed)

    def part(checker: Any, step_name: str, clause: str, *rest: Any, once: bool = False) -> Any:
        seed = made[-1][2]
        if once and seed is not None and undecided(seed):
            return obligations.Outcome(step_name, clause, False, 0.0, "  z3: cut", undecided=True)
        return real_part(checker, step_name, clause, *rest, once=once)

    monkeypatch.setattr(obligations, "_solver", solver)
    monkeypatch.setattr(obligations, "_check_part", part)
    idle = lambda w: w.s.phase == sym.S_IDLE  # noqa: E731
    cover = lambda w: (("idle", idle(w)), ("not idle", z3.Not(idle(w))))  # noqa: E731
    outcomes = list(check_step(_with_branches("supervisor receives ACK", cover)))
    return [outcomes, [m for m in made if m[2] is not None]]


def test_a_check_z3_does_not_decide_alone_is_begun_again_with_other_seeds(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A check made in a solver of its own that z3 does not decide is begun again with the next
    seed and a larger share of the effort (an eighth, an eighth, a quarter, a half: at most the
    effort in all), and decided by the first attempt that decides it: undecided with seed 1
    everywhere, every goal is still proved, each with seed 2; undecided with every seed, the
    goal is undecided after four attempts, never refuted."""
    from canergy.prove import EFFORT

    outcomes, made = _attempts(monkeypatch, lambda seed: seed == 1)
    failed = [f"{o.clause}\n{o.counterexample}" for o in outcomes if not o.proved]
    assert not failed, failed[0]
    assert made and {m[2] for m in made} == {1, 2}
    assert made[:2] == [(None, EFFORT // 8, 1), (None, EFFORT // 8, 2)]
    outcomes, made = _attempts(monkeypatch, lambda seed: True)
    stuck = [o for o in outcomes if not o.proved]
    assert stuck and all(o.undecided for o in stuck)
    assert [m[1:] for m in made[:5]] == [
        (EFFORT // 8, 1),
        (EFFORT // 8, 2),
        (EFFORT // 4, 3),
        (EFFORT // 2, 4),
        (EFFORT // 8, 1),
    ]
    assert sum(m[1] for m in made[:4]) <= EFFORT


def test_a_check_cut_short_is_undecided_never_refuted() -> None:
    """Every kind of check of a step stopped by ``effort`` (one of z3's steps here) is
    undecided, with z3's reason, and none reads as refuted: not whether the step can happen,
    not what it can move, not its lemmas or goals (CI once saw a cut-short 'can move' reported
    as a failure of the rules)."""
    (case,) = [c for c in cases() if c.name == "client receives INTENTION"]
    outcomes = list(check_step(case, effort=1))
    assert [o.clause for o in outcomes[:3]] == [
        "can happen (changes the world or sends)",
        "can move Uc",
        "can move received",
    ]
    assert all(o.undecided and "z3: " in o.counterexample for o in outcomes[:3])
    assert all(o.proved != o.undecided for o in outcomes), [
        o.clause for o in outcomes if o.proved == o.undecided
    ]


def test_step_checks_only_the_steps_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--step NAME`` checks that step's obligations alone (no initial state, no conclusion);
    a name the rules have no step for is refused with the list of their steps."""
    step = "supervisor receives ACK"
    code, results = prove(tmp_path, "--step", step)
    assert code == 0 and results and {r["step"] for r in results} == {step}
    assert "obligations of 1 step(s) proved" in capsys.readouterr().out
    assert main(["prove", "--step", "client: spend (DRAW)"]) == 2  # a witnessed step's name
    err = capsys.readouterr().err
    assert "no step 'client: spend (DRAW)' in the hardened rules" in err
    assert f"  {step}\n" in err
