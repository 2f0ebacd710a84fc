"""The search on two cores (``canergy check --workers 2``): one process stores, one expands.

Storing (membership, subsumption, the ledger check) is about a quarter of a search, expanding
(``Engine.successors``) the rest. Here a forked *expander* process keeps the engine's tables and
expands the stored states in breadth-first order as this process sends them, in batches, while
this process stores the successors it gets back, in the same order as the sequential search: the
states, their numbers and the counterexample are the same. The gain is what storing costs, and
it pays only in large searches: the expander is forked once ``TWO_FROM`` states are stored.

Node contents are numbered by the expander alone; with each batch it sends what the storing side
needs of the contents it numbered since (``NodeTable.held``, ``quiet``, ``syncing``, ``bare``,
``seen``), and
at the end the tables that decode a code into a world.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections import deque
from collections.abc import Iterator
from multiprocessing.process import BaseProcess
from multiprocessing.queues import Queue
from queue import Empty
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canergy.check.engine import Engine

BATCH = 1_000
"""States sent to the expander at once."""
AHEAD = 8
"""Batches sent ahead of the storing side (what it waits for when the search stops early)."""
TWO_FROM = 500_000
"""Stored states from which a second process expands (below, forking and sending cost more)."""
MAX_WORKERS = 2
"""Storing and expanding (a second expander would have to share the numbering of contents)."""

Expanded = tuple[int, list[int]]
"""A state's number and its successors' codes."""


def default_workers() -> int:
    """Two processes when this one may run on two cores or more, else one."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return min(MAX_WORKERS, cores or 1)


def expansions(engine: Engine, violating: set[int], workers: int) -> Iterator[Expanded]:
    """Each stored state that is not a violation, by number, with its successors' codes, in
    breadth-first order; the caller stores each one's successors before asking for the next."""
    codes, i = engine.codes, 0
    while i < len(codes):
        if workers > 1 and len(codes) >= TWO_FROM:
            yield from _pipelined(engine, violating, i)
            return
        if i not in violating:
            yield i, engine.successors(codes[i])
        i += 1


def _pipelined(engine: Engine, violating: set[int], first: int) -> Iterator[Expanded]:
    """``expansions`` from state ``first`` on, by a forked expander."""
    engine.expander_from = first
    context = multiprocessing.get_context("fork")
    requests: Queue[Any] = context.Queue()
    answers: Queue[Any] = context.Queue()
    expander = context.Process(target=_expand, args=(engine, requests, answers), daemon=True)
    expander.start()
    codes, table = engine.codes, engine.table
    sent = first  # states numbered below have been sent (or skipped: violations)
    waiting = 0  # batches sent and not answered yet
    ready: deque[Expanded] = deque()

    def top_up() -> None:
        """Keep up to ``AHEAD`` batches at the expander."""
        nonlocal sent, waiting
        while waiting < AHEAD and sent < len(codes):
            end = min(sent + BATCH, len(codes))
            batch = [(i, codes[i]) for i in range(sent, end) if i not in violating]
            sent = end
            if batch:
                requests.put(batch)
                waiting += 1

    def finish() -> None:
        """Stop the expander; take the tables that decode codes into worlds."""
        requests.put(None)
        for _ in range(waiting):  # answers the search did not need (it stopped early)
            _receive(answers, expander)
        decoding = _receive(answers, expander)
        table.contents, table.parts.objects, table.parts.flights, table.parts.seens = decoding
        expander.join()

    try:
        while True:
            if not ready:
                top_up()
                if not waiting:
                    break  # nothing stored is left to expand: the search is over
                numbered, expanded = _receive(answers, expander)
                waiting -= 1
                for held, quiet, syncing, bare, seen in numbered:
                    table.held.append(held)
                    table.quiet.append(quiet)
                    table.syncing.append(syncing)
                    table.bare.append(bare)
                    table.seen.append(seen)
                ready.extend(expanded)
            yield ready.popleft()
            if waiting < AHEAD:
                top_up()
    except GeneratorExit:  # the search stopped early
        finish()
        raise
    except BaseException:
        expander.kill()
        raise
    finish()


def _receive(answers: Queue[Any], expander: BaseProcess) -> Any:
    while True:
        try:
            return answers.get(timeout=1)
        except Empty:
            if not expander.is_alive():
                raise ChildProcessError(_stopped(expander.exitcode)) from None


def _stopped(code: int | None) -> str:
    """Why the search cannot go on, in the words a user needs (the CLI prints it, exit 2)."""
    how = f"exit status {code}"
    if code is not None and code < 0:
        known = -code in signal.Signals._value2member_map_
        how = f"killed by {signal.Signals(-code).name if known else f'signal {-code}'}"
        if code == -signal.SIGKILL:
            how += ", as the kernel's out-of-memory killer does"
    return (
        f"the checker's expander process stopped ({how}); the states held so far are lost: "
        "lower a bound or pass --max-states"
    )


def _expand(engine: Engine, requests: Queue[Any], answers: Queue[Any]) -> None:
    """The expander: successors for each batch of states, and what was numbered meanwhile."""
    table = engine.table
    known = len(table.contents)
    while (batch := requests.get()) is not None:
        expanded = [(i, engine.successors(code)) for i, code in batch]
        numbered = [
            (table.held[c], table.quiet[c], table.syncing[c], table.bare[c], table.seen[c])
            for c in range(known, len(table.contents))
        ]
        known = len(table.contents)
        answers.put((numbered, expanded))
    parts = table.parts
    answers.put((table.contents, parts.objects, parts.flights, parts.seens))
