"""Symmetry and subsumption shrink the search without changing what it finds."""

from __future__ import annotations

from itertools import permutations

import pytest

from canergy.check import Bounds, check, replay
from canergy.check.model import Model, World, initial_world
from canergy.check.reduce import Reducer, inverse, relabel
from canergy.core.variants import VARIANTS
from canergy.frozen import evolve


def _reachable(bounds: Bounds, limit: int) -> list[World]:
    """Worlds in breadth-first order without any reduction."""
    model = Model(VARIANTS["hardened"], bounds)
    seen = {initial_world(bounds)}
    order = list(seen)
    for world in order:
        for step in model.steps(world):
            nxt = model.apply(world, step)
            if nxt is not None and nxt not in seen:
                seen.add(nxt)
                order.append(nxt)
        if len(order) >= limit:
            break
    return order


@pytest.mark.parametrize("clients", [2, 3])
def test_every_labeling_of_a_world_has_the_same_canonical_form(clients: int) -> None:
    reducer = Reducer(clients)
    worlds = _reachable(Bounds(clients=clients, transactions=2, units=2), 3000)
    asymmetric = 0
    for w in worlds:
        canon = reducer.canonical(w)
        labelings = {relabel(w, perm) for perm in permutations(range(clients))}
        for perm in permutations(range(clients)):
            assert relabel(relabel(w, perm), inverse(perm)) == w
        assert {reducer.canonical(other) for other in labelings} == {canon}
        asymmetric += len(labelings) > 1
    assert asymmetric > len(worlds) // 2  # most worlds are not symmetric in themselves


def test_subsumption_keeps_only_the_cheapest_runs_to_a_state() -> None:
    reducer = Reducer(1)
    w = initial_world(Bounds())
    assert reducer.admit(evolve(w, started=1, lost=1))
    assert not reducer.admit(evolve(w, started=1, lost=2))  # more used of one budget
    assert not reducer.admit(evolve(w, started=1, lost=1))  # the same again
    assert reducer.admit(evolve(w, started=0, lost=2))  # cheaper in another budget
    assert reducer.admit(evolve(w, started=0, lost=0))  # cheaper in all
    assert not reducer.admit(evolve(w, started=1, lost=1, duplicated=1))
    assert reducer.subsumed == 3


@pytest.mark.parametrize(
    "bounds",
    [
        Bounds(clients=2, duplicates=0, power_losses=0),
        Bounds(clients=2, losses=0, timeouts=2, spending=False),
        Bounds(clients=2, losses=0, duplicates=0, timeouts=3, returns=False),
    ],
    ids=["loss", "duplicate", "power"],
)
def test_paper_counterexamples_stay_shortest_and_replay(bounds: Bounds) -> None:
    plain = check("paper", bounds, stop_at_first=True, symmetry=False, subsumption=False)
    reduced = check("paper", bounds, stop_at_first=True)
    assert plain.counterexample is not None and reduced.counterexample is not None
    assert len(reduced.counterexample) == len(plain.counterexample)
    assert reduced.states < plain.states
    worlds = replay(Model(VARIANTS["paper"], bounds), [s for s, _ in reduced.counterexample])
    assert worlds == [w for _, w in reduced.counterexample]
    assert worlds[-1].ledger().dissipated < 0


def test_reductions_agree_with_the_plain_search_on_the_hardened_rules() -> None:
    bounds = Bounds(clients=2, transactions=2, losses=1, duplicates=1, in_flight=2, retries=0)
    plain = check("hardened", bounds, symmetry=False, subsumption=False)
    reduced = check("hardened", bounds)
    assert plain.violations == reduced.violations == 0
    assert plain.worst_quiescent_dissipation == reduced.worst_quiescent_dissipation
    assert reduced.states * 3 < plain.states and reduced.subsumed > 0
