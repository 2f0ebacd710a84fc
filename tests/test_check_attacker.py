"""The model checker's attacker: a keyless forger generates energy, a replayer does not."""

from __future__ import annotations

import json

import pytest

from canergy.check import Bounds, check, replay
from canergy.check.attacker import forgeable
from canergy.check.explore import step_from_json
from canergy.check.model import Model, Step, StepKind, initial_world
from canergy.cli import main
from canergy.core.variants import VARIANTS
from canergy.frozen import evolve
from canergy.messages import Admit, Commit, Intention, Return, StatusRequest

FORGER = Bounds(clients=1, transactions=2, forgeries=1)
REPLAYER = Bounds(
    clients=1, transactions=2, losses=0, duplicates=0, power_losses=1, in_flight=2, retries=0
)
REPLAYER = evolve(REPLAYER, replays=1)
K = StepKind


@pytest.mark.parametrize("variant", ["hardened", "paper"])
def test_the_forger_generates_energy_and_the_trace_replays(variant: str) -> None:
    result = check(variant, FORGER, stop_at_first=True)
    assert result.counterexample is not None
    steps = [step for step, _ in result.counterexample]
    assert steps[-1].kind is K.FORGE
    data = result.as_json()["counterexample"]
    worlds = replay(Model(VARIANTS[variant], FORGER), [step_from_json(s["step"]) for s in data])
    assert worlds[-1].ledger().dissipated < 0
    assert worlds[-1].ledger().as_json() == data[-1]["ledger"]


@pytest.mark.parametrize(
    "steps",
    [
        [Step(K.FORGE, message=Commit(1, 1, 1))],  # a COMMIT for the next tx, no INTENTION
        [Step(K.FORGE, message=Intention(1, 1, 1, 0)), Step(K.COMMAND_TIMER, 1)],  # timeout-commit
        [Step(K.FORGE, message=Return(1, 1, 1))],  # a RETURN the client never sent
    ],
    ids=["commit", "intention", "return"],
)
def test_the_known_forgeries_generate_energy_on_the_hardened_rules(steps: list[Step]) -> None:
    worlds = replay(Model(VARIANTS["hardened"], FORGER), steps)
    assert worlds[-1].ledger().dissipated == -1000  # one unit generated
    assert all(w.ledger().dissipated >= 0 for w in worlds[:-1])


def test_the_forger_builds_only_what_the_variant_handles_and_within_its_budget() -> None:
    w = initial_world(FORGER)
    hardened = set(forgeable(VARIANTS["hardened"], w.sup.sessions, w.clients, 1))
    paper = set(forgeable(VARIANTS["paper"], w.sup.sessions, w.clients, 1))
    assert StatusRequest(1, 1) in paper - hardened
    assert not any(isinstance(m, Admit) for m in hardened)  # the node is not joining
    with pytest.raises(ValueError, match="not applicable"):  # a second forgery is over budget
        replay(Model(VARIANTS["hardened"], FORGER), [Step(K.FORGE, message=Commit(1, 1, 1))] * 2)


def test_the_replayer_sends_only_frames_seen_on_the_bus() -> None:
    model = Model(VARIANTS["hardened"], REPLAYER)
    with pytest.raises(ValueError, match="not applicable"):
        replay(model, [Step(K.REPLAY, message=Intention(1, 1, 1, 0))])
    worlds = replay(
        model, [Step(K.BEGIN, 1, units=1), Step(K.REPLAY, message=Intention(1, 1, 1, 0))]
    )
    assert worlds[-1].replayed == 1 and Intention(1, 1, 1, 0) in worlds[-1].seen


def test_the_replayer_finds_the_paper_hazard_without_duplicates() -> None:
    """Hazard (c), a RETURN credited twice, with a replay instead of a channel duplicate."""
    bounds = Bounds(losses=0, duplicates=0, power_losses=0, timeouts=0, spending=False, replays=1)
    result = check("paper", bounds, stop_at_first=True)
    assert result.counterexample is not None
    assert result.counterexample[-1][0].kind is K.REPLAY


def test_the_replayer_generates_nothing_on_the_hardened_rules() -> None:
    result = check("hardened", REPLAYER)
    without = check("hardened", evolve(REPLAYER, replays=0))
    assert result.complete and result.violations == 0
    assert result.states > without.states  # the replays were explored


def test_cli_attacker_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--transactions", "1", "--forgeries", "1", "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["bounds"]["forgeries"] == 1 and report["bounds"]["replays"] == 0
    assert report["counterexample"][-1]["step"]["kind"] == "forge"
    argv = ["check", "--transactions", "1", "--power-losses", "0", "--replays", "2"]
    assert main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["bounds"]["replays"] == 2 and report["violations"] == 0
    assert main(["check", "--variant", "paper", "--forgeries", "1", "--replays", "1"]) == 1
    assert "forgeries 1, replays 1" in capsys.readouterr().out


def test_the_reductions_keep_the_attackers_results() -> None:
    """Symmetry and subsumption (seen frames count as a budget) against the plain search."""
    paper = Bounds(clients=2, losses=0, duplicates=0, power_losses=0, timeouts=0, replays=1)
    paper = evolve(paper, spending=False)
    lengths = set()
    for reduced in (True, False):
        result = check("paper", paper, stop_at_first=True, symmetry=reduced, subsumption=reduced)
        assert result.counterexample is not None
        lengths.add(len(result.counterexample))
    assert lengths == {8}  # hazard (c): the late replay of a RETURN is credited again
    hardened = evolve(REPLAYER, clients=2, transactions=1)
    for reduced in (True, False):
        result = check("hardened", hardened, symmetry=reduced, subsumption=reduced)
        assert result.violations == 0
