"""The C supervisor session (firmware/src/session.c) is the hardened SUPERVISOR table: every
cell, on states and events drawn by hypothesis, gives in C the record, the frame sent, the
budget moved and the resolution that ``canergy.core.hardened`` gives (counters modulo 2**32).
A local request the table refuses is refused in C with the record untouched."""

from __future__ import annotations

import ctypes
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.c_binding import ERR_AMOUNT, ERR_PHASE, OK, CSession, Msg, SessionStep, library

from canergy.core.actions import Acknowledged, Resolved, Send
from canergy.core.errors import LocalProtocolError
from canergy.core.hardened import SUPERVISOR
from canergy.core.inputs import POWER_LOSS, RESPONSE_TIMEOUT, Begin, Decide
from canergy.core.state import Decision, Outcome, Phase, Session
from canergy.core.timing import Timing
from canergy.messages import QUANTUM_UJ, Aborted, Ack, Committed, Join, Message, Return

NEVER = (1 << 64) - 1
MOD = 1 << 32
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


def to_c(s: Session) -> CSession:
    return CSession(
        delivered_uj=s.delivered,
        returned_uj=s.returned,
        deadline=NEVER if s.deadline is None else s.deadline,
        tx=s.tx % MOD,
        returns_credited=s.returns_credited % MOD,
        reserved_uj=s.reserved,
        node=s.node,
        phase=int(s.phase),
        decision=int(s.decision),
        tries=s.tries,
    )


def fields_of(s: Session | CSession) -> dict[str, int]:
    if isinstance(s, Session):
        return {
            "delivered": s.delivered,
            "returned": s.returned,
            "deadline": NEVER if s.deadline is None else s.deadline,
            "tx": s.tx % MOD,
            "returns_credited": s.returns_credited % MOD,
            "reserved": s.reserved,
            "phase": int(s.phase),
            "decision": int(s.decision),
            "tries": s.tries,
        }
    return {
        "delivered": s.delivered_uj,
        "returned": s.returned_uj,
        "deadline": s.deadline,
        "tx": s.tx,
        "returns_credited": s.returns_credited,
        "reserved": s.reserved_uj,
        "phase": s.phase,
        "decision": s.decision,
        "tries": s.tries,
    }


def timing_of(t: Timing) -> Any:
    from support.c_binding import SessionTiming

    return SessionTiming(response_timeout_us=t.response_timeout_us, retries=t.retries)


def sent_of(actions: tuple[Any, ...]) -> dict[str, int] | None:
    frames: list[Message] = [a.message for a in actions if isinstance(a, Send)]
    assert len(frames) <= 1
    if not frames:
        return None
    m = frames[0]
    out = {"type": int(m.TYPE), "node": m.node}
    for name in ("tx", "seq", "nonce", "amount_mj", "delivered_mj"):
        if hasattr(m, name):
            out[name] = getattr(m, name)
    return out


def c_sent(step: SessionStep, like: dict[str, int] | None) -> dict[str, int] | None:
    if not step.send:
        return None
    names = like.keys() if like is not None else ("type", "node")
    return {n: getattr(step.msg, n) for n in names}


def resolution(actions: tuple[Any, ...]) -> int:
    done = [a.outcome for a in actions if isinstance(a, Resolved)]
    return int(done[0]) if done else int(Outcome.NONE)


def same(s: Session, t: Timing, event: Any, now: int, call: Any) -> None:
    """Step the Python table and the C library from the same record; compare everything."""
    c = to_c(s)
    step = SessionStep()
    try:
        py = SUPERVISOR.step(t, s, event, now)
    except LocalProtocolError:
        before = fields_of(c)
        assert call(c, step) in (ERR_PHASE, ERR_AMOUNT)
        assert fields_of(c) == before
        return
    assert call(c, step) in (OK, None)
    assert fields_of(c) == fields_of(py.session)
    assert step.credit_uj == py.credit
    expected = sent_of(py.actions)
    assert c_sent(step, expected) == expected
    assert step.resolved == resolution(py.actions)
    assert step.acknowledged == any(isinstance(a, Acknowledged) for a in py.actions)


def wire_near(value: int) -> st.SearchStrategy[int]:
    return st.one_of(st.integers(0, 0xFFFF), st.integers(-3, 4).map(lambda d: (value + d) & 0xFFFF))


@settings(max_examples=400)
@given(sessions(), timings, st.data())
def test_every_message_cell(s: Session, t: Timing, data: st.DataObject) -> None:
    c_lib, ct, now = library(), timing_of(t), data.draw(st.integers(0, 10**9))
    tx, seq = data.draw(wire_near(s.tx)), data.draw(wire_near(s.returns_credited))
    messages: list[Message] = [
        Ack(s.node, tx),
        Committed(s.node, tx),
        Aborted(s.node, tx),
        Return(s.node, seq, data.draw(st.integers(1, 0xFFFF))),
        Join(s.node, data.draw(st.integers(0, 0xFFFF))),
    ]
    for m in messages:
        cm = Msg(type=int(m.TYPE), node=m.node)
        for name in ("tx", "seq", "nonce", "amount_mj"):
            if hasattr(m, name):
                setattr(cm, name, getattr(m, name))
        same(
            s,
            t,
            m,
            now,
            lambda c, step, cm=cm: c_lib.canergy_session_on_msg(
                ctypes.byref(c), ctypes.byref(ct), ctypes.byref(cm), now, ctypes.byref(step)
            ),
        )


@settings(max_examples=300)
@given(sessions(), timings, st.data())
def test_every_local_cell_and_timer(s: Session, t: Timing, data: st.DataObject) -> None:
    c_lib, ct = library(), timing_of(t)
    now = data.draw(st.one_of(st.integers(0, 10**9), st.just(s.deadline or 0)))
    amount = data.draw(
        st.one_of(
            st.integers(1, 65_535).map(lambda mj: mj * QUANTUM_UJ),
            st.sampled_from([0, 1, 999, 65_535_001, 65_536_000]),
        )
    )
    commit = data.draw(st.booleans())
    cases = [
        (Begin(amount), lambda c, step: c_lib.canergy_session_begin(
            ctypes.byref(c), ctypes.byref(ct), amount, now, ctypes.byref(step))),
        (Decide(Decision.COMMIT if commit else Decision.ABORT),
         lambda c, step: c_lib.canergy_session_decide(
             ctypes.byref(c), ctypes.byref(ct), commit, now, ctypes.byref(step))),
        (RESPONSE_TIMEOUT, lambda c, step: c_lib.canergy_session_timer(
            ctypes.byref(c), ctypes.byref(ct), now, ctypes.byref(step))),
        (POWER_LOSS, lambda c, step: c_lib.canergy_session_restart(
            ctypes.byref(c), now, ctypes.byref(step))),
    ]  # fmt: skip
    for event, call in cases:
        same(s, t, event, now, call)


def test_a_changed_cell_fails_here() -> None:
    """The broken build credits an ABORTED without an abort decision (CANERGY_BREAK_ABORTED):
    the comparison catches it on the first such record."""
    s = Session(1, Phase.WAIT_CONFIRM, 7, 5_000, 0, Decision.COMMIT)
    broken, ct, cm = (
        library("broken"),
        timing_of(Timing()),
        Msg(type=int(Aborted.TYPE), node=1, tx=7),
    )

    def call(c: CSession, step: SessionStep) -> None:
        broken.canergy_session_on_msg(
            ctypes.byref(c), ctypes.byref(ct), ctypes.byref(cm), 0, ctypes.byref(step)
        )

    same(
        s,
        Timing(),
        Aborted(1, 7),
        0,
        lambda c, step: library().canergy_session_on_msg(
            ctypes.byref(c), ctypes.byref(ct), ctypes.byref(cm), 0, ctypes.byref(step)
        ),
    )
    with pytest.raises(AssertionError):
        same(s, Timing(), Aborted(1, 7), 0, call)
