"""The model checker over the real core: paper hazards as shortest traces, hardened clean."""

from __future__ import annotations

import json

import pytest

from canergy.check import Bounds, check, replay
from canergy.check.explore import step_from_json
from canergy.check.model import Model, Step, StepKind
from canergy.cli import main
from canergy.core import ClientState, ClientStep, Session, SessionStep, Timing
from canergy.core import hardened as H
from canergy.core.common import start_blank
from canergy.core.inputs import BooksLost, PowerLoss, ReturnTimeout
from canergy.core.table import ANY, cell
from canergy.core.variants import VARIANTS, Variant
from canergy.frozen import evolve
from canergy.messages import (
    QUANTUM_UJ,
    Ack,
    Admit,
    Commit,
    Committed,
    Intention,
    Join,
    Return,
)

HAZARD_BOUNDS = {
    # (a) the reservation re-sent under a new id is paid twice
    "a": Bounds(losses=1, duplicates=0, power_losses=0, timeouts=2, returns=False),
    # (b) TimeoutN forgets a timeout-commit; the re-sent intention is taken as new
    "b": Bounds(losses=0, duplicates=1, power_losses=0, returns=False),
    # (c) a duplicated RETURN is credited twice
    "c": Bounds(losses=0, duplicates=1, power_losses=0, timeouts=0, spending=False),
    # (d) after a client reset a late duplicate of an old intention is accepted
    "d": Bounds(losses=0, duplicates=1, power_losses=1, timeouts=1, returns=False, spending=False),
    # (e) a reset right after a timeout-commit forgets it
    "e": Bounds(losses=0, duplicates=0, power_losses=1, timeouts=3, returns=False, spending=False),
}
SHAPES = {
    "a": [
        "begin",
        "supervisor_timer",
        "deliver",
        "deliver",
        "decide",
        "deliver",
        "deliver",
        "command_timer",
    ],
    "b": [
        "begin",
        "supervisor_timer",
        "deliver",
        "command_timer",
        "deliver",
        "command_timer",
        "deliver",
        "command_timer",
    ],
    "c": [
        "begin",
        "deliver",
        "deliver",
        "decide",
        "deliver",
        "give_back",
        "duplicate",
        "deliver",
        "deliver",
    ],
    "d": [
        "begin",
        "duplicate",
        "deliver",
        "deliver",
        "decide",
        "deliver",
        "client_power_loss",
        "deliver",
        "command_timer",
    ],
    "e": [
        "begin",
        "supervisor_timer",
        "deliver",
        "command_timer",
        "deliver",
        "client_power_loss",
        "deliver",
        "command_timer",
    ],
}


@pytest.mark.parametrize("hazard", sorted(HAZARD_BOUNDS))
def test_paper_hazard_is_a_shortest_counterexample(hazard: str) -> None:
    result = check("paper", HAZARD_BOUNDS[hazard], stop_at_first=True)
    assert result.violations > 0 and result.counterexample is not None
    assert [step.kind.value for step, _ in result.counterexample] == SHAPES[hazard]
    assert result.counterexample[-1][1].ledger().dissipated == -QUANTUM_UJ
    assert all(w.ledger().dissipated >= 0 for _, w in result.counterexample[:-1])


@pytest.mark.parametrize("hazard", sorted(HAZARD_BOUNDS))
def test_hardened_has_no_violation_within_the_same_bounds(hazard: str) -> None:
    result = check("hardened", HAZARD_BOUNDS[hazard])
    assert result.complete and result.violations == 0 and result.counterexample is None
    assert result.states > 50


def test_hardened_two_clients_sharing_the_budget_with_supervisor_resets() -> None:
    """The CI bound: two clients, every fault kind, supervisor and client power losses."""
    bounds = Bounds(
        clients=2,
        transactions=2,
        losses=1,
        duplicates=1,
        power_losses=1,
        in_flight=2,
        units=1,
        retries=0,
    )
    result = check("hardened", bounds)
    assert result.complete and result.violations == 0
    assert result.states > 10_000, result.states


def credit_every_copy(t: Timing, s: Session, msg: Return, now: int) -> SessionStep:
    """Broken on purpose: credits a RETURN again instead of only re-acknowledging it."""
    s = evolve(s, returns_credited=max(s.returns_credited, msg.seq))
    return SessionStep(s, (), msg.amount_mj * QUANTUM_UJ)


def forget_last_tx(t: Timing, c: ClientState, event: PowerLoss, now: int) -> ClientStep:
    """Broken on purpose: keeps the last resolved transaction in volatile memory."""
    return ClientStep(evolve(H.restart_client(t, c, event, now).client, last_tx=0))


def renumber_resent_return(t: Timing, c: ClientState, event: ReturnTimeout, now: int) -> ClientStep:
    """Broken on purpose: re-sends an unacknowledged return under a fresh number."""
    if not c.return_pending:
        return ClientStep(c)
    return H.resend_return(t, evolve(c, return_seq=c.return_seq + 1), event, now)


SUP, CLIENT = H.SUPERVISOR, H.CLIENT


@pytest.mark.parametrize(
    "broken",
    [
        Variant("credits-duplicates", SUP.with_cells(cell(ANY, Return, credit_every_copy)), CLIENT),
        Variant(
            "volatile-ltx", SUP, CLIENT.with_cells(cell(ANY, PowerLoss, forget_last_tx, to=H.IDLE))
        ),
        Variant(
            "renumbered-returns",
            SUP,
            CLIENT.with_cells(cell(ANY, ReturnTimeout, renumber_resent_return)),
        ),
    ],
    ids=lambda v: v.name,
)
def test_the_checker_finds_a_deliberately_broken_rule(broken: Variant) -> None:
    result = check(broken, Bounds(units=2), stop_at_first=True)
    assert result.violations >= 1 and result.counterexample is not None
    assert check(VARIANTS["hardened"], Bounds(units=2), max_states=5000).violations == 0


def test_cli_paper_counterexample_replays_through_the_core(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["check", "--variant", "paper", "--json"]) == 1  # stops at the first (shortest)
    report = json.loads(capsys.readouterr().out)
    assert {"states", "transitions", "depth", "seconds", "violations", "counterexample"} <= set(
        report
    )
    assert report["violations"] >= 1 and report["states"] > 0
    steps = [step_from_json(s["step"]) for s in report["counterexample"]]
    worlds = replay(Model(VARIANTS["paper"], Bounds()), steps)
    assert worlds[-1].ledger().dissipated < 0
    assert worlds[-1].ledger().as_json() == report["counterexample"][-1]["ledger"]


def test_cli_hardened_summary(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--transactions", "1", "--trace"]) == 0
    out = capsys.readouterr().out
    assert "violations: 0" in out and "states/s" in out and "no counterexample" in out


def test_cli_rejects_bad_bounds(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["check", "--clients", "0"])
    assert "outside" in capsys.readouterr().err


# -- NV loss and an old copy of the record ----------------------------------------------------
NV_BOUNDS = Bounds(
    nv_losses=1, power_losses=1, losses=1, duplicates=0, in_flight=2, retries=0, timeouts=3
)
TRUSTING = Variant(
    "trusting-blank-record", SUP, CLIENT.with_cells(cell(ANY, BooksLost, start_blank, to=H.IDLE))
)
"""The behaviour before issue 13: a node without a record started from zero and trusted Gs."""


def test_a_lost_record_never_creates_energy() -> None:
    result = check("hardened", NV_BOUNDS)
    assert result.complete and result.violations == 0
    without = check("hardened", evolve(NV_BOUNDS, nv_losses=0))
    assert result.states > without.states > 1_000  # the NV-loss steps were explored too


def test_the_old_behaviour_pays_a_lost_node_back_or_replays_into_it() -> None:
    result = check(TRUSTING, NV_BOUNDS, stop_at_first=True)
    assert result.counterexample is not None
    kinds = [step.kind.value for step, _ in result.counterexample]
    assert "client_nv_lost" in kinds and kinds.index("client_nv_lost") < len(kinds) - 1
    assert result.counterexample[-1][1].ledger().dissipated < 0


def test_a_replayed_intention_after_admission_moves_nothing() -> None:
    """NV lost after a transaction closed, then a late copy of its intention arrives: the
    trusting node commits it again; the hardened node is admitted above it and ignores it."""
    steps = [
        Step(StepKind.BEGIN, 1, units=1),
        Step(StepKind.DUPLICATE, message=Intention(1, 1, 1, 0)),
        Step(StepKind.DELIVER, message=Intention(1, 1, 1, 0)),
        Step(StepKind.DELIVER, message=Ack(1, 1)),
        Step(StepKind.DECIDE, 1, commit=True),
        Step(StepKind.DELIVER, message=Commit(1, 1, 1)),
        Step(StepKind.DELIVER, message=Committed(1, 1)),
        Step(StepKind.SPEND, 1),
        Step(StepKind.NV_LOST, 1, nonce=1),
    ]
    bounds = evolve(NV_BOUNDS, duplicates=1, in_flight=3)
    trusting = replay(Model(TRUSTING, bounds), [*steps, *_late_copy()])
    assert trusting[-1].ledger().dissipated < 0
    hardened = replay(
        Model(VARIANTS["hardened"], bounds),
        [
            *steps,
            Step(StepKind.DELIVER, message=Join(1, 1)),
            Step(StepKind.DELIVER, message=Admit(1, 1, 1, 0)),
            *_late_copy()[:1],
        ],
    )
    assert hardened[-1].clients[0].usable == 0 and hardened[-1].ledger().dissipated >= 0
    assert hardened[-1].flight == frozenset()  # the late copy got no ACK


def _late_copy() -> list[Step]:
    return [
        Step(StepKind.DELIVER, message=Intention(1, 1, 1, 0)),
        Step(StepKind.COMMAND_TIMER, 1),
    ]


def test_an_old_copy_of_the_record_is_caught_as_the_residual_risk() -> None:
    """No message can reveal a record rolled back to an earlier valid copy (docs/protocol.md,
    NV): the checker shows what it costs, e.g. a return given back twice."""
    bounds = Bounds(old_copies=1, power_losses=0, losses=0, duplicates=0)
    result = check("hardened", bounds, stop_at_first=True)
    assert result.counterexample is not None
    assert result.counterexample[-1][0].kind is StepKind.NV_OLD_COPY


def test_cli_takes_nv_fault_bounds(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["check", "--transactions", "1", "--nv-losses", "1", "--power-losses", "0"]
    assert main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["bounds"]["nv_losses"] == 1 and report["violations"] == 0
