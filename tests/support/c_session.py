"""The C supervisor session (firmware/src/session.c) next to the Python table: a Python
``Session`` as the C record, one event as a C call, and ``same``, which steps both from one record
and compares the record, the message sent, the budget moved and the resolution
(tests/test_c_session.py)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from canergy.core.actions import Acknowledged, Admitted, Resolved, Send
from canergy.core.errors import LocalProtocolError
from canergy.core.hardened import SUPERVISOR
from canergy.core.inputs import Begin, Decide, PowerLoss, ResponseTimeout
from canergy.core.state import Decision, Outcome, Session
from canergy.core.table import SupervisorTable
from canergy.core.timing import Timing
from canergy.messages import Message
from support.c_binding import (
    ERR_AMOUNT,
    ERR_END,
    ERR_PHASE,
    ERR_WINDOW,
    NEVER,
    OK,
    RULES,
    CLib,
    CSession,
    Msg,
    SessionStep,
    SessionTiming,
    library,
    ref,
    struct_bytes,
)

MOD = 1 << 32
Call = Callable[[CSession, SessionStep], Any]


def to_c(s: Session) -> CSession:
    return CSession(
        delivered_uj=s.delivered,
        returned_uj=s.returned,
        deadline=NEVER if s.deadline is None else s.deadline,
        tx=s.tx % MOD,
        returns_credited=s.returns_credited % MOD,
        reserved_uj=s.reserved,
        resume_from=s.resume_from % MOD,
        resume_to=s.resume_to % MOD,
        resume_nonce=s.resume_nonce,
        witness=s.witness,
        join_tx=s.join_tx % MOD,
        join_seq=s.join_seq % MOD,
        join_nonce=s.join_nonce,
        sync_nonce=s.sync_nonce,
        node=s.node,
        phase=int(s.phase),
        decision=int(s.decision),
        tries=s.tries,
        resync=int(s.resync),
    )


def fields_of(s: Session | CSession) -> dict[str, int]:
    if isinstance(s, Session):
        return fields_of(to_c(s))
    names = ("delivered_uj", "returned_uj", "deadline", "tx", "returns_credited", "reserved_uj")
    names += ("phase", "decision", "tries", "resume_from", "resume_to", "resume_nonce")
    names += ("witness", "sync_nonce", "join_tx", "join_seq", "join_nonce", "resync")
    return {n: int(getattr(s, n)) for n in names}


def timing_of(t: Timing, rules: str = "hardened", lib: CLib | None = None) -> Any:
    """The C session's timing; ``rules``: the rule set, "hardened" or "witnessed"."""
    return SessionTiming(
        response_timeout_us=t.response_timeout_us,
        retries=t.retries,
        rules=RULES[rules],
        window=t.window,
        lib=lib,
    )


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


def c_call(event: Any, t: Timing, now: int, variant: str = "", rules: str = "hardened") -> Call:
    """The C call for ``event`` (a client message for the node, or a local request or timer)."""
    lib = library(variant)
    ct = timing_of(t, rules, lib)
    call = _c_call(lib, ct, event, now)
    if lib is library():
        return call

    def in_variant(c: Any, step: Any) -> Any:  # the record through the variant's own structs
        vc, vstep = CSession(lib=lib), SessionStep(lib=lib)
        lib.ffi.memmove(vc, struct_bytes(c), CSession.size())
        result = call(vc, vstep)
        ffi = library().ffi
        ffi.memmove(c, bytes(lib.ffi.buffer(vc)), CSession.size())
        ffi.memmove(step, bytes(lib.ffi.buffer(vstep)), SessionStep.size())
        return result

    return in_variant


def _c_call(lib: CLib, ct: Any, event: Any, now: int) -> Call:
    if isinstance(event, Begin):
        return lambda c, step: lib.canergy_session_begin(
            ref(c), ref(ct), event.amount, now, ref(step)
        )
    if isinstance(event, Decide):
        commit = event.decision is Decision.COMMIT
        return lambda c, step: lib.canergy_session_decide(ref(c), ref(ct), commit, now, ref(step))
    if isinstance(event, ResponseTimeout):
        return lambda c, step: lib.canergy_session_timer(ref(c), ref(ct), now, ref(step))
    if isinstance(event, PowerLoss):
        return lambda c, step: lib.canergy_session_start(
            ref(c), ref(ct), event.nonce, now, ref(step)
        )
    cm = Msg(type=int(event.TYPE), node=event.node, lib=lib)
    for name in ("tx", "seq", "nonce", "amount_mj", "flags"):
        if hasattr(event, name):
            setattr(cm, name, getattr(event, name))
    return lambda c, step: lib.canergy_session_on_msg(ref(c), ref(ct), ref(cm), now, ref(step))


def same(
    s: Session,
    t: Timing,
    event: Any,
    now: int,
    call: Call | None = None,
    table: SupervisorTable = SUPERVISOR,
) -> None:
    """Step the Python table and the C library from the same record; compare everything
    (``table``: the witnessed one runs the C session with its rules set to witnessed)."""
    call = call or c_call(event, t, now, rules=table.variant)
    c = to_c(s)
    step = SessionStep()
    try:
        py = table.step(t, s, event, now)
    except LocalProtocolError:
        before = fields_of(c)
        assert call(c, step) in (ERR_PHASE, ERR_AMOUNT, ERR_END, ERR_WINDOW)
        assert fields_of(c) == before
        return
    assert call(c, step) in (OK, None)
    assert fields_of(c) == fields_of(py.session)
    assert step.credit_uj == py.credit
    expected = sent_of(py.actions)
    assert c_sent(step, expected) == expected
    assert step.resolved == resolution(py.actions)
    assert step.acknowledged == any(isinstance(a, Acknowledged) for a in py.actions)
    assert step.admitted == any(isinstance(a, Admitted) for a in py.actions)
