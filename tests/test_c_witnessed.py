"""The C client under the witnessed rules (``cfg.rules = CANERGY_RULES_WITNESSED``) is
``canergy.core.witnessed.CLIENT``: every table case of tests/test_witnessed.py, every ignored
and refused cell, run on the C struct with the same state, frames, notes and persist; the NV
record carries the pending draw; a hardened client refuses a record holding one."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import client_cases
from support.c_binding import (
    ERR_AMOUNT,
    ERR_PHASE,
    EV_ADMITTED,
    EV_RELEASED,
    FLAG_PENDING_DRAW,
    OK,
    CClient,
    Out,
    c_view,
    events_of,
    frames_of,
)
from support.c_session import same
from support.cells import Case, params
from support.mem_nv import MemNv, write_slot
from test_c_session import sessions, timings, wire_near
from test_hardened_supervisor import REFUSED as SUP_REFUSED
from test_hardened_supervisor import STATES as SUP_STATES
from test_witnessed import (
    CLIENT_CASES,
    CLIENT_IGNORED,
    CLIENT_REFUSED,
    CLIENT_STATES,
    DRAWING,
    FRESH,
    RESUMED,
    S_OPEN,
    ST,
    SUP_CASES,
    SUP_EVENTS,
    SUP_IGNORED,
    T,
    resume,
)

from canergy.codec import Codec
from canergy.core import witnessed as W
from canergy.core.inputs import (
    BooksLost,
    CommandTimeout,
    GiveBack,
    PowerLoss,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import ClientState, Phase, Session
from canergy.core.timing import Timing
from canergy.messages import Admit, Debit, ReturnAck

CODEC = Codec()
TABLE = W.CLIENT


def run_c(start: ClientState, event: object, now: int) -> tuple[CClient, Out | int]:
    """The witnessed C client in ``start``, after ``event`` at ``now``."""
    c = CClient(start.node, timing=T, state=start, rules="witnessed")
    if isinstance(event, CommandTimeout):
        return c, c.command_timer(now)
    if isinstance(event, ReturnTimeout):
        return c, c.return_timer(now)
    if isinstance(event, PowerLoss):
        return c, c.resume(event.nonce, now)
    if isinstance(event, BooksLost):
        return c, c.join(event.nonce, now)
    if isinstance(event, Spend):
        code = c.do_draw(event.amount, now)
        return c, c.out if code == OK else code
    if isinstance(event, GiveBack):
        code = c.do_give_back(event.amount, now)
        return c, c.out if code == OK else code
    return c, c.message(event, now)  # type: ignore[arg-type]


def assert_same_step(start: ClientState, event: object, now: int) -> Out:
    """The C client and the Python witnessed table agree on this step in every respect."""
    step = TABLE.step(T, start, event, now)
    c, out = run_c(start, event, now)
    assert isinstance(out, Out), f"C refused with {out}"
    assert c.view() == c_view(step.client)
    assert out.sent() == frames_of(CODEC, step.actions)
    assert out.events & ~(EV_ADMITTED | EV_RELEASED) == events_of(step.actions)
    books_from = start.phase in (Phase.JOINING, Phase.RESUMING)
    admitted = books_from and step.client.phase not in (Phase.JOINING, Phase.RESUMING)
    assert bool(out.events & EV_ADMITTED) == admitted
    assert bool(out.events & EV_RELEASED) == (step.client.spent > start.spent)
    record_changed = TABLE.persistent(start) != TABLE.persistent(step.client)
    if not isinstance(event, BooksLost):  # C never writes a blank record (client.h)
        assert bool(out.persist) == record_changed
    return out


@pytest.mark.parametrize("case", params(CLIENT_CASES))
def test_cell(case: Case) -> None:
    assert isinstance(case.start, ClientState)
    assert_same_step(case.start, case.event, case.now)
    c, out = run_c(case.start, case.event, case.now)
    assert isinstance(out, Out)
    assert c.view() == c_view(case.end)  # type: ignore[arg-type]
    assert out.sent() == frames_of(CODEC, case.actions)


@pytest.mark.parametrize("cell", sorted(CLIENT_IGNORED, key=str), ids=str)
def test_ignored(cell: tuple[Phase, type]) -> None:
    start, event = CLIENT_STATES[cell[0]], client_cases.EVENTS[cell[1]]
    c, out = run_c(start, event, 10**9)
    assert isinstance(out, Out)
    assert c.view() == c_view(start) and out.sent() == [] and not out.persist
    assert out.events == 0


@pytest.mark.parametrize("cell", sorted(CLIENT_REFUSED, key=str), ids=str)
def test_refused(cell: tuple[Phase, type]) -> None:
    start, event = CLIENT_STATES[cell[0]], client_cases.EVENTS[cell[1]]
    c, out = run_c(start, event, 0)
    assert out == ERR_PHASE and c.view() == c_view(start)


@pytest.mark.parametrize("state", [DRAWING, client_cases.RETURNING, RESUMED, FRESH], ids=str)
def test_one_debit_at_a_time_and_none_before_the_confirmation(state: ClientState) -> None:
    c = CClient(state.node, timing=T, state=state, rules="witnessed")
    assert c.lib.canergy_client_can_draw(c.c) == TABLE.can_spend(state)
    assert c.can_give_back() == TABLE.can_give_back(state)


@pytest.mark.parametrize(
    "event", [Spend(0), Spend(1500), Spend(65_536_000), GiveBack(0), GiveBack(11_000)], ids=str
)
def test_draws_and_returns_guarded_by_energy(event: object) -> None:
    c, out = run_c(FRESH, event, 0)
    assert out == ERR_AMOUNT and c.view() == c_view(FRESH)


def test_spend_is_refused_under_the_witnessed_rules() -> None:
    """Energy reaches the actuator only through an acknowledged draw."""
    c = CClient(FRESH.node, timing=T, state=FRESH, rules="witnessed")
    assert c.do_spend(1000) == ERR_PHASE and c.view() == c_view(FRESH)


def _booted(image: bytes, rules: str, nonce: int = 0x77) -> CClient:
    c = CClient(FRESH.node, timing=T, rules=rules)
    c.start(image, nonce, 0)
    return c


def test_a_pending_draw_survives_a_reset_and_is_resumed_with_it() -> None:
    """The draw's record (flag bit 1) is written before DRAW leaves; the next start RESUMEs
    with the draw pending, and a hardened client refuses that record (it would return it)."""
    c = CClient(FRESH.node, timing=T, state=FRESH, rules="witnessed")
    assert c.do_draw(2000, 5) == OK and c.out.persist
    assert c.out.sent() == [CODEC.encode(Debit(FRESH.node, 0, Debit.DRAW, 1, 2))]
    assert bytes(c.out.nv_image)[6 + 29] & FLAG_PENDING_DRAW
    image = bytearray()
    write_slot(image, c.out.nv_slot, bytes(c.out.nv_image))
    again = _booted(bytes(image), "witnessed")
    resume = Debit(FRESH.node, 0x77, Debit.START | Debit.DRAW, 1, 2)
    assert again.out.sent() == [CODEC.encode(resume)]
    assert again.state.pending_draw and again.state.phase is Phase.RESUMING
    hardened = _booted(bytes(image), "hardened")
    assert hardened.state.phase is Phase.JOINING
    assert not hardened.state.return_pending


def test_a_restored_older_record_spends_nothing_and_is_found_behind() -> None:
    """A node draws and the supervisor acknowledges (C = 1); its NV is put back to the copy
    from before the draw: it RESUMEs with q = 0, spends nothing, and ADMIT(C + 1) finds it
    behind: its usable budget is gone, the energy the actuator got is counted once."""
    start = replace(FRESH, usable=8000)
    c = CClient(start.node, timing=T, state=start, rules="witnessed")
    older = bytearray()
    MemNv(older).save(start)  # the copy from before the draw
    assert c.do_draw(8000, 0) == OK
    c.message(ReturnAck(start.node, 1), 10)
    assert c.state.spent == start.spent + 8000  # the actuator got it once
    restored = _booted(bytes(older), "witnessed", nonce=0x99)
    assert restored.state.phase is Phase.RESUMING and restored.state.usable == 8000
    assert restored.do_draw(1000, 20) == ERR_PHASE
    assert restored.lib.canergy_client_can_draw(restored.c) is False
    restored.message(Admit(start.node, 0x99, start.last_tx & 0xFFFF, 2), 30)
    assert restored.state.phase is Phase.IDLE and restored.state.usable == 0
    assert restored.state.spent == start.spent


# -- the supervisor's session: witnessed.SUPERVISOR -------------------------------------------


@pytest.mark.parametrize("case", params(SUP_CASES))
def test_session_cell(case: Case) -> None:
    assert isinstance(case.start, Session)
    same(case.start, ST, case.event, case.now, table=W.SUPERVISOR)


@pytest.mark.parametrize("cell", sorted(SUP_IGNORED, key=str), ids=str)
def test_session_ignored(cell: tuple[Phase, type]) -> None:
    same(SUP_STATES[cell[0]], ST, SUP_EVENTS[cell[1]], 10**9, table=W.SUPERVISOR)


@pytest.mark.parametrize("cell", sorted(SUP_REFUSED, key=str), ids=str)
def test_session_refused(cell: tuple[Phase, type]) -> None:
    same(SUP_STATES[cell[0]], ST, SUP_EVENTS[cell[1]], 0, table=W.SUPERVISOR)


def test_the_hardened_session_ignores_a_debit() -> None:
    """DEBIT is taken only with the session's rules set to witnessed."""
    for event in (resume(4), Debit(3, 0, Debit.DRAW, 5, 2)):
        same(S_OPEN, ST, event, 0)


@st.composite
def witnessed_sessions(draw: Any) -> Session:
    """Records with a last RESUME answered near the session's count, as the rules leave it
    (Python's numbers are unbounded, C's modulo 2**32: they agree within 2**15 of each other)."""
    s = draw(sessions())
    near = st.integers(-3, 2).map(lambda d: s.returns_credited + d)
    far = st.sampled_from([-0x10000, 0x10000, 0x8000]).map(lambda d: s.returns_credited + d)
    return replace(
        s,
        resume_nonce=draw(st.sampled_from([0, 9]) | st.integers(0, 0xFFFF)),
        resume_from=draw(near | far),
        resume_to=draw(st.just(s.returns_credited) | near),
    )


@settings(max_examples=400)
@given(witnessed_sessions(), timings, st.data())
def test_every_debit_cell_on_drawn_records(s: Session, t: Timing, data: st.DataObject) -> None:
    """Draws and resumes near the session's counters (a repeat of the last RESUME answered
    included) give in C the record, the frame, the budget, the resolution of witnessed.py."""
    seq = data.draw(wire_near(s.returns_credited))
    amount = data.draw(st.sampled_from([0, 1, 0xFFFF]) | st.integers(0, 0xFFFF))
    nonce = data.draw(st.just(s.resume_nonce) | st.integers(0, 0xFFFF))
    repeat = (s.resume_from & 0xFFFF) if data.draw(st.booleans()) else seq
    for m in (
        Debit(s.node, 0, Debit.DRAW, seq, max(amount, 1)),
        Debit(s.node, nonce, Debit.START, seq, amount),
        Debit(s.node, nonce, Debit.START | Debit.DRAW, seq, amount),
        Debit(s.node, s.resume_nonce, Debit.START, repeat, amount),
    ):
        same(s, t, m, data.draw(st.integers(0, 10**9)), table=W.SUPERVISOR)
