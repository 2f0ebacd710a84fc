"""The compact engine stores exactly what the reference search stores, and finds the same trace.

Every figure the checker reports (states, transitions, depth, violations, subsumed worlds, the
quiescent states and their worst dissipation) and the counterexample itself must be equal on
bounds that exercise each kind of step: the paper rules (violations), forged and replayed frames,
lost records and old copies, and the reductions off. A divergence in the step order, the
canonical form, the subsumption or a rule's bookkeeping changes at least one of them.
"""

from __future__ import annotations

import json
import os
import signal
from dataclasses import replace
from typing import Any

import pytest

from canergy.check import Bounds, CheckResult, check, workers
from canergy.check.engine import Engine
from canergy.check.model import Model, StepKind, initial_world
from canergy.check.reduce import Reducer, relabel
from canergy.cli import main
from canergy.core.variants import VARIANTS

FIGURES = (
    "states",
    "transitions",
    "depth",
    "violations",
    "subsumed",
    "quiescent_states",
    "worst_quiescent_dissipation",
    "complete",
    "notes",
)
NV = Bounds(nv_losses=1, power_losses=1, losses=1, duplicates=0, in_flight=2, retries=0, timeouts=3)
SUP_COPY = Bounds(
    clients=2, supervisor_old_copies=1, transactions=1, losses=1, duplicates=0, timeouts=2
)
CASES: list[tuple[str, str, Bounds, dict[str, Any]]] = [
    ("one client", "hardened", Bounds(transactions=1), {}),
    ("the supervisor's old copy", "hardened", SUP_COPY, {}),
    ("the supervisor's old copy, witnessed", "witnessed", SUP_COPY, {"max_states": 20_000}),
    ("two units", "hardened", Bounds(transactions=1, units=2, retries=0), {}),
    ("paper, first", "paper", Bounds(), {"stop_at_first": True}),
    ("paper, all", "paper", Bounds(), {"max_states": 4000}),
    (
        "paper, 2 clients",
        "paper",
        Bounds(clients=2, duplicates=0, power_losses=0),
        {"stop_at_first": True},
    ),
    ("2 clients", "hardened", Bounds(clients=2, transactions=1), {}),
    ("2 clients CI", "hardened", Bounds(clients=2, in_flight=2, retries=0), {"max_states": 6000}),
    ("no symmetry", "hardened", Bounds(clients=2, transactions=1), {"symmetry": False}),
    ("no subsumption", "hardened", Bounds(clients=2, transactions=1), {"subsumption": False}),
    (
        "plain",
        "paper",
        Bounds(clients=2, duplicates=0, power_losses=0, timeouts=2),
        {"symmetry": False, "subsumption": False, "max_states": 3000},
    ),
    ("forger, first", "hardened", Bounds(transactions=1, forgeries=1), {"stop_at_first": True}),
    ("forger, all", "hardened", Bounds(transactions=1, forgeries=1, losses=0, power_losses=0), {}),
    ("replayer", "hardened", Bounds(transactions=1, replays=2, power_losses=0), {}),
    (
        "replayer, 2 clients",
        "paper",
        Bounds(
            clients=2, losses=0, duplicates=0, power_losses=0, timeouts=0, replays=1, spending=False
        ),
        {"stop_at_first": True},
    ),
    ("NV loss", "hardened", NV, {}),
    (
        "NV loss, 2 clients",
        "hardened",
        Bounds(clients=2, transactions=1, nv_losses=2, losses=0, in_flight=2),
        {"max_states": 5000},
    ),
    (
        "old copy, first",
        "hardened",
        Bounds(old_copies=1, power_losses=0, losses=0, duplicates=0),
        {"stop_at_first": True},
    ),
    (
        "old copy, all",
        "hardened",
        Bounds(transactions=1, old_copies=1, power_losses=0, losses=0),
        {},
    ),
    (
        "witnessed, old copy",
        "witnessed",
        Bounds(transactions=1, old_copies=1, losses=0, duplicates=0, timeouts=3),
        {"max_states": 20000},
    ),
    (
        "backups, 2 clients",
        "witnessed",
        Bounds(clients=2, transactions=1, old_copies=1, backups=True, losses=0, duplicates=0),
        {"max_states": 20000},
    ),
    (
        "the supervisor's backups",
        "hardened",
        replace(SUP_COPY, supervisor_backups=True, losses=0),
        {"max_states": 5000},
    ),
    (
        "the supervisor's backups, a node's books lost",
        "witnessed",
        Bounds(
            transactions=1,
            nv_losses=1,
            supervisor_old_copies=1,
            supervisor_backups=True,
            power_losses=0,
            losses=0,
            duplicates=0,
            retries=0,
            timeouts=2,
            in_flight=2,
        ),
        {"stop_at_first": True},
    ),
    (
        "re-syncs, 2 clients",
        "witnessed",
        Bounds(clients=2, transactions=1, duplicates=0, power_losses=0, timeouts=2, resyncs=1),
        {"max_states": 20000},
    ),
    (
        "re-syncs, the supervisor's old copy",
        "witnessed",
        replace(SUP_COPY, resyncs=2),
        {"max_states": 20000},
    ),
    ("3 clients", "hardened", Bounds(clients=3, transactions=1, losses=0, in_flight=2), {}),
    (
        "bounded timers",
        "hardened",
        Bounds(clients=2, transactions=1, timeouts=1, returns=False),
        {},
    ),
]


def _both(variant: str, bounds: Bounds, **kwargs: Any) -> tuple[CheckResult, CheckResult]:
    reference = check(variant, bounds, engine="reference", **kwargs)
    compact = check(variant, bounds, engine="compact", **kwargs)
    return reference, compact


@pytest.mark.parametrize(
    ("variant", "bounds", "kwargs"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_the_engines_agree(variant: str, bounds: Bounds, kwargs: dict[str, Any]) -> None:
    reference, compact = _both(variant, bounds, **kwargs)
    assert [getattr(compact, f) for f in FIGURES] == [getattr(reference, f) for f in FIGURES]
    assert compact.counterexample == reference.counterexample
    assert reference.states > 2


def test_the_cases_cover_violations_and_every_kind_of_step() -> None:
    """The list above is not vacuous: it finds violations and takes each kind of step."""
    kinds = set()
    violations = 0
    for _, variant, bounds, kwargs in CASES:
        model = Model(VARIANTS[variant], bounds)
        symmetry, subsumption = kwargs.get("symmetry", True), kwargs.get("subsumption", True)
        engine = Engine(model, symmetry=symmetry, subsumption=subsumption)
        violations += engine.run(max_states=min(kwargs.get("max_states", 2000), 2000)).violations
        for code in engine.codes[:300]:
            kinds |= {step.kind for step in model.steps(engine.decode(code))}
    assert violations > 10
    assert kinds == set(StepKind)


def test_codes_decode_to_the_canonical_worlds() -> None:
    bounds = Bounds(clients=2, transactions=1, nv_losses=1, old_copies=1, replays=1)
    model = Model(VARIANTS["hardened"], bounds)
    engine = Engine(model, symmetry=True, subsumption=True)
    engine.run(max_states=3000)
    reducer = Reducer(2)
    worlds = [engine.decode(code) for code in engine.codes]
    assert worlds[0] == initial_world(bounds)
    for w in worlds[::7]:
        assert reducer.canonical(w) == w
        assert engine.encode(w) == engine.encode(relabel(w, (1, 0)))
        assert engine.decode(engine.encode(w)) == w
    assert any(w.seen for w in worlds) and any(w.lost_records for w in worlds)
    assert any(w.older != w.clients for w in worlds)


@pytest.mark.parametrize(
    ("variant", "bounds", "kwargs"),
    [
        ("hardened", Bounds(clients=2, transactions=1), {}),
        ("paper", Bounds(), {"max_states": 3000}),
        ("paper", Bounds(clients=2, duplicates=0, power_losses=0), {"stop_at_first": True}),
        ("hardened", Bounds(transactions=1, replays=2, power_losses=0), {}),
        ("hardened", Bounds(transactions=1, forgeries=1, losses=0), {"max_states": 500}),
    ],
    ids=["hardened", "paper, all", "paper, first", "replayer", "forger"],
)
def test_a_second_process_expanding_changes_nothing(
    variant: str, bounds: Bounds, kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(workers, "TWO_FROM", 40)  # the expander takes over early in the search
    forked = []
    pipelined = workers._pipelined

    def spy(*args: Any) -> Any:
        forked.append(args[2])
        return pipelined(*args)

    monkeypatch.setattr(workers, "_pipelined", spy)
    alone = check(variant, bounds, **kwargs)
    assert not forked
    shared = check(variant, bounds, workers=2, **kwargs)
    assert len(forked) == 1 and 0 < forked[0] < shared.states
    assert [getattr(shared, f) for f in FIGURES] == [getattr(alone, f) for f in FIGURES]
    assert shared.counterexample == alone.counterexample
    assert shared.workers == 2 and shared.as_json()["workers"] == 2


def test_cli_engine_and_workers(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["check", "--transactions", "1", "--json"]
    runs = []
    for extra in ([], ["--engine", "reference"], ["--workers", "2"]):
        assert main([*argv, *extra]) == 0
        runs.append(json.loads(capsys.readouterr().out))
    assert [r["engine"] for r in runs] == ["compact", "reference", "compact"]
    assert [r["workers"] for r in runs] == [1, 1, 1]  # too small a search to fork for
    assert len({(r["states"], r["transitions"], r["depth"], r["subsumed"]) for r in runs}) == 1
    with pytest.raises(SystemExit):
        main(["check", "--workers", "3"])
    assert "outside" in capsys.readouterr().err


def test_an_expander_killed_mid_search_is_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The kernel's out-of-memory killer takes the expander (seen on `--old-copies 2
    --backups`, 7.2 million states, 20 GB): the command says so in one line, exit 2, no
    traceback and no result that looks complete."""
    monkeypatch.setattr(workers, "TWO_FROM", 40)
    expand = workers._expand

    def killed_after_one_batch(engine: Any, requests: Any, answers: Any) -> None:
        real, batches = requests.get, 0

        def once() -> Any:
            nonlocal batches
            if batches:
                os.kill(os.getpid(), signal.SIGKILL)
            batches += 1
            return real()

        requests.get = once
        expand(engine, requests, answers)

    monkeypatch.setattr(workers, "_expand", killed_after_one_batch)
    code = main(["check", "--transactions", "1", "--clients", "2", "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "killed by SIGKILL" in err and "out-of-memory" in err and "--max-states" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
