"""Every cell of the hardened client's transition table (its cases: ``support.client_cases``)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from support import cells
from support.cells import Case, params, run_case, run_ignored
from support.client_cases import (
    CASES,
    EVENTS,
    FRESH,
    HOLDING,
    IGNORED,
    REFUSED,
    RETURNING,
    STATES,
    T,
    intention,
)

from canergy.core import LocalProtocolError, Send
from canergy.core.hardened import CLIENT as TABLE
from canergy.core.inputs import GiveBack, Spend
from canergy.messages import Ack


@pytest.mark.parametrize("case", params(CASES))
def test_cell(case: Case) -> None:
    run_case(TABLE, T, case)


@pytest.mark.parametrize("cell", sorted(IGNORED, key=str), ids=str)
def test_ignored(cell: cells.CellKey) -> None:
    run_ignored(TABLE, T, cell, STATES, EVENTS)


def test_every_cell_has_a_test() -> None:
    cells.check_coverage(TABLE, CASES, IGNORED, REFUSED)


@pytest.mark.parametrize(
    "event", [Spend(0), Spend(10_001), GiveBack(1500), GiveBack(11_000), GiveBack(0)], ids=str
)
def test_local_requests_guarded_by_energy(event: object) -> None:
    with pytest.raises(LocalProtocolError):
        TABLE.step(T, FRESH, event, 0)


def test_one_return_at_a_time() -> None:
    assert TABLE.can_give_back(FRESH) and not TABLE.can_give_back(RETURNING)
    with pytest.raises(LocalProtocolError):
        TABLE.step(T, RETURNING, GiveBack(1000), 0)


def test_tx_wraps_on_the_wire() -> None:
    start = replace(FRESH, last_tx=0xFFFF)
    held, actions = TABLE.step(T, start, intention(0), 0)
    assert held.held_tx == 0x10000 and actions == (Send(Ack(2, 0)),)


def test_what_persists() -> None:
    assert TABLE.persistent(HOLDING) == TABLE.persistent(FRESH)
    assert TABLE.persistent(RETURNING) != TABLE.persistent(FRESH)
