"""Every table test of the hardened client (tests/test_hardened_client.py), run on the C client.

Each case's start state is put into the C struct, its event goes in through the C entry point
(messages as frames through the C decoder), and the C end state, frames, notes and persist
request must equal what the Python table gives and what the case expects.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
from support.c_binding import (
    ERR_AMOUNT,
    ERR_PHASE,
    EV_ADMITTED,
    OK,
    PHASES,
    CClient,
    Out,
    c_view,
    events_of,
    frames_of,
    out_frames,
)
from support.cells import Case, check_coverage, params
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
)

from canergy.codec import Codec
from canergy.core.errors import LocalProtocolError
from canergy.core.hardened import CLIENT as TABLE
from canergy.core.inputs import (
    RETURN_TIMEOUT,
    BooksLost,
    CommandTimeout,
    GiveBack,
    PowerLoss,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import ClientState, Phase
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    USABLE_MAX_UJ,
    Abort,
    Commit,
    Intention,
    ReturnAck,
)

CODEC = Codec()


def run_c(start: ClientState, event: object, now: int) -> tuple[CClient, Out | int]:
    """The C client in ``start``, after ``event`` at ``now``: (client, out or refusal code)."""
    c = CClient(start.node, timing=T, state=start)
    if isinstance(event, CommandTimeout):
        return c, c.command_timer(now)
    if isinstance(event, ReturnTimeout):
        return c, c.return_timer(now)
    if isinstance(event, PowerLoss):
        return c, c.restart(now)
    if isinstance(event, BooksLost):
        return c, c.join(event.nonce, now)
    if isinstance(event, Spend):
        code = c.do_spend(event.amount)
        return c, c.out if code == OK else code
    if isinstance(event, GiveBack):
        code = c.do_give_back(event.amount, now)
        return c, c.out if code == OK else code
    return c, c.message(event, now)  # type: ignore[arg-type]


def assert_same_step(start: ClientState, event: object, now: int) -> None:
    """The C client and the Python table agree on this step in every respect."""
    step = TABLE.step(T, start, event, now)
    c, out = run_c(start, event, now)
    assert isinstance(out, Out), f"C refused with {out}"
    assert c.view() == c_view(step.client)
    assert out_frames(out) == frames_of(CODEC, step.actions)
    assert out.events & ~EV_ADMITTED == events_of(step.actions)
    admitted = start.phase is Phase.JOINING and step.client.phase is not Phase.JOINING
    assert bool(out.events & EV_ADMITTED) == admitted
    record_changed = TABLE.persistent(start) != TABLE.persistent(step.client)
    if not isinstance(event, BooksLost):  # C never writes a blank record (client.h)
        assert bool(out.persist) == record_changed


@pytest.mark.parametrize("case", params(CASES))
def test_cell(case: Case) -> None:
    assert isinstance(case.start, ClientState)
    assert_same_step(case.start, case.event, case.now)
    c, out = run_c(case.start, case.event, case.now)
    assert isinstance(out, Out)
    assert c.view() == c_view(case.end)  # type: ignore[arg-type]
    assert out_frames(out) == frames_of(CODEC, case.actions)


@pytest.mark.parametrize("cell", sorted(IGNORED, key=str), ids=str)
def test_ignored(cell: tuple[Phase, type]) -> None:
    start, event = STATES[cell[0]], EVENTS[cell[1]]
    c, out = run_c(start, event, 10**9)
    assert isinstance(out, Out)
    assert c.view() == c_view(start) and out_frames(out) == [] and not out.persist
    assert out.events == 0


@pytest.mark.parametrize("cell", sorted(REFUSED, key=str), ids=str)
def test_refused(cell: tuple[Phase, type]) -> None:
    start, event = STATES[cell[0]], EVENTS[cell[1]]
    c, out = run_c(start, event, 0)
    assert out == ERR_PHASE and c.view() == c_view(start)


@pytest.mark.parametrize(
    "event", [Spend(0), Spend(10_001), GiveBack(1500), GiveBack(11_000), GiveBack(0)], ids=str
)
def test_local_requests_guarded_by_energy(event: object) -> None:
    c, out = run_c(FRESH, event, 0)
    assert out == ERR_AMOUNT and c.view() == c_view(FRESH)


def test_one_return_at_a_time() -> None:
    c, out = run_c(RETURNING, GiveBack(1000), 0)
    assert out == ERR_PHASE and not c.can_give_back()
    assert CClient(2, timing=T, state=FRESH).can_give_back()


def test_every_cell_is_run_on_c_too() -> None:
    """The cases above are the Python table's own list, so a new cell there is a new C test."""
    check_coverage(TABLE, CASES, IGNORED, REFUSED)


# -- beyond the table's cases: counters at their wrap and end, energy at the record's limit ------

WRAPS = [
    0xFFFF,
    0x10000,
    0x2_FFFF,
    COUNTER_END - 0x8000,
    COUNTER_END - 3,
    COUNTER_END - 2,
    COUNTER_END - 1,
    COUNTER_END,
    COUNTER_BOUND - 1,
]


@pytest.mark.parametrize("last_tx", WRAPS)
@pytest.mark.parametrize("delta", [-0x8000, -2, -1, 0, 1, 2, 3, 0x7FFE, 0x7FFF])
def test_tx_comparisons_wrap_as_in_python(last_tx: int, delta: int) -> None:
    """Counters compare as Python's, past every wrap of the wire, up to the end of the numbering
    (``COUNTER_END``: neither takes a transaction there) and in a record at the bound."""
    for start in (
        replace(FRESH, last_tx=last_tx),
        replace(HOLDING, last_tx=last_tx, held_tx=last_tx + 1, deadline=1000),
        replace(HOLDING, last_tx=last_tx, held_tx=last_tx + 3, deadline=1000),
    ):
        wire = (last_tx + delta) & 0xFFFF
        for event in (
            Intention(2, wire, 4, 50),
            Commit(2, wire, 4),
            Abort(2, wire, 4),
        ):
            assert_same_step(start, event, 77)


@pytest.mark.parametrize("credited_mj", [0, 5, 0xFFFFFF, 0x1000000, 2**32 - 3, 2**32 + 9])
@pytest.mark.parametrize("delta", [-0x800000, -1, 0, 1, 1000, 0x7FFFFF])
def test_delivered_count_wraps_as_in_python(credited_mj: int, delta: int) -> None:
    for usable in (0, 10_000, USABLE_MAX_UJ - 4000, USABLE_MAX_UJ):
        start = replace(FRESH, usable=usable, credited=credited_mj * 1000)
        gs = (credited_mj + delta) & 0xFFFFFF
        assert_same_step(start, Intention(2, 6, 4, gs), 0)
        assert_same_step(start, Intention(2, 5, 4, gs), 0)
        assert_same_step(replace(start, credited_unknown=True), Intention(2, 6, 4, gs), 0)


@pytest.mark.parametrize("seq", [0, 1, 0xFFFF, 0x10000, COUNTER_END - 3, COUNTER_END - 2])
def test_return_numbers_wrap_as_in_python(seq: int) -> None:
    start = replace(RETURNING, return_seq=seq)
    for wire in (seq & 0xFFFF, (seq + 1) & 0xFFFF, (seq - 1) & 0xFFFF):
        assert_same_step(start, ReturnAck(2, wire), 0)
    assert_same_step(replace(FRESH, return_seq=seq), GiveBack(3000), 5)
    assert_same_step(start, RETURN_TIMEOUT, 300)


@pytest.mark.parametrize("seq", [COUNTER_END - 1, COUNTER_END, COUNTER_BOUND - 1])
def test_no_return_is_numbered_at_the_end_in_either_core(seq: int) -> None:
    """The return after ``COUNTER_END - 1`` is refused by both (its RETURN would be ignored),
    and a pending one at the end still completes."""
    fresh = replace(FRESH, return_seq=seq)
    assert not TABLE.can_give_back(fresh)
    with pytest.raises(LocalProtocolError, match=f"return {seq} is the last below"):
        TABLE.step(T, fresh, GiveBack(3000), 5)
    c, code = run_c(fresh, GiveBack(3000), 5)
    assert code == ERR_PHASE and not c.can_give_back() and c.view() == c_view(fresh)
    pending = replace(RETURNING, return_seq=seq)
    assert_same_step(pending, ReturnAck(2, seq & 0xFFFF), 0)
    assert_same_step(pending, RETURN_TIMEOUT, 300)


def test_phases_map_one_to_one() -> None:
    assert sorted(PHASES.values()) == list(range(len(PHASES))) and set(TABLE.phases) < set(PHASES)
