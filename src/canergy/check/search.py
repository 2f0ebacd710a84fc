"""Breadth-first search over worlds, shared by the single-bus and the chain checkers.

Breadth-first order makes every counterexample found a shortest one. Worlds are compared as
given (callers pass canonical forms) and a caller's ``admit`` may refuse one it subsumes.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Generic, TypeVar

W = TypeVar("W", bound=Hashable)
S = TypeVar("S")
PROGRESS_EVERY = 100_000


@dataclass(slots=True)
class Search(Generic[W, S]):
    """What one search found. ``parent`` links every stored world to the one it came from."""

    parent: dict[W, tuple[W, S] | None]
    transitions: int = 0
    depth: int = 0
    violations: int = 0
    first_violation: W | None = None
    complete: bool = True
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def states(self) -> int:
        return len(self.parent)

    def path(self, end: W) -> list[tuple[S, W]]:
        """The steps from the root to ``end``, each with the world it led to."""
        links: list[tuple[S, W]] = []
        node = end
        while (link := self.parent[node]) is not None:
            prev, step = link
            links.append((step, node))
            node = prev
        return links[::-1]


def breadth_first(
    root: W,
    successors: Callable[[W], Iterator[tuple[S, W]]],
    *,
    admit: Callable[[W], bool],
    violates: Callable[[W], bool],
    kept: Callable[[W], None] | None = None,
    max_states: int | None = None,
    stop_at_first: bool = False,
    progress: Callable[[int, int, float], None] | None = None,
) -> Search[W, S]:
    """Every world reachable from ``root`` through ``successors`` (step, world) pairs.

    A new world is stored when ``admit`` takes it; one that ``violates`` is counted and not
    expanded (nothing after it matters); ``kept`` sees every other one. ``progress(states,
    depth, seconds)`` is called every 100,000 stored worlds.
    """
    start = time.perf_counter()
    search: Search[W, S] = Search({root: None})
    admit(root)
    parent = search.parent
    frontier: deque[tuple[W, int]] = deque([(root, 0)])
    while frontier:
        world, depth = frontier.popleft()
        search.depth = max(search.depth, depth)
        for step, nxt in successors(world):
            search.transitions += 1
            if nxt in parent or not admit(nxt):
                continue
            parent[nxt] = (world, step)
            if progress is not None and len(parent) % PROGRESS_EVERY == 0:
                progress(len(parent), depth + 1, time.perf_counter() - start)
            if violates(nxt):
                search.violations += 1
                if search.first_violation is None:
                    search.first_violation = nxt
                    if stop_at_first:
                        frontier.clear()
                        break
                continue
            if kept is not None:
                kept(nxt)
            frontier.append((nxt, depth + 1))
        if max_states is not None and len(parent) >= max_states:
            search.complete = False
            search.notes.append(f"stopped at --max-states {max_states}")
            break
    search.seconds = time.perf_counter() - start
    return search
