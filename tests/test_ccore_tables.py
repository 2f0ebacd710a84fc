"""The supervisor's tables written twice, side by side. The TELEMETRY table,
``canergy.live.supervisor.telemetry`` and firmware/src/telemetry.c: step for step the same
verdicts and records. The witness's RETURN hold, ``canergy.live.supervisor.witness.ReturnGate``
and firmware/src/witness.c (table for table in tests/test_c_witness.py), here through the
service. Frame for frame a service on the Python core's usual path, one on the Python core's frame
path (``canergy.core.frame_answers``) and one on the C core's frame path (the tables run in the
call that decodes the frame) send the same frames, keep the same books and status and report
the same intrusions in the same words; and on the C path a
TELEMETRY or a RETURN takes none of Python's tables. The grant caps, ``policy.capped_grant``,
``RateLimiter`` and ``TopUp.wanted`` and firmware/src/grants.c: call for call, and through a
service with a top-up policy and limits on each core, frame for frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import can
import pytest
from hypothesis import event, example, given, settings
from hypothesis import strategies as st
from support.c_binding import compiled_core, library
from support.wire import Wire

from canergy.ccore.grants import CompiledGrantCaps
from canergy.codec import Codec
from canergy.core.state import Session
from canergy.core.supervisor import Supervisor
from canergy.core.timing import Timing
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor import policy as policy_module
from canergy.live.supervisor import telemetry
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.grants import PythonGrantCaps
from canergy.live.supervisor.joins import JOIN_HOLD_US, JoinHold
from canergy.live.supervisor.policy import Limits, TopUp, level_room
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.telemetry import (
    BEYOND_BOOKS,
    RECENT_RETURNS,
    TAKEN,
    Heard,
    credited,
    take_telemetry,
)
from canergy.messages import (
    LEVEL_MAX_MJ,
    QUANTUM_UJ,
    Ack,
    Committed,
    Direction,
    Intention,
    Join,
    Message,
    MsgType,
    Return,
    Telemetry,
)

LOST_AFTER_US = 3_000_000
T = Timing(response_timeout_us=1_000, retries=2)
CODEC = Codec()


# -- the tables, call for call ----------------------------------------------------------------
class _CTable:
    """firmware/src/telemetry.c on the tests' sanitizer build: one record, one session."""

    def __init__(self) -> None:
        module = library().module
        self.ffi, self.lib = module.ffi, module.lib
        self.h = self.ffi.new("struct canergy_heard *")
        self.s = self.ffi.new("struct canergy_session *")
        self.m = self.ffi.new("struct canergy_msg *")
        self.lib.canergy_heard_init(self.h)
        assert self.lib.CANERGY_HEARD_RECENT == RECENT_RETURNS
        assert (self.lib.CANERGY_HEARD_TAKEN, self.lib.CANERGY_HEARD_BEYOND) == (
            TAKEN,
            BEYOND_BOOKS,
        )

    def telemetry(self, s: Session, level_mj: int, flags: int, now: int) -> int:
        self.s.delivered_uj, self.s.reserved_uj, self.s.returned_uj = (
            s.delivered,
            s.reserved,
            s.returned,
        )
        self.m.type, self.m.level_mj, self.m.flags = MsgType.TELEMETRY, level_mj, flags
        return int(self.lib.canergy_heard_telemetry(self.h, self.s, self.m, now, LOST_AFTER_US))

    def credited(self, amount_uj: int, now: int) -> None:
        self.lib.canergy_heard_credited(self.h, amount_uj, now, LOST_AFTER_US)

    def record(self) -> Heard:
        h = self.h
        return Heard(
            int(h.level_mj) * QUANTUM_UJ if h.has_level else None,
            int(h.level_at) if h.has_level_at else None,
            int(h.flags),
            int(h.heard_at) if h.has_heard else None,
            int(h.telemetry),
            [(int(h.recent_at[k]), int(h.recent_uj[k])) for k in range(h.recent_count)],
        )


_levels = st.one_of(
    st.integers(0, 12_000), st.sampled_from([LEVEL_MAX_MJ - 1, LEVEL_MAX_MJ]), st.just(0)
)
_table_steps = st.lists(
    st.one_of(
        st.tuples(
            st.just("telemetry"),
            _levels,
            st.sampled_from([0, Telemetry.LOW, Telemetry.JOINING, 0xFF]),
        ),
        *[st.tuples(st.just("credited"), st.integers(1, 65_535).map(lambda mj: mj * QUANTUM_UJ))]
        * 3,  # often enough to fill the entries and merge them
        st.tuples(
            st.just("books"),
            st.integers(0, 10**10),
            st.integers(0, 65_535_000),
            st.integers(0, 10**10),
        ),
        st.tuples(st.just("wait"), st.sampled_from([1, 1, 1_000, LOST_AFTER_US, 1_000_000])),
    ),
    min_size=20,
    max_size=80,
)


@settings(max_examples=300, deadline=None)
@given(_table_steps)
def test_the_c_table_takes_every_step_as_the_python_table(steps: list[tuple[Any, ...]]) -> None:
    """Every verdict (taken, beyond the books) and the whole record after each step: level,
    when, flags, when heard, how many, the returns credited lately (pruned after
    ``lost_after``, merged beyond ``RECENT_RETURNS``)."""
    c, py = _CTable(), Heard()
    now, s = 0, Session(4)
    for step in steps:
        if step[0] == "telemetry":
            verdict = take_telemetry(py, s, step[1], step[2], now, LOST_AFTER_US)
            assert c.telemetry(s, step[1], step[2], now) == verdict, step
            event(f"verdict {verdict}")
        elif step[0] == "credited":
            credited(py, step[1], now, LOST_AFTER_US)
            c.credited(step[1], now)
        elif step[0] == "books":  # delivered, open and returned: what it may hold
            delivered, reserved, returned = step[1:]
            s = Session(4, delivered=delivered + returned, reserved=reserved, returned=returned)
        else:
            now += step[1]
        assert c.record() == py, step


@pytest.mark.parametrize("side", ["python", "c"])
def test_a_level_above_the_books_and_the_returns_lately_is_beyond_them(side: str) -> None:
    """The table's own cases, on each side: the books allow 2 J; 1 J returned lately lifts
    what a level may show for ``lost_after``; nine returns keep eight entries, none lost."""
    c, py = _CTable(), Heard()
    s = Session(4, delivered=2_000_000, returned=0)

    def take(level_mj: int, now: int) -> int:
        if side == "c":
            return c.telemetry(s, level_mj, 0, now)
        return take_telemetry(py, s, level_mj, 0, now, LOST_AFTER_US)

    assert take(2_000, 0) == TAKEN
    assert take(2_001, 0) == TAKEN | BEYOND_BOOKS
    assert take(LEVEL_MAX_MJ, 0) == TAKEN  # saturated: no judgement
    for k in range(9):
        c.credited(100_000, k) if side == "c" else credited(py, 100_000, k, LOST_AFTER_US)
    recent = c.record().recent if side == "c" else py.recent
    assert len(recent) == RECENT_RETURNS and sum(uj for _, uj in recent) == 900_000
    assert recent[0] == (1, 200_000)  # the oldest merged into the next, at the next's time
    assert take(2_900, 10) == TAKEN  # 0.9 J returned lately still counts
    assert take(2_900, 8 + LOST_AFTER_US + 1) == TAKEN | BEYOND_BOOKS  # long after: not


# -- the service, frame for frame -------------------------------------------------------------


@dataclass
class _Bench:
    wire: Wire
    service: SupervisorService
    loop: BusRuntime
    now: list[int]

    def feed(self, msg: Message, wait: int = 100) -> None:
        self.now[0] += wait
        ident, data = CODEC.encode(msg)
        self.wire.inbox.append(can.Message(arbitration_id=ident, data=data, is_extended_id=True))
        self.loop.poll(0)

    def snapshot(self) -> dict[str, Any]:
        status = self.service.status()
        for key in ("core", "frame_path", "frame_path_off", "frame_path_frames"):
            status.pop(key, None)
        return {"sent": list(self.wire.sent), "status": status}


def _bench(
    core: str,
    hold_us: int | None = None,
    limits: Limits | None = None,
    policy: TopUp | None = None,
    path: bool = True,
) -> _Bench:
    """A service on ``core`` with its frame path, or (``path`` False) every frame decoded by
    the bus loop and handed to the service (the usual path)."""
    nodes = [3, 5]
    wire, now = Wire(), [0]
    sup: Any = (
        Supervisor(nodes, 10_000_000, timing=T)
        if core == "python"
        else compiled_core(nodes, 10_000_000, timing=T)
    )
    config = ServiceConfig(
        lost_after_us=LOST_AFTER_US,
        return_hold_us=hold_us,
        limits=limits or Limits(),
        policy=policy,
    )
    service = build_service(sup, config, 0)
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        frame_path=service.frame_path() if path else None,
        counters=service.bus_counters,
        clock=lambda: now[0],
    )
    return _Bench(wire, service, loop, now)


_node = st.sampled_from([3, 5])
_service_steps = st.lists(
    st.one_of(
        st.tuples(st.just("grant"), _node, st.integers(1, 3_000)),
        st.tuples(st.just("return"), _node, st.integers(1, 1_500)),
        st.tuples(
            st.just("telemetry"),
            _node,
            st.one_of(st.integers(0, 8_000), st.just(LEVEL_MAX_MJ)),
            st.sampled_from([0, Telemetry.LOW, Telemetry.JOINING]),
            st.integers(0, 3),
        ),
        st.tuples(st.just("wait"), st.sampled_from([1_000, 1_000_000, LOST_AFTER_US + 1])),
    ),
    max_size=25,
)


def _step(b: _Bench, step: tuple[Any, ...]) -> None:
    kind, *args = step
    s = b.service
    if kind == "grant":  # asked for, then answered by the node: ACK, COMMITTED
        node, mj = args
        s.request_grant(node, mj * QUANTUM_UJ, lambda reply: None)
        b.now[0] += 100
        b.loop.poll(0)
        tx = s.core.session(node).tx & 0xFFFF
        b.feed(Ack(node, tx))
        b.feed(Committed(node, tx))
    elif kind == "return":  # numbered next: credited, or beyond the books (an intrusion)
        node, mj = args
        b.feed(Return(node, (s.core.session(node).returns_credited + 1) & 0xFFFF, mj))
    elif kind == "telemetry":
        node, level, flags, witness = args
        seq = s.core.session(node).returns_credited & 0xFFFF
        b.feed(Telemetry(node, level, flags, seq, witness))
    else:
        b.now[0] += args[0]
        b.loop.poll(0)


@settings(max_examples=100, deadline=None)
@given(_service_steps)
def test_the_c_frame_path_takes_telemetry_as_the_python_path(steps: list[tuple[Any, ...]]) -> None:
    """Frame for frame: the same frames sent, the same books and status (every node's level,
    whether it is lost, its counts), the same intrusions with the same words (a level beyond
    the books, a witness count that moved), the same refusals. The C run's TELEMETRY frames
    were all taken in C."""
    ref, py, c = _bench("python", path=False), _bench("python"), _bench("c")
    for b in (ref, py, c):
        b.feed(Telemetry(3, 0))
        b.feed(Telemetry(5, 0))
    assert c.snapshot() == ref.snapshot() == py.snapshot()
    for step in steps:
        for b in (ref, py, c):
            _step(b, step)
        assert c.snapshot() == ref.snapshot() == py.snapshot(), step
    telemetry_frames = 2 + sum(step[0] == "telemetry" for step in steps)
    assert ref.service.telemetry_heard == c.service.telemetry_heard == telemetry_frames
    assert ref.service.frames_in_c == 0 and c.service.frames_in_c >= telemetry_frames
    status = c.service.status()
    event(f"intrusions: {min(status['intrusions'], 3)}+")
    event(f"returns credited: {min(status['nodes']['3']['returns_credited'], 2)}+")
    for b in (ref, py, c):
        b.wire.shutdown()


def test_on_the_c_frame_path_a_telemetry_takes_no_python_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A TELEMETRY of a managed node on the C core's frame path is taken by the table in C in
    the call that decodes it: Python's table, and the entry to C's for a TELEMETRY decoded in
    Python, are never called; the status counts it among the frames the C path took."""

    def fallback(*args: Any) -> None:
        raise AssertionError("a TELEMETRY fell back to a table called from Python")

    b = _bench("c")
    monkeypatch.setattr(telemetry, "take_telemetry", fallback)
    monkeypatch.setattr(type(b.service.heard), "telemetry", fallback)
    b.feed(Telemetry(3, 0))
    b.feed(Telemetry(3, 1))  # above the books (nothing granted): evidence, worded in Python
    status = b.service.status()
    assert status["frame_path"] == "c" and status["frame_path_frames"] == 2
    assert status["nodes"]["3"]["level_uj"] == 1_000 and status["intrusions"] == 1
    assert (
        "reports 0.001000 J, its books allow 0.000000 J"
        in (b.service.intrusions.recent[-1]["kind"])
    )
    b.wire.shutdown()


# -- the witness's RETURN hold, frame for frame -------------------------------------------------
HOLD_US = 500_000
_witness_steps = st.lists(
    st.one_of(
        st.tuples(st.just("grant"), _node, st.integers(1, 3_000)),
        st.tuples(st.just("return"), _node, st.integers(1, 3), st.integers(1, 1_500)),
        st.tuples(
            st.just("telemetry"),
            _node,
            st.integers(0, 6_000),
            st.integers(-1, 3),
            st.sampled_from([0, 0, 0, 1, 2]),  # mostly no evidence: returns are released
        ),
        st.tuples(st.just("wait"), st.sampled_from([1_000, HOLD_US, HOLD_US + 1, 5_000_000])),
    ),
    max_size=30,
)


def _witness_step(b: _Bench, step: tuple[Any, ...], witness: dict[int, int]) -> None:
    """A RETURN numbered 1-3 past the books' (held, a copy, another amount: evidence); a
    TELEMETRY reporting a return number -1..3 past them and a witness count moved by 0-2."""
    kind, *args = step
    s = b.service
    if kind == "return":
        node, ahead, mj = args
        b.feed(Return(node, (s.core.session(node).returns_credited + ahead) & 0xFFFF, mj))
    elif kind == "telemetry":
        node, level, ahead, moved = args
        witness[node] = (witness[node] + moved) & 0xFF
        seq = (s.core.session(node).returns_credited + ahead) & 0xFFFF
        b.feed(Telemetry(node, level, 0, seq, witness[node]))
    else:
        _step(b, step)


@settings(max_examples=100, deadline=None)
@given(_witness_steps)
@example(  # a RETURN credited that the books never gave (a silent node's, confirmed by a forged
    # TELEMETRY): the books then let the node hold less than nothing, and its next RETURN is
    # evidence on both paths (C once compared unsigned, wrapped, and saw none)
    [("return", 3, 2, 1), ("telemetry", 3, 0, 2, 0), ("wait", HOLD_US), ("return", 3, 1, 1)]
)
def test_the_c_frame_path_holds_returns_as_the_python_path(steps: list[tuple[Any, ...]]) -> None:
    """Without a key (``return_hold_us``): frame for frame the same frames, books and status
    (returns held, refuted, resynchronised, credited), the same evidence in the same words (a
    witness count that moved, a return number that went back, two RETURNs under one number)
    and the same stop-worthy intrusions. The C run took every TELEMETRY and RETURN the books
    allow in C."""
    ref, py, c = (
        _bench("python", HOLD_US, path=False),
        _bench("python", HOLD_US),
        _bench("c", HOLD_US),
    )
    witness = {"python": {3: 0, 5: 0}, "path": {3: 0, 5: 0}, "c": {3: 0, 5: 0}}
    for b in (ref, py, c):
        b.feed(Telemetry(3, 0))
        b.feed(Telemetry(5, 0))
    for step in steps:
        _witness_step(ref, step, witness["python"])
        _witness_step(py, step, witness["path"])
        _witness_step(c, step, witness["c"])
        assert c.snapshot() == ref.snapshot() == py.snapshot(), step
    assert [r["kind"] for r in c.service.intrusions.recent] == [
        r["kind"] for r in ref.service.intrusions.recent
    ]
    status = c.service.status()
    held = sum(n.get("returns_refuted", 0) for n in status["nodes"].values())
    event(f"refuted: {min(held, 2)}+, intrusions: {min(status['intrusions'], 2)}+")
    event(f"credited: {min(status['nodes']['3']['returns_credited'], 2)}+")
    for b in (ref, py, c):
        b.wire.shutdown()


def _no_fallback(*args: Any) -> None:
    raise AssertionError("fell back to a rule called from Python")


def test_on_the_c_frame_path_a_return_takes_no_python_rule(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A RETURN the books allow is held by the witness in C (without a key) in the call that
    decodes it, or credited by the rules there (an old number; with a key, no hold): neither
    Python's gate nor the core's ``receive`` (a frame decoded in Python) is called, and the
    status counts both among the frames the C path took."""
    for hold in (HOLD_US, None):
        b = _bench("c", hold)
        b.feed(Telemetry(3, 0))
        _step(b, ("grant", 3, 2_000))
        taken = b.service.frames_in_c
        monkeypatch.setattr(type(b.service.witness), "hold", _no_fallback)
        monkeypatch.setattr(type(b.service.core), "receive", _no_fallback)
        b.feed(Return(3, 1, 500))
        node = b.service.status()["nodes"]["3"]
        if hold is None:  # credited at once
            assert node["returns_credited"] == 1 and node["returns_credited_uj"] == 500_000
        else:
            assert node["returns_held"] == 1 and node["returns_credited"] == 0
        assert b.service.frames_in_c == taken + 1
        monkeypatch.undo()
        b.wire.shutdown()


def test_on_the_c_frame_path_the_witness_reads_a_telemetry_in_c(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The witness takes a TELEMETRY in C, in the call that decodes it: Python's gate is not
    called, and what C found is worded as Python words it (a witness count that moved)."""
    b = _bench("c", HOLD_US)
    monkeypatch.setattr(type(b.service.witness), "telemetry", _no_fallback)
    b.feed(Telemetry(3, 0, 0, 0, 0))
    b.feed(Telemetry(3, 0, 0, 0, 2))
    status = b.service.status()
    assert status["frame_path_frames"] == 2 and status["intrusions"] == 1
    assert b.service.intrusions.recent[-1]["kind"] == (
        "the node saw 2 frame(s) in its name that it did not send"
    )
    b.wire.shutdown()


# -- the grant caps, call for call and frame for frame ----------------------------------------
_maybe = st.one_of(st.none(), st.none(), st.integers(0, 20_000_000), st.integers(0, 2**39))
_limits = st.builds(
    Limits,
    max_grant=st.integers(1, 65_535).map(lambda mj: mj * QUANTUM_UJ),
    max_node_level=st.one_of(st.none(), st.none(), st.integers(0, level_room(65_535_000))),
    max_total=_maybe,
    rate_uj_per_s=_maybe,
)
_policies = st.one_of(
    st.none(),
    st.builds(TopUp, target=st.integers(0, 20_000_000), minimum=st.integers(0, 5_000_000)),
)
_cap_steps = st.lists(
    st.one_of(
        st.tuples(st.just("wait"), st.integers(0, 3_000_000)),
        st.tuples(
            st.just("cap"),
            st.one_of(st.integers(-10, 70_000_000), st.integers(0, 2**41)),
            st.one_of(
                st.none(),
                st.integers(0, 10_000_000),
                st.integers(0, LEVEL_MAX_MJ * QUANTUM_UJ),
            ),
            st.one_of(st.integers(-5_000_000, 100_000_000), st.integers(0, 2**40)),
            st.integers(0, 3_000_000),
        ),
        st.tuples(st.just("wanted"), st.integers(0, LEVEL_MAX_MJ * QUANTUM_UJ)),
    ),
    max_size=40,
)


@settings(max_examples=300, deadline=None)
@given(_limits, _policies, _cap_steps)
def test_the_c_grant_caps_size_every_grant_as_python_does(
    limits: Limits, policy: TopUp | None, steps: list[tuple[Any, ...]]
) -> None:
    """``capped_grant`` with the rate limiter's tokens, and ``TopUp.wanted``, call for call: the
    same tokens at each look (refilled, taken by each grant sized), the same cap for any
    wanted amount, level (or none), budget and total granted."""
    py, c = PythonGrantCaps(limits, policy), CompiledGrantCaps(library().module, limits, policy)
    now = 0
    for step in steps:
        if step[0] == "wait":
            now += step[1]
        elif step[0] == "wanted":
            if policy is not None:
                assert c.wanted(step[1]) == py.wanted(step[1]), step
        else:
            tokens = py.available(now)
            assert c.available(now) == tokens, step
            amount = py.cap(step[1], step[2], step[3], step[4], tokens)
            assert c.cap(step[1], step[2], step[3], step[4], tokens) == amount, step
            event("capped to 0" if amount == 0 else "a grant")
            py.take(amount)
            c.take(amount)


def _answer_open(b: _Bench, node: int) -> None:
    """The node answers an open INTENTION: ACK, then COMMITTED."""
    s = b.service.core.session(node)
    if s.phase.name == "WAIT_ACK":
        b.feed(Ack(node, s.tx & 0xFFFF))
        b.feed(Committed(node, s.tx & 0xFFFF))


_top_up_steps = st.lists(
    st.one_of(
        st.tuples(st.just("telemetry"), _node, st.integers(0, 8_000), st.just(0), st.just(0)),
        st.tuples(st.just("answer"), _node),
        st.tuples(st.just("grant"), _node, st.integers(1, 3_000)),
        st.tuples(st.just("wait"), st.sampled_from([1_000, 100_000, 1_000_000])),
    ),
    max_size=25,
)


@settings(max_examples=60, deadline=None)
@given(_limits, st.builds(TopUp, target=st.integers(1_000, 8_000_000)), _top_up_steps)
def test_the_c_core_grants_as_the_python_core(
    limits: Limits, top_up: TopUp, steps: list[tuple[Any, ...]]
) -> None:
    """With a top-up policy and limits, frame for frame: the same INTENTIONs (sized by the caps
    in C on the C core), the same refusals of one-shot grants, books and status."""
    ref, c = _bench("python", None, limits, top_up, False), _bench("c", None, limits, top_up)
    py = _bench("python", None, limits, top_up)
    assert c.service.desk.caps.implementation == "c"
    for b in (ref, py, c):
        b.feed(Telemetry(3, 0))
        b.feed(Telemetry(5, 0))
    for step in steps:
        for b in (ref, py, c):
            if step[0] == "answer":
                _answer_open(b, step[1])
            else:
                _step(b, step)
        assert c.snapshot() == ref.snapshot() == py.snapshot(), step
    intentions = sum(ident >> 8 & 0xF == Intention.TYPE for ident, _ in c.wire.sent)
    event(f"INTENTIONs sent: {min(intentions, 3)}+")
    for b in (ref, py, c):
        b.wire.shutdown()


def test_the_c_core_sizes_grants_without_pythons_caps(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the C core the grant desk sizes a top-up and a one-shot grant in C: Python's
    ``capped_grant`` and ``RateLimiter`` are never called."""
    monkeypatch.setattr(policy_module, "capped_grant", _no_fallback)
    monkeypatch.setattr(policy_module.RateLimiter, "available", _no_fallback)
    monkeypatch.setattr(PythonGrantCaps, "cap", _no_fallback)
    b = _bench("c", None, Limits(rate_uj_per_s=5_000_000), TopUp(3_000_000))
    b.feed(Telemetry(3, 1_000))  # 2 J short: a top-up
    assert b.service.core.session(3).reserved == 2_000_000
    _answer_open(b, 3)
    replies: list[dict[str, Any]] = []
    b.service.request_grant(5, 1_000_000, replies.append)
    b.feed(Telemetry(5, 3_000))  # at the target: the one-shot grant only
    assert b.service.core.session(5).reserved == 1_000_000 and not replies
    b.wire.shutdown()


# -- the held JOINs, frame for frame ----------------------------------------------------------
_join_steps = st.lists(
    st.one_of(
        st.tuples(st.just("join"), _node, st.integers(1, 3)),
        st.tuples(
            st.just("telemetry"),
            _node,
            st.integers(0, 3_000),
            st.sampled_from([0, Telemetry.JOINING]),
            st.just(0),
        ),
        st.tuples(st.just("grant"), _node, st.integers(1, 2_000)),
        st.tuples(st.just("answer"), _node),
        st.tuples(
            st.just("wait"), st.sampled_from([1_000, JOIN_HOLD_US - 1_000, JOIN_HOLD_US + 1])
        ),
    ),
    max_size=30,
)


_JOINING = Telemetry.JOINING
_HELD = JOIN_HOLD_US + 1


@settings(max_examples=200, deadline=None)
@given(_join_steps)
@example(  # a JOIN after the one confirmed cancels its admission
    [("join", 3, 1), ("telemetry", 3, 0, _JOINING, 0), ("join", 3, 2), ("wait", _HELD)]
)
@example(  # admitted, then the node shows its books: the same JOIN again is a replay
    [
        ("join", 3, 1),
        ("telemetry", 3, 0, _JOINING, 0),
        ("wait", _HELD),
        ("telemetry", 3, 0, 0, 0),
        ("join", 3, 1),
        ("telemetry", 3, 0, 0, 0),
    ]
)
def test_the_c_frame_path_holds_joins_as_the_python_path(steps: list[tuple[Any, ...]]) -> None:
    """JOINs held in C as in Python, frame for frame: confirmed by a TELEMETRY without books
    and admitted after the hold (the same ADMIT, the same write-off), refused by one with books
    (the same intrusions in the same words), a copy of the JOIN just admitted counted as
    re-sent; the same books and status. The C run took every JOIN in C."""
    ref, py, c = _bench("python", path=False), _bench("python"), _bench("c")
    for b in (ref, py, c):
        b.feed(Telemetry(3, 0))
        b.feed(Telemetry(5, 0))
    for step in steps:
        for b in (ref, py, c):
            if step[0] == "join":
                b.feed(Join(step[1], step[2]))
            elif step[0] == "answer":
                _answer_open(b, step[1])
            else:
                _step(b, step)
        assert c.snapshot() == ref.snapshot() == py.snapshot(), step
        _due_are_the_waiting(ref, c, step)
    assert [r["kind"] for r in c.service.intrusions.recent] == [
        r["kind"] for r in ref.service.intrusions.recent
    ]
    status = c.service.status()
    admitted = sum(n["admitted"] for n in status["nodes"].values())
    event(f"admitted: {min(admitted, 2)}+, intrusions: {min(status['intrusions'], 2)}+")
    for b in (ref, py, c):
        b.wire.shutdown()


def _due_are_the_waiting(ref: _Bench, c: _Bench, step: tuple[Any, ...]) -> None:
    """The nodes each side looks at every loop pass (``due``) are the nodes whose confirmed
    JOIN waits for its hold, not every node that ever joined: exactly in Python; in C a JOIN
    its frame path held may leave a node there until its next TELEMETRY, whose report then
    sets it right."""
    waiting = {n for n, h in ref.service.joins.nodes.items() if h.admitting is not None}
    assert ref.service.joins.due == waiting, step
    joins = c.service.joins
    in_c = {n for n in (3, 5) if joins._rec(n).has_admitting}
    assert in_c == waiting and in_c <= joins.due, step
    if step[0] == "telemetry":
        assert (step[1] in joins.due) == (step[1] in in_c), step


def test_on_the_c_frame_path_a_join_takes_no_python_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A JOIN is held in C in the call that decodes it, and the TELEMETRY that confirms it
    is taken there too: neither Python's ``JoinHold`` nor the entries to C's for frames decoded
    in Python are called; the JOIN is admitted after the hold and counted among the frames
    the C path took."""
    b = _bench("c")
    for table in (JoinHold, type(b.service.joins)):
        monkeypatch.setattr(table, "on_join", _no_fallback)
        monkeypatch.setattr(table, "on_telemetry", _no_fallback)
    b.feed(Join(3, 7))
    b.feed(Telemetry(3, 0, Telemetry.JOINING))
    assert b.service.frames_in_c == 2 and b.service.joins.holding(3)
    b.now[0] += JOIN_HOLD_US
    b.loop.poll(0)
    assert b.service.status()["nodes"]["3"]["admitted"] == 1
    b.wire.shutdown()


def test_a_new_service_over_the_same_c_core_gets_tables_of_its_own() -> None:
    """The tables in C are made anew for each service built over a core: a JOIN the second
    service's frame path holds is admitted by the second service, with nothing left over from
    the first one's."""
    core = compiled_core([3, 5], 10_000_000, timing=T)
    first = build_service(core, ServiceConfig(lost_after_us=LOST_AFTER_US), 0)
    first.on_message(Join(3, 1), 0)  # held by the first service's table
    b = _bench("c")
    b.service = build_service(core, ServiceConfig(lost_after_us=LOST_AFTER_US), 0)
    b.loop = BusRuntime(
        b.wire,
        b.service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        frame_path=b.service.frame_path(),
        counters=b.service.bus_counters,
        clock=lambda: b.now[0],
    )
    assert not b.service.joins.holding(3)
    b.feed(Join(3, 2))
    b.feed(Telemetry(3, 0, Telemetry.JOINING))
    b.now[0] += JOIN_HOLD_US
    b.loop.poll(0)
    assert b.service.status()["nodes"]["3"]["admitted"] == 1
    assert first.status()["nodes"]["3"]["admitted"] == 0 and b.service.frames_in_c == 2
    b.wire.shutdown()
