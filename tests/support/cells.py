"""Cell-by-cell tests of the transition tables: every cell of a table must have a test.

A test module lists named ``Case``s for the cells that do something, plus the cells it expects to
ignore an event or refuse a request; ``check_coverage`` fails when a table has a cell none of these
name (a new rule without a test) or a test names a cell the table lacks.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import pytest

from canergy.core import ClientState, LocalProtocolError, Phase, Session, Timing
from canergy.core.table import RuleTable

CellKey = tuple[Phase, type]


@dataclass(frozen=True)
class Case:
    name: str
    start: Session | ClientState
    event: object
    end: Session | ClientState
    actions: tuple[Any, ...] = ()
    credit: int = 0
    now: int = 50

    @property
    def cell(self) -> CellKey:
        return (self.start.phase, type(self.event))


def params(cases: Iterable[Case]) -> list[Any]:
    return [pytest.param(c, id=c.name) for c in cases]


def run_case(table: RuleTable[Any, Any], t: Timing, case: Case) -> None:
    step = table.step(t, case.start, case.event, case.now)
    expected = (case.end, case.actions)
    if isinstance(case.start, Session):
        expected = (*expected, case.credit)
    assert tuple(step) == expected
    assert step[0].phase in table.cells[case.cell].to, "ended in a phase the table does not list"


def run_ignored(
    table: RuleTable[Any, Any], t: Timing, cell: CellKey, states: Mapping[Phase, Any], events: Any
) -> None:
    start, event = states[cell[0]], events[cell[1]]
    step = table.step(t, start, event, 10**9)
    assert step[0] == start and tuple(step[1]) == ()
    if isinstance(start, Session):
        assert step[2] == 0


def run_refused(
    table: RuleTable[Any, Any], t: Timing, cell: CellKey, states: Mapping[Phase, Any], events: Any
) -> None:
    with pytest.raises(LocalProtocolError):
        table.step(t, states[cell[0]], events[cell[1]], 0)


def check_coverage(
    table: RuleTable[Any, Any], cases: Iterable[Case], ignored: set[CellKey], refused: set[CellKey]
) -> None:
    tested = {c.cell for c in cases}
    assert not (tested & ignored) and not (tested & refused) and not (ignored & refused)
    every = set(table.cells)
    assert (tested | ignored | refused) - every == set(), "tests name cells the table lacks"
    assert every - (tested | ignored | refused) == set(), "cells without a test"
