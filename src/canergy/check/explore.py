"""Breadth-first exploration: every counterexample found is a shortest one."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from canergy.check.engine import Engine
from canergy.check.model import Bounds, Model, Step, StepKind, World, initial_world
from canergy.check.reduce import Reducer, inverse, relabel_step
from canergy.check.search import breadth_first
from canergy.core.variants import Variant, get_variant
from canergy.messages import MESSAGE_CLASSES, MsgType


@dataclass(slots=True)
class CheckResult:
    variant: str
    bounds: Bounds
    states: int = 0
    transitions: int = 0
    depth: int = 0
    seconds: float = 0.0
    violations: int = 0
    counterexample: list[tuple[Step, World]] | None = None
    worst_quiescent_dissipation: int = 0
    quiescent_states: int = 0
    subsumed: int = 0
    symmetry: bool = True
    engine: str = "compact"
    workers: int = 1
    """Processes the search ran in (a second one expands large searches: ``workers``)."""
    complete: bool = True
    notes: list[str] = field(default_factory=list)

    @property
    def states_per_second(self) -> float:
        return self.states / self.seconds if self.seconds > 0 else 0.0

    def as_json(self) -> dict[str, Any]:
        trace = None
        if self.counterexample is not None:
            trace = [
                {"step": step_json(step), "event": step.describe(), "ledger": w.ledger().as_json()}
                for step, w in self.counterexample
            ]
        return {
            "variant": self.variant,
            "bounds": {k: getattr(self.bounds, k) for k in self.bounds.__slots__},
            "states": self.states,
            "transitions": self.transitions,
            "depth": self.depth,
            "seconds": round(self.seconds, 3),
            "states_per_second": round(self.states_per_second),
            "violations": self.violations,
            "subsumed": self.subsumed,
            "symmetry": self.symmetry,
            "engine": self.engine,
            "workers": self.workers,
            "complete": self.complete,
            "worst_quiescent_dissipated_uj": self.worst_quiescent_dissipation,
            "quiescent_states": self.quiescent_states,
            "counterexample": trace,
        }


def step_json(step: Step) -> dict[str, Any]:
    out: dict[str, Any] = {"kind": step.kind.value}
    if step.node:
        out["node"] = step.node
    if step.kind is StepKind.BEGIN:
        out["units"] = step.units
    if step.kind is StepKind.DECIDE:
        out["commit"] = step.commit
    if step.kind is StepKind.RESYNC:
        out["nonce"] = step.nonce
    if step.message is not None:
        out["message"] = {"type": step.message.TYPE.name, **_fields(step.message)}
    return out


def step_from_json(data: dict[str, Any]) -> Step:
    """The inverse of ``step_json``: rebuild a step (and its message) from a JSON trace."""
    message = None
    if "message" in data:
        fields = dict(data["message"])
        cls = MESSAGE_CLASSES[MsgType[fields.pop("type")]]
        message = cls(**fields)
    return Step(
        StepKind(data["kind"]),
        data.get("node", 0),
        data.get("units", 0),
        data.get("commit", False),
        message,
        data.get("nonce", 0),
    )


def _fields(msg: object) -> dict[str, int]:
    return {name: getattr(msg, name) for name in msg.__slots__}  # type: ignore[attr-defined]


def check(
    variant: str | Variant = "hardened",
    bounds: Bounds | None = None,
    *,
    max_states: int | None = None,
    stop_at_first: bool = False,
    progress: Callable[[int, int, float], None] | None = None,
    symmetry: bool = True,
    subsumption: bool = True,
    engine: str = "compact",
    workers: int = 1,
) -> CheckResult:
    """Explore every reachable world within ``bounds``; count the ones that generate energy.

    Worlds are stored up to client symmetry and counter subsumption (see ``reduce``), which the
    flags can turn off. ``progress(states, depth, seconds)`` is called every 100,000 new states.
    ``engine``: ``compact`` (packed worlds, ``engine``) or ``reference`` (``World`` objects);
    both store the same states in the same order and find the same counterexample. ``workers``
    2 (compact engine): a second process expands the states while this one stores them.
    """
    v = get_variant(variant) if isinstance(variant, str) else variant
    b = bounds or Bounds()
    model = Model(v, b)
    # the supervisor's old copy holds every session: it is not relabeled with the nodes
    symmetry = symmetry and not b.supervisor_old_copies
    reducer = Reducer(b.clients, symmetry=symmetry, subsumption=subsumption)
    result = CheckResult(v.name, b, symmetry=reducer.symmetry, engine=engine)
    if engine == "compact":
        return _check_compact(model, reducer, result, max_states, stop_at_first, progress, workers)
    if engine != "reference":
        raise ValueError(f"unknown engine {engine!r}; choose compact or reference")
    if workers != 1:
        raise ValueError("more workers need the compact engine")

    def successors(world: World) -> Iterator[tuple[Step, World]]:
        for step in model.steps(world):
            nxt = model.apply(world, step)
            if nxt is not None:
                yield step, reducer.canonical(nxt)

    def kept(world: World) -> None:
        if world.quiescent():
            result.quiescent_states += 1
            dissipated = world.ledger().dissipated
            result.worst_quiescent_dissipation = max(result.worst_quiescent_dissipation, dissipated)

    search = breadth_first(
        reducer.canonical(initial_world(b)),
        successors,
        admit=reducer.admit,
        violates=lambda world: world.ledger().dissipated < 0,
        kept=kept,
        max_states=max_states,
        stop_at_first=stop_at_first,
        progress=progress,
    )
    result.states, result.transitions, result.depth = (
        search.states,
        search.transitions,
        search.depth,
    )
    result.violations, result.complete, result.notes = (
        search.violations,
        search.complete,
        search.notes,
    )
    result.subsumed, result.seconds = reducer.subsumed, search.seconds
    if search.first_violation is not None:
        result.counterexample = _trace(model, reducer, search.path(search.first_violation))
    return result


def _check_compact(
    model: Model,
    reducer: Reducer,
    result: CheckResult,
    max_states: int | None,
    stop_at_first: bool,
    progress: Callable[[int, int, float], None] | None,
    workers: int,
) -> CheckResult:
    engine = Engine(model, symmetry=reducer.symmetry, subsumption=reducer.subsumption)
    found = engine.run(
        max_states=max_states, stop_at_first=stop_at_first, progress=progress, workers=workers
    )
    result.workers = 1 if engine.expander_from is None else 2
    for name in (
        "states",
        "transitions",
        "depth",
        "violations",
        "subsumed",
        "quiescent_states",
        "worst_quiescent_dissipation",
        "complete",
        "notes",
        "seconds",
    ):
        setattr(result, name, getattr(found, name))
    if found.first_violation is not None:
        worlds = engine.path(found.first_violation)
        links = [(_step_between(model, reducer, a, b), b) for a, b in itertools.pairwise(worlds)]
        result.counterexample = _trace(model, reducer, links)
    return result


def _step_between(model: Model, reducer: Reducer, world: World, stored: World) -> Step:
    """The first step (in ``Model.steps`` order) from ``world`` to the canonical ``stored``."""
    for step in model.steps(world):
        nxt = model.apply(world, step)
        if nxt is not None and reducer.canonical(nxt) == stored:
            return step
    raise AssertionError("no step leads to a stored successor")


def _trace(
    model: Model, reducer: Reducer, links: list[tuple[Step, World]]
) -> list[tuple[Step, World]]:
    """The path as steps that replay from the initial world (symmetry undone)."""
    trace: list[tuple[Step, World]] = []
    actual = initial_world(model.bounds)
    for step, stored in links:
        # ``step`` was taken from the canonical form of ``actual``: undo that relabeling.
        step = relabel_step(step, inverse(reducer.perm(actual)))
        actual_next = model.apply(actual, step)
        assert actual_next is not None and reducer.canonical(actual_next) == stored
        trace.append((step, actual_next))
        actual = actual_next
    return trace
