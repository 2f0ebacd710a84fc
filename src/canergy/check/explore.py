"""Breadth-first exploration: every counterexample found is a shortest one."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from canergy.check.model import Bounds, Model, Step, StepKind, World, initial_world
from canergy.check.reduce import Reducer, inverse, relabel_step
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
) -> CheckResult:
    """Explore every reachable world within ``bounds``; count the ones that generate energy.

    Worlds are stored up to client symmetry and counter subsumption (see ``reduce``), which the
    flags can turn off. ``progress(states, depth, seconds)`` is called every 100,000 new states.
    """
    v = get_variant(variant) if isinstance(variant, str) else variant
    b = bounds or Bounds()
    model = Model(v, b)
    reducer = Reducer(b.clients, symmetry=symmetry, subsumption=subsumption)
    result = CheckResult(v.name, b, symmetry=reducer.symmetry)
    start = time.perf_counter()
    root = reducer.canonical(initial_world(b))
    reducer.admit(root)
    parent: dict[World, tuple[World, Step] | None] = {root: None}
    frontier: deque[tuple[World, int]] = deque([(root, 0)])
    while frontier:
        world, depth = frontier.popleft()
        result.depth = max(result.depth, depth)
        for step in model.steps(world):
            nxt = model.apply(world, step)
            if nxt is None:
                continue
            result.transitions += 1
            nxt = reducer.canonical(nxt)
            if nxt in parent or not reducer.admit(nxt):
                continue
            parent[nxt] = (world, step)
            if progress is not None and len(parent) % 100_000 == 0:
                progress(len(parent), depth + 1, time.perf_counter() - start)
            dissipated = nxt.ledger().dissipated
            if dissipated < 0:
                result.violations += 1
                if result.counterexample is None:
                    result.counterexample = _trace(model, reducer, parent, nxt)
                    if stop_at_first:
                        frontier.clear()
                        break
                continue  # energy was created: nothing after it matters
            if nxt.quiescent():
                result.quiescent_states += 1
                result.worst_quiescent_dissipation = max(
                    result.worst_quiescent_dissipation, dissipated
                )
            frontier.append((nxt, depth + 1))
        if max_states is not None and len(parent) >= max_states:
            result.complete = False
            result.notes.append(f"stopped at --max-states {max_states}")
            break
    result.states = len(parent)
    result.subsumed = reducer.subsumed
    result.seconds = time.perf_counter() - start
    return result


def _trace(
    model: Model, reducer: Reducer, parent: dict[World, tuple[World, Step] | None], end: World
) -> list[tuple[Step, World]]:
    """The path to ``end`` as steps that replay from the initial world (symmetry undone)."""
    links: list[tuple[Step, World]] = []
    node = end
    while (link := parent[node]) is not None:
        prev, step = link
        links.append((step, node))
        node = prev
    trace: list[tuple[Step, World]] = []
    actual = initial_world(model.bounds)
    for step, stored in reversed(links):
        # ``step`` was taken from the canonical form of ``actual``: undo that relabeling.
        step = relabel_step(step, inverse(reducer.perm(actual)))
        actual_next = model.apply(actual, step)
        assert actual_next is not None and reducer.canonical(actual_next) == stored
        trace.append((step, actual_next))
        actual = actual_next
    return trace
