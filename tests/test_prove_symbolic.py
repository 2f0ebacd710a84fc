"""The symbolic hardened rules (``canergy.prove.symbolic``) are the Python tables: every
handler, evaluated on concrete states and messages drawn by hypothesis, gives the state, the
frame sent and the budget moved that ``canergy.core.hardened`` gives. A cell changed in one and
not the other fails here."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.core.actions import Send
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import forward, withdraw_for_return
from canergy.core.hardened import CLIENT, SUPERVISOR
from canergy.core.inputs import (
    POWER_LOSS,
    RESPONSE_TIMEOUT,
    RETURN_TIMEOUT,
    Begin,
    BooksLost,
    CommandTimeout,
    Decide,
    GiveBack,
    PowerLoss,
    Spend,
)
from canergy.core.state import (
    SYNC_PHASES,
    ClientState,
    Decision,
    Outcome,
    Phase,
    Session,
    SupervisorState,
)
from canergy.core.steps import ClientStep
from canergy.core.timing import Timing
from canergy.core.witnessed import CLIENT as W_CLIENT
from canergy.core.witnessed import SUPERVISOR as W_SUPERVISOR
from canergy.core.witnessed import resync_session
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    QUANTUM_UJ,
    SYNC_CONFIRMED,
    USABLE_MAX_UJ,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    Intention,
    Join,
    Message,
    Return,
    ReturnAck,
)

z3 = pytest.importorskip("z3")  # the prove extra: in dev, so CI runs this
from support.sym_states import sym_client, sym_session  # noqa: E402

from canergy.prove import symbolic as sym  # noqa: E402
from canergy.prove import witnessed as sym_w  # noqa: E402

T = Timing()
LIMIT = COUNTER_BOUND - 1
"""Counters drawn up to this, the proof's domain (every loader refuses one beyond it:
tests/test_counters_end.py): the Python core's are unbounded, the model's 32 bits wide and
compared signed, which agree only while counters are less than 2**31 apart (a session at
tx 2.5e9 with W 0 differed in W after counts)."""

counters = st.one_of(
    st.integers(0, 40),
    st.integers(65_500, 65_600),
    st.integers(COUNTER_END - 3, COUNTER_END + 1),  # the end of a node's numbering
    st.integers(0, LIMIT),
)
mj = st.integers(0, 70_000)
energy = mj.map(lambda m: m * QUANTUM_UJ)
amounts = st.integers(1, 65_535)


def near(reference: st.SearchStrategy[int], bits: int = 16) -> st.SearchStrategy[int]:
    """Wire values near a counter (the interesting branches) or anywhere."""
    return st.one_of(st.integers(0, (1 << bits) - 1), reference)


@st.composite
def clients(draw: Any) -> ClientState:
    phase = draw(st.sampled_from([Phase.IDLE, Phase.AWAIT_COMMAND, Phase.JOINING]))
    last_tx = draw(counters)
    holding = phase is Phase.AWAIT_COMMAND
    return ClientState(
        node=1,
        usable=draw(st.integers(0, USABLE_MAX_UJ // QUANTUM_UJ)) * QUANTUM_UJ,
        credited=draw(energy),
        spent=draw(energy),
        last_tx=last_tx,
        outcome=draw(st.sampled_from(list(Outcome))),
        return_seq=draw(counters),
        return_pending=draw(st.sampled_from([0, 5_000])),
        credited_unknown=draw(st.booleans()),
        held_tx=draw(st.integers(last_tx, last_tx + 3)) if holding else 0,
        held_amount=draw(amounts) * QUANTUM_UJ if holding else 0,
        phase=phase,
        nonce=draw(st.integers(0, 0xFFFF)),
    )


def wire_near(value: int) -> st.SearchStrategy[int]:
    return st.one_of(st.integers(0, 0xFFFF), st.integers(-3, 4).map(lambda d: (value + d) & 0xFFFF))


def value(term: Any) -> int | bool:
    term = z3.simplify(term)
    if z3.is_bool(term):
        return bool(z3.is_true(term))
    return int(term.as_long())


def client_fields(c: ClientState | sym.Client) -> dict[str, int | bool]:
    names = ("usable", "credited", "spent", "last_tx", "outcome", "return_seq", "return_pending")
    names += ("credited_unknown", "held_tx", "held_amount", "phase", "nonce", "pending_draw")
    if isinstance(c, ClientState):
        flags = ("credited_unknown", "pending_draw")
        return {n: int(getattr(c, n)) if n not in flags else getattr(c, n) for n in names}
    return {n: value(getattr(c, n)) for n in names}


def sent_python(actions: tuple[Any, ...]) -> tuple[int, ...] | None:
    """The one frame a step sends, as (type, fields...), or None."""
    frames = [a.message for a in actions if isinstance(a, Send)]
    assert len(frames) <= 1
    if not frames:
        return None
    m: Message = frames[0]
    fields = {
        Ack: lambda: (m.tx,),
        Committed: lambda: (m.tx,),
        Aborted: lambda: (m.tx,),
        Join: lambda: (m.nonce,),
        ReturnAck: lambda: (m.seq,),
        Return: lambda: (m.seq, m.amount_mj),
        Admit: lambda: (m.nonce, m.tx, m.seq),
        Intention: lambda: (m.tx, m.amount_mj, m.delivered_mj),
        Commit: lambda: (m.tx, m.amount_mj),
        Abort: lambda: (m.tx, m.amount_mj),
        Debit: lambda: (m.seq, m.amount_mj, m.flags, m.nonce),
    }[type(m)]()
    return (int(m.TYPE), *fields)


def sent_symbolic(s: sym.Sent, width: int) -> tuple[int, ...] | None:
    if not value(s.present):
        return None
    return (value(s.kind), value(s.a), value(s.b), value(s.c), value(s.d))[: width + 1]


def same_client(py: Any, symbolic: tuple[sym.Client, sym.Sent]) -> None:
    state, sent = symbolic
    assert client_fields(state) == client_fields(py.client)
    expected = sent_python(py.actions)
    assert sent_symbolic(sent, 0 if expected is None else len(expected) - 1) == expected


@settings(max_examples=400)
@given(st.data())
def test_intention(data: st.DataObject) -> None:
    c = data.draw(clients())
    tx = data.draw(wire_near(c.last_tx))
    delivered = data.draw(
        near(st.integers(-3, 3).map(lambda d: (c.credited // 1000 + d) % (1 << 24)), 24)
    )
    amount = data.draw(amounts)
    py = CLIENT.step(T, c, Intention(1, tx, amount, delivered), 0)
    args = (z3.BitVecVal(tx, 16), z3.IntVal(amount), z3.IntVal(delivered))
    same_client(py, sym.on_intention(sym_client(c), *args))


@settings(max_examples=300)
@given(st.data(), st.booleans())
def test_commit_and_abort(data: st.DataObject, commit: bool) -> None:
    c = data.draw(clients())
    tx, amount = data.draw(wire_near(c.last_tx)), data.draw(amounts)
    msg = (Commit if commit else Abort)(1, tx, amount)
    py = CLIENT.step(T, c, msg, 0)
    same_client(py, sym.on_command(sym_client(c), commit, z3.BitVecVal(tx, 16), z3.IntVal(amount)))


@settings(max_examples=200)
@given(st.data())
def test_return_ack_admit_and_timeout_commit(data: st.DataObject) -> None:
    c = data.draw(clients())
    seq = data.draw(wire_near(c.return_seq))
    same_client(
        CLIENT.step(T, c, ReturnAck(1, seq), 0),
        sym.on_return_ack(sym_client(c), z3.BitVecVal(seq, 16)),
    )
    nonce = data.draw(st.one_of(st.just(c.nonce), st.integers(0, 0xFFFF)))
    tx, q = data.draw(st.integers(0, 0xFFFF)), data.draw(st.integers(0, 0xFFFF))
    same_client(
        CLIENT.step(T, c, Admit(1, nonce, tx, q), 0),
        sym.on_admit(sym_client(c), *(z3.BitVecVal(v, 16) for v in (nonce, tx, q))),
    )
    if c.phase is Phase.AWAIT_COMMAND:
        c = ClientState(**{**{f: getattr(c, f) for f in c.__slots__}, "deadline": 0})
    same_client(CLIENT.step(T, c, CommandTimeout(), 0), sym.timeout_commit(sym_client(c)))


# -- the supervisor's session ---------------------------------------------------------------


@st.composite
def sessions(draw: Any) -> Session:
    phase = draw(st.sampled_from([Phase.IDLE, Phase.WAIT_ACK, Phase.ACKED, Phase.WAIT_CONFIRM]))
    idle = phase is Phase.IDLE
    decided = phase is Phase.WAIT_CONFIRM
    return Session(
        node=1,
        phase=phase,
        tx=draw(counters),
        reserved=0 if idle else draw(amounts) * QUANTUM_UJ,
        delivered=draw(energy),
        decision=draw(st.sampled_from([Decision.COMMIT, Decision.ABORT]))
        if decided
        else Decision.NONE,
        returns_credited=draw(counters),
        returned=draw(energy),
    )


def same_session(py: Any, step: sym.SessionStep) -> None:
    names = ("phase", "tx", "reserved", "delivered", "decision", "returns_credited", "returned")
    assert {n: value(getattr(step.session, n)) for n in names} == {
        n: int(getattr(py.session, n)) for n in names
    }
    assert value(step.credit) == py.credit
    expected = sent_python(py.actions)
    assert sent_symbolic(step.sent, 0 if expected is None else len(expected) - 1) == expected


@settings(max_examples=300)
@given(st.data())
def test_session_answers(data: st.DataObject) -> None:
    s = data.draw(sessions())
    tx = data.draw(wire_near(s.tx))
    bv = z3.BitVecVal(tx, 16)
    same_session(SUPERVISOR.step(T, s, Ack(1, tx), 0), sym.on_ack(sym_session(s), bv))
    same_session(SUPERVISOR.step(T, s, Committed(1, tx), 0), sym.on_committed(sym_session(s), bv))
    same_session(SUPERVISOR.step(T, s, Aborted(1, tx), 0), sym.on_aborted(sym_session(s), bv))
    seq, amount = data.draw(wire_near(s.returns_credited)), data.draw(amounts)
    same_session(
        SUPERVISOR.step(T, s, Return(1, seq, amount), 0),
        sym.credit_return(sym_session(s), z3.BitVecVal(seq, 16), z3.IntVal(amount)),
    )
    nonce = data.draw(st.integers(0, 0xFFFF))
    same_session(
        SUPERVISOR.step(T, s, Join(1, nonce), 0), sym.admit(sym_session(s), z3.BitVecVal(nonce, 16))
    )


@settings(max_examples=200)
@given(sessions(), amounts, st.booleans())
def test_begin_and_decide(s: Session, amount: int, commit: bool) -> None:
    if s.phase is Phase.IDLE:
        room = value(sym.may_begin(sym_session(s)))
        assert room == (s.tx + 1 < COUNTER_END)
        if room:
            py = SUPERVISOR.step(T, s, Begin(amount * QUANTUM_UJ), 0)
            same_session(py, sym.begin(sym_session(s), z3.IntVal(amount * QUANTUM_UJ)))
        else:
            with pytest.raises(LocalProtocolError, match="the last below"):
                SUPERVISOR.step(T, s, Begin(amount * QUANTUM_UJ), 0)
    if s.phase is Phase.ACKED:
        decision = Decision.COMMIT if commit else Decision.ABORT
        same_session(SUPERVISOR.step(T, s, Decide(decision), 0), sym.decide(sym_session(s), commit))


# -- local events and timers ------------------------------------------------------------------


def due(c: ClientState) -> ClientState:
    """``c`` with its timers due now (the model takes them as due)."""
    return replace(c, deadline=0, return_deadline=0)


@settings(max_examples=200)
@given(clients(), st.integers(1, 80_000).map(lambda m: m * QUANTUM_UJ), st.integers(0, 0xFFFF))
def test_spend_give_back_timers_resets_and_lost_books(
    c: ClientState, amount: int, nonce: int
) -> None:
    s = sym_client(c)
    state, allowed = sym.spend(s, z3.IntVal(amount))
    assert value(allowed) == (c.phase is not Phase.JOINING and amount <= c.usable)
    if value(allowed):
        same_client(CLIENT.step(T, c, Spend(amount), 0), (state, sym.Sent.none()))
    state, sent, allowed = sym.give_back(s, z3.IntVal(amount))
    assert value(allowed) == (CLIENT.can_give_back(c) and amount <= min(c.usable, 65_535_000))
    if value(allowed):
        same_client(CLIENT.step(T, c, GiveBack(amount), 0), (state, sent))
    same_client(CLIENT.step(T, due(c), RETURN_TIMEOUT, 0), sym.resend_return(s))
    same_client(CLIENT.step(T, c, POWER_LOSS, 0), sym.client_power_loss(s))
    same_client(CLIENT.step(T, c, BooksLost(nonce), 0), sym.books_lost(s, z3.BitVecVal(nonce, 16)))


@settings(max_examples=200)
@given(sessions(), st.integers(0, 6))
def test_response_timeouts_and_resets(s: Session, tries: int) -> None:
    timed = replace(s, tries=tries, deadline=0)
    gives_up = z3.BoolVal(tries > T.retries)
    same_session(
        SUPERVISOR.step(T, timed, RESPONSE_TIMEOUT, 0),
        sym.response_timeout(sym_session(s), gives_up),
    )
    same_session(SUPERVISOR.step(T, s, POWER_LOSS, 0), sym.supervisor_power_loss(sym_session(s)))


# -- a gateway's link rules on its client role -------------------------------------------------


@settings(max_examples=200)
@given(clients(), st.integers(1, 80_000).map(lambda m: m * QUANTUM_UJ))
def test_a_gateways_forward_and_give_back_from_below(c: ClientState, amount: int) -> None:
    down = SupervisorState(initial=0, usable=10**12, injected=10**12)
    s = sym_client(c)
    state, allowed = sym.forward(s)
    assert value(allowed) == (c.usable > 0)
    if c.usable > 0:
        up, _ = forward(c, down)
        same_client(ClientStep(up), (state, sym.Sent.none()))
    state, sent, allowed = sym.give_back_from_below(s, z3.IntVal(amount))
    room = CLIENT.can_give_back(c) and amount <= min(c.spent, 65_535_000)
    assert value(allowed) == room
    if room:
        up, _ = withdraw_for_return(c, down, amount)
        same_client(CLIENT.step(T, up, GiveBack(amount), 0), (state, sent))


# -- the witnessed rules (canergy.prove.witnessed against canergy.core.witnessed), both sides'
# starts included: RESUME, SYNC, its books and counts, the window ------------------------------


def frames_python(actions: tuple[Any, ...]) -> list[tuple[int, ...]]:
    """Every frame a step sends, in order, as (type, fields...)."""
    return [f for a in actions if isinstance(a, Send) for f in [sent_python((a,))] if f]


def frames_symbolic(frames: sym_w.Frames, expected: list[tuple[int, ...]]) -> list[Any]:
    out = []
    for i, frame in enumerate(frames):
        width = len(expected[i]) - 1 if i < len(expected) else 0
        got = sent_symbolic(frame, width)
        if got is not None:
            out.append(got)
    return out


def same_client_w(py: Any, symbolic: tuple[sym.Client, sym_w.Frames]) -> None:
    state, frames = symbolic
    assert client_fields(state) == client_fields(py.client)
    expected = frames_python(py.actions)
    assert frames_symbolic(frames, expected) == expected
    assert not value(frames[1].present) or value(frames[0].present)


@st.composite
def witnessed_clients(draw: Any) -> ClientState:
    """A client of the witnessed rules: any phase of their table, a pending draw or return."""
    c = draw(clients())
    phase = draw(st.sampled_from([c.phase, Phase.RESUMING, Phase.SYNCING]))
    held = phase is Phase.AWAIT_COMMAND
    return replace(
        c,
        phase=phase,
        held_tx=c.held_tx if held else 0,
        held_amount=c.held_amount if held else 0,
        pending_draw=bool(c.return_pending) and draw(st.booleans()),
    )


@st.composite
def witnessed_sessions(draw: Any) -> Session:
    """A session with the last start it answered, often the one about to arrive again, W at
    most tx, and any phase of the witnessed table (a start's two, a re-sync's or not)."""
    s = draw(sessions())
    start = draw(st.sampled_from([None, Phase.SYNCING, Phase.SYNC_BOOKS]))
    if start is not None:
        s = replace(s, phase=start, reserved=0, decision=Decision.NONE)
    if s.phase not in (Phase.IDLE, *SYNC_PHASES):
        s = replace(s, tx=max(1, s.tx))  # an open transaction is numbered from 1
    to = draw(st.one_of(st.just(s.returns_credited), st.just(0), counters))
    near_c = st.integers(-2, 2).map(lambda d: max(0, s.returns_credited + d))
    return replace(
        s,
        resume_nonce=draw(st.integers(0, 3)) | draw(st.sampled_from([0, 1 << 16])),
        resume_from=draw(st.one_of(near_c, counters)),
        resume_to=to,
        # below 0: counts whose ltx reads there set W there (``witnessed.ltx_of``)
        witness=draw(
            st.one_of(
                st.integers(max(0, s.tx - 70), s.tx),
                st.integers(0, s.tx),
                st.integers(-0x8000, -1),
            )
        ),
        sync_nonce=draw(st.integers(0, 3)) if start is not None else 0,
        join_nonce=draw(st.integers(0, 3)),
        join_tx=draw(st.integers(max(0, s.tx - 70), s.tx)),
        join_seq=draw(st.one_of(st.just(0), st.integers(0, s.returns_credited))),
        resync=start is not None and draw(st.booleans()),
    )


def witnessed_fields(s: Session | sym.Session) -> dict[str, int]:
    names = ("resume_nonce", "resume_from", "resume_to", "witness", "sync_nonce")
    names += ("join_nonce", "join_tx", "join_seq", "resync")
    if isinstance(s, Session):
        return {n: getattr(s, n) % (1 << 32) for n in names}  # the core keeps an unwrapped -q
    return {n: int(value(getattr(s, n))) for n in names}


def same_session_w(py: Any, step: sym.SessionStep) -> None:
    same_session(py, step)
    assert witnessed_fields(step.session) == witnessed_fields(py.session)


@settings(max_examples=400)
@given(st.data())
def test_witnessed_client_answers(data: st.DataObject) -> None:
    c = data.draw(witnessed_clients())
    s = sym_client(c)
    tx, amount = data.draw(wire_near(c.last_tx)), data.draw(amounts)
    delivered = data.draw(st.integers(0, (1 << 24) - 1))
    same_client_w(
        W_CLIENT.step(T, c, Intention(1, tx, amount, delivered), 0),
        sym_w.on_intention(s, z3.BitVecVal(tx, 16), z3.IntVal(amount), z3.IntVal(delivered)),
    )
    for commit in (True, False):
        msg = (Commit if commit else Abort)(1, tx, amount)
        same_client_w(
            W_CLIENT.step(T, c, msg, 0),
            sym_w.on_command(s, commit, z3.BitVecVal(tx, 16), z3.IntVal(amount)),
        )
    seq = data.draw(wire_near(c.return_seq))
    same_client_w(
        W_CLIENT.step(T, c, ReturnAck(1, seq), 0), sym_w.on_debit_ack(s, z3.BitVecVal(seq, 16))
    )
    ours = c.nonce ^ SYNC_CONFIRMED if c.phase is Phase.SYNCING else c.nonce
    # the last: an ADMIT with SYNC_CONFIRMED set that answers nothing (no SYNC: ignored)
    nonce = data.draw(
        st.sampled_from([c.nonce, ours, c.nonce ^ 1, 0, c.nonce ^ 1 | SYNC_CONFIRMED])
    )
    q = data.draw(st.one_of(wire_near(c.return_seq + 1), st.integers(0, 0xFFFF)))
    same_client_w(
        W_CLIENT.step(T, c, Admit(1, nonce, tx, q), 0),
        sym_w.on_admit(s, *(z3.BitVecVal(v, 16) for v in (nonce, tx, q)), window=T.window),
    )


@settings(max_examples=300)
@given(
    witnessed_clients(),
    st.integers(1, 80_000).map(lambda m: m * QUANTUM_UJ),
    st.integers(0, 0xFFFF),
)
def test_witnessed_client_requests_timers_and_starts(
    c: ClientState, amount: int, nonce: int
) -> None:
    s = sym_client(c)
    for request, cell in ((Spend, sym_w.draw), (GiveBack, sym_w.give_back)):
        state, sent, allowed = cell(s, z3.IntVal(amount))
        try:
            py = W_CLIENT.step(T, c, request(amount), 0)
        except LocalProtocolError:
            assert not value(allowed)
        else:
            assert value(allowed)
            same_client(py, (state, sent))
    same_client_w(W_CLIENT.step(T, due(c), RETURN_TIMEOUT, 0), sym_w.resend(s))
    if c.phase is Phase.AWAIT_COMMAND:
        same_client_w(W_CLIENT.step(T, due(c), CommandTimeout(), 0), sym_w.timeout_commit(s))
    same_client_w(
        W_CLIENT.step(T, c, PowerLoss(nonce), 0), sym_w.power_loss(s, z3.BitVecVal(nonce, 16))
    )
    same_client_w(
        W_CLIENT.step(T, c, BooksLost(nonce), 0), sym_w.books_lost(s, z3.BitVecVal(nonce, 16))
    )


DEBIT_FLAGS = [
    Debit.DRAW,
    Debit.START,
    Debit.START | Debit.DRAW,
    sym_w.COUNTS,
    sym_w.AFRESH_COUNTS,
    Debit.BOOKS,
    sym_w.UNKNOWN_BOOKS,
]


@settings(max_examples=400)
@given(st.data())
def test_witnessed_supervisor_answers_debits(data: st.DataObject) -> None:
    s = data.draw(witnessed_sessions())
    seq = data.draw(st.one_of(wire_near(s.returns_credited), wire_near(s.resume_from)))
    nonce = data.draw(st.one_of(st.integers(0, 3), st.just(s.sync_nonce)))
    flags = data.draw(st.sampled_from(DEBIT_FLAGS))
    amount = 0 if flags == Debit.START and data.draw(st.booleans()) else data.draw(amounts)
    if flags in (sym_w.COUNTS, sym_w.AFRESH_COUNTS):  # ltx on the wire
        amount = data.draw(wire_near(s.tx))
    if flags == Debit.BOOKS:  # Rc: its high 8 bits in the amount field
        rc = data.draw(
            near(st.integers(-3, 3).map(lambda d: (s.delivered // 1000 + d) % (1 << 24)), 24)
        )
        seq, amount = rc & 0xFFFF, rc >> 16
    if flags == sym_w.UNKNOWN_BOOKS:  # no Rc
        seq, amount = 0, 0
    if flags == Debit.DRAW:
        nonce = 0
    msg = Debit(1, nonce, flags, seq, amount)
    args = (z3.BitVecVal(nonce, 16), z3.IntVal(flags), z3.BitVecVal(seq, 16), z3.IntVal(amount))
    same_session_w(W_SUPERVISOR.step(T, s, msg, 0), sym_w.on_debit(sym_session(s), *args))
    same_session_w(W_SUPERVISOR.step(T, s, Join(1, nonce), 0), sym_w.admit(sym_session(s), args[0]))
    same_session_w(
        W_SUPERVISOR.step(T, s, Return(1, seq, max(1, amount)), 0),
        sym_w.credit_return(sym_session(s), args[2], z3.IntVal(max(1, amount))),
    )


@settings(max_examples=200)
@given(witnessed_sessions(), st.integers(-3, 6), st.booleans(), st.data())
def test_witnessed_counts_afresh_near_c(
    s: Session, ahead: int, afresh: bool, data: st.DataObject
) -> None:
    """A start's counts near C, afresh or not: what q above C + 1 moves from Us to Gs
    (``witnessed.ahead_of_image``) is the same in both."""
    s = replace(s, phase=Phase.SYNC_BOOKS, sync_nonce=2)
    seq = (s.returns_credited + ahead) % (1 << 16)
    ltx = data.draw(wire_near(s.tx))
    msg = Debit.counts(1, 2, seq, ltx, afresh)
    args = (z3.BitVecVal(2, 16), z3.IntVal(msg.flags), z3.BitVecVal(seq, 16), z3.IntVal(ltx))
    py = W_SUPERVISOR.step(T, s, msg, 0)
    same_session_w(py, sym_w.on_debit(sym_session(s), *args))
    moved = py.session.delivered - s.delivered
    assert moved == (afresh and ahead > 1) * (ahead - 1) * 65_535_000


@settings(max_examples=300)
@given(witnessed_sessions(), st.data())
def test_witnessed_supervisor_responses_starts_and_window(s: Session, data: st.DataObject) -> None:
    tx = data.draw(wire_near(s.tx))
    bv = z3.BitVecVal(tx, 16)
    for msg, cell in (
        (Ack(1, tx), sym_w.on_ack),
        (Committed(1, tx), sym_w.on_committed),
        (Aborted(1, tx), sym_w.on_aborted),
    ):
        same_session_w(W_SUPERVISOR.step(T, s, msg, 0), cell(sym_session(s), bv))
    tries = data.draw(st.integers(0, 6))
    same_session_w(
        W_SUPERVISOR.step(T, replace(s, tries=tries, deadline=0), RESPONSE_TIMEOUT, 0),
        sym_w.response_timeout(sym_session(s), z3.BoolVal(tries > T.retries)),
    )
    nonce = data.draw(st.integers(0, 0xFFFF))
    same_session_w(
        W_SUPERVISOR.step(T, s, PowerLoss(nonce), 0),
        sym_w.start(sym_session(s), z3.BitVecVal(nonce, 16)),
    )
    may_resync = value(sym_w.may_resync(sym_session(s)))
    try:
        py = resync_session(T, s, nonce, 0)
    except LocalProtocolError:
        assert not may_resync
    else:
        assert may_resync
        same_session_w(py, sym_w.resync_session(sym_session(s), z3.BitVecVal(nonce, 16)))
    if s.phase is Phase.IDLE:
        amount = data.draw(amounts) * QUANTUM_UJ
        room = value(sym_w.may_begin(sym_session(s), T.window))
        try:
            py = W_SUPERVISOR.step(T, s, Begin(amount), 0)
        except LocalProtocolError:
            assert not room
        else:
            assert room
            same_session_w(py, sym.begin(sym_session(s), z3.IntVal(amount)))


@pytest.mark.parametrize("tx", [COUNTER_END - 1, 1 << 31])
def test_a_resume_far_behind_a_lifted_count_is_voided_above_the_lift(tx: int) -> None:
    """C lifted to tx's high half lies far above a q unwrapped below 0: the voided number is
    the lifted C + 1 (a signed comparison of the two would get it wrong 2**31 apart), held below
    the bound (``capped``)."""
    s = Session(1, tx=tx, witness=tx)
    msg = Debit(1, 0, Debit.START, 0x8000, 0)
    py = W_SUPERVISOR.step(T, s, msg, 0)
    args = (z3.BitVecVal(0, 16), z3.IntVal(Debit.START), z3.BitVecVal(0x8000, 16), z3.IntVal(0))
    same_session_w(py, sym_w.on_debit(sym_session(s), *args))
    assert py.session.returns_credited == min((tx & ~0xFFFF) + 1, COUNTER_BOUND - 1)


@pytest.mark.parametrize(
    ("s", "msg"),
    [
        (Session(1), Debit(1, 0, Debit.START, 0, 0)),  # no RESUME answered yet: resume_to 0
        (  # a RETURN pending at a RESUME, numbered at the end: not credited
            Session(1, returns_credited=COUNTER_END - 1),
            Debit(1, 9, Debit.START, COUNTER_END & 0xFFFF, 2),
        ),
        (  # a RESUME with the nonce a SYNC's counts were answered under: answered afresh
            Session(1, returns_credited=5, resume_nonce=9 | 1 << 16, resume_from=4, resume_to=5),
            Debit(1, 9, Debit.START, 4, 0),
        ),
        (  # the counts of that SYNC again: the same answer, nonce flipped
            Session(1, returns_credited=5, resume_nonce=9 | 1 << 16, resume_from=4, resume_to=5),
            Debit.counts(1, 9, 4, 0),
        ),
        (  # those counts again from a later start, ltx above tx: tx and W up, C kept
            Session(
                1, tx=3, returns_credited=5, resume_nonce=9 | 1 << 16, resume_from=4, resume_to=5
            ),
            Debit.counts(1, 9, 4, 70),
        ),
        (  # the same while a transaction is open: written off first
            Session(
                1,
                phase=Phase.WAIT_ACK,
                tx=4,
                reserved=2000,
                delivered=3000,
                returns_credited=5,
                resume_nonce=9 | 1 << 16,
                resume_from=4,
                resume_to=5,
            ),
            Debit.counts(1, 9, 4, 70),
        ),
        (  # an earlier start's counts (another nonce), ltx ahead once widened: ignored
            Session(
                1,
                tx=100_000,
                witness=100_000,
                returns_credited=50,
                resume_nonce=9 | 1 << 16,
                resume_from=49,
                resume_to=50,
            ),
            Debit.counts(1, 3, 10, 60_000),
        ),
        *(  # another nonce, ltx at tx + B (a node that took a late ADMIT for a SYNC: taken)
            # and one past it (ignored)
            (
                Session(1, tx=7, returns_credited=4, resume_nonce=9, resume_from=3, resume_to=4),
                Debit.counts(1, 3, 4, 7 + 64 + d),
            )
            for d in (0, 1)
        ),
    ],
    ids=[
        "first-resume",
        "return-at-the-end",
        "resume-after-counts",
        "counts-again",
        "counts-again-ahead",
        "counts-again-ahead-open",
        "counts-of-an-earlier-start",
        "counts-of-another-nonce-at-tx-plus-b",
        "counts-of-another-nonce-past-tx-plus-b",
    ],
)
def test_witnessed_resumes_at_the_edges(s: Session, msg: Debit) -> None:
    args = (
        z3.BitVecVal(msg.nonce, 16),
        z3.IntVal(msg.flags),
        z3.BitVecVal(msg.seq, 16),
        z3.IntVal(msg.amount_mj),
    )
    same_session_w(W_SUPERVISOR.step(T, s, msg, 0), sym_w.on_debit(sym_session(s), *args))


@pytest.mark.parametrize("seq", [COUNTER_END - 2, COUNTER_END - 1])
def test_no_witnessed_debit_is_numbered_at_the_end(seq: int) -> None:
    c = ClientState(1, usable=5 * QUANTUM_UJ, return_seq=seq)
    for cell in (sym_w.draw, sym_w.give_back):
        assert value(cell(sym_client(c), z3.IntVal(QUANTUM_UJ))[2]) == (seq + 1 < COUNTER_END)


@pytest.mark.parametrize(
    ("c", "msg"),
    [
        (  # SYNC to a node admitted without books: its books say Rc unknown
            ClientState(1, last_tx=5, credited_unknown=True),
            Admit(1, 0x51, 3, 9),
        ),
        (  # a RESUME confirmed below ltx: confirmed, then the counts under its nonce
            ClientState(1, last_tx=69, phase=Phase.RESUMING, nonce=7, credited=5000),
            Admit(1, 7, 5, 1),
        ),
        (  # the counts confirmed below ltx: taken as they come
            ClientState(1, last_tx=69, phase=Phase.SYNCING, nonce=7),
            Admit(1, 7 ^ SYNC_CONFIRMED, 5, 1),
        ),
    ],
    ids=["unknown-rc-books", "resume-below-ltx", "counts-below-ltx"],
)
def test_witnessed_client_starts_at_the_edges(c: ClientState, msg: Admit) -> None:
    same_client_w(
        W_CLIENT.step(T, c, msg, 0),
        sym_w.on_admit(
            sym_client(c),
            *(z3.BitVecVal(v, 16) for v in (msg.nonce, msg.tx, msg.seq)),
            window=T.window,
        ),
    )


@pytest.mark.parametrize("delivered", [2000, (1 << 23) * QUANTUM_UJ + 1000, 10**10])
def test_witnessed_books_of_an_unknown_rc_leave_gs_alone(delivered: int) -> None:
    s = Session(1, phase=Phase.SYNCING, sync_nonce=0x51, delivered=delivered)
    msg = Debit.books(1, 0x51, None)
    args = (z3.BitVecVal(0x51, 16), z3.IntVal(msg.flags), z3.BitVecVal(0, 16), z3.IntVal(0))
    py = W_SUPERVISOR.step(T, s, msg, 0)
    same_session_w(py, sym_w.on_debit(sym_session(s), *args))
    assert py.session.delivered == delivered and py.credit == 0
