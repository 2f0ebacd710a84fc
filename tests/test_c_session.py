"""The C supervisor session (firmware/src/session.c) is the hardened SUPERVISOR table: every
cell, on states and events drawn by hypothesis, and every supervisor transition the model
checker explores at its CI bound, gives in C the record, the frame sent, the budget moved and
the resolution that ``canergy.core.hardened`` gives (counters modulo 2**32). A local request the
table refuses is refused in C with the record untouched."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.c_session import MOD, c_call, same

from canergy.check import Bounds, check
from canergy.core.inputs import POWER_LOSS, RESPONSE_TIMEOUT, Begin, Decide
from canergy.core.state import Decision, Phase, Session
from canergy.core.table import SupervisorTable
from canergy.core.timing import Timing
from canergy.messages import QUANTUM_UJ, Aborted, Ack, Committed, Join, Message, Return

OPEN = (Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM)

counters = st.one_of(st.integers(0, 40), st.integers(65_500, 65_600), st.integers(0, MOD - 1))
timings = st.builds(Timing, response_timeout_us=st.integers(0, 10**6), retries=st.integers(0, 5))


@st.composite
def sessions(draw: Any) -> Session:
    phase = draw(st.sampled_from([Phase.IDLE, *OPEN]))
    decided = phase is Phase.WAIT_CONFIRM
    return Session(
        node=draw(st.integers(1, 127)),
        phase=phase,
        tx=draw(counters),
        reserved=0 if phase is Phase.IDLE else draw(st.integers(1, 65_535)) * QUANTUM_UJ,
        delivered=draw(st.integers(0, 1 << 40)) * QUANTUM_UJ,
        decision=draw(st.sampled_from([Decision.COMMIT, Decision.ABORT]))
        if decided
        else Decision.NONE,
        returns_credited=draw(counters),
        returned=draw(st.integers(0, 1 << 40)) * QUANTUM_UJ,
        tries=draw(st.integers(0, 6)),
        deadline=draw(st.one_of(st.none(), st.integers(0, 10**9))),
    )


def wire_near(value: int) -> st.SearchStrategy[int]:
    return st.one_of(st.integers(0, 0xFFFF), st.integers(-3, 4).map(lambda d: (value + d) & 0xFFFF))


@settings(max_examples=400)
@given(sessions(), timings, st.data())
def test_every_message_cell(s: Session, t: Timing, data: st.DataObject) -> None:
    now = data.draw(st.integers(0, 10**9))
    tx, seq = data.draw(wire_near(s.tx)), data.draw(wire_near(s.returns_credited))
    messages: list[Message] = [
        Ack(s.node, tx),
        Committed(s.node, tx),
        Aborted(s.node, tx),
        Return(s.node, seq, data.draw(st.integers(1, 0xFFFF))),
        Join(s.node, data.draw(st.integers(0, 0xFFFF))),
    ]
    for m in messages:
        same(s, t, m, now)


@settings(max_examples=300)
@given(sessions(), timings, st.data())
def test_every_local_cell_and_timer(s: Session, t: Timing, data: st.DataObject) -> None:
    now = data.draw(st.one_of(st.integers(0, 10**9), st.just(s.deadline or 0)))
    amount = data.draw(
        st.one_of(
            st.integers(1, 65_535).map(lambda mj: mj * QUANTUM_UJ),
            st.sampled_from([0, 1, 999, 65_535_001, 65_536_000]),
        )
    )
    decision = data.draw(st.sampled_from([Decision.COMMIT, Decision.ABORT]))
    for event in (Begin(amount), Decide(decision), RESPONSE_TIMEOUT, POWER_LOSS):
        same(s, t, event, now)


def test_a_changed_cell_fails_here() -> None:
    """The broken build credits a duplicated RETURN again (CANERGY_BREAK_RETURN_AGAIN, hazard
    (c)): the comparison catches it on the first such record."""
    s = Session(1, returns_credited=5, returned=7_000)
    again = Return(1, 5, 7)
    same(s, Timing(), again, 0)
    with pytest.raises(AssertionError):
        same(s, Timing(), again, 0, c_call(again, Timing(), 0, "broken"))


CI_BOUND = Bounds(
    clients=2, transactions=2, losses=1, duplicates=1, power_losses=1, in_flight=2, units=1,
    retries=0,
)  # fmt: skip
"""The model checker's bound in the test suite (docs/protocol.md's table)."""
NV_BOUND = dataclasses.replace(CI_BOUND, nv_losses=1)
"""The same with a node that loses its books (JOIN and ADMIT)."""


@pytest.mark.parametrize("bound", [CI_BOUND, NV_BOUND], ids=["ci", "ci-nv-loss"])
def test_every_supervisor_transition_of_the_checkers_ci_bound_is_the_same_in_c(
    bound: Bounds, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The checker explores the bound through the Python table (each distinct record and event
    worked out once); every one of those transitions is replayed on the C session and must
    give the same record, message, budget and resolution, so the checker's verdict (0
    violations) covers the C rules too."""
    seen: list[tuple[Timing, Session, Any, int]] = []
    real_step = SupervisorTable.step

    def recorded(self: SupervisorTable, t: Timing, s: Session, event: Any, now: int) -> Any:
        seen.append((t, s, event, now))
        return real_step(self, t, s, event, now)

    monkeypatch.setattr(SupervisorTable, "step", recorded)
    result = check("hardened", bound, workers=1)
    monkeypatch.undo()
    assert result.complete and result.violations == 0
    kinds = {type(event).__name__ for _, _, event, _ in seen}
    assert {"Begin", "Decide", "Ack", "Committed", "Aborted", "Return", "ResponseTimeout"} <= kinds
    assert "PowerLoss" in kinds and len(seen) > 200
    assert ("Join" in kinds) == (bound.nv_losses > 0)
    for t, s, event, now in seen:
        same(s, t, event, now)
    caught = 0  # and the same replay tells the broken build apart
    for t, s, event, now in seen:
        try:
            same(s, t, event, now, c_call(event, t, now, "broken"))
        except AssertionError:
            caught += 1
    assert caught > 0
