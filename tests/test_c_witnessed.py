"""The C client under the witnessed rules (``cfg.rules = CANERGY_RULES_WITNESSED``) is
``canergy.core.witnessed.CLIENT``: every table case of tests/test_witnessed.py, every ignored
and refused cell, run on the C struct with the same state, frames, notes and persist; the NV
record carries the pending draw; a hardened client refuses a record holding one. The client's
cells, a node's older copy and the side-by-side machine run again on the build with the witnessed
rules alone (``CANERGY_RULES_WITNESSED_ONLY``, the node port's), which refuses the hardened
rules at start."""

from __future__ import annotations

import struct
import subprocess
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import initialize, rule
from support import c_session, client_cases
from support.c_binding import (
    ERR_AMOUNT,
    ERR_PHASE,
    ERR_RECORD,
    EV_ADMITTED,
    EV_RELEASED,
    FIRMWARE,
    FLAG_CREDITED_UNKNOWN,
    FLAG_PENDING_DRAW,
    OK,
    PHASES,
    RULES,
    SLOT,
    SUPERVISOR_SLOT,
    CClient,
    ClientConfig,
    CNodeState,
    CSupervisor,
    NodeConfig,
    Out,
    SessionTiming,
    SupervisorConfig,
    SupervisorOut,
    c_view,
    cbuf,
    compiled_core,
    events_of,
    frames_of,
    library,
    make,
    out_frames,
    ref,
    rx,
)
from support.c_session import same
from support.cells import Case, params
from support.mem_nv import MemNv, write_slot
from support.side_by_side import BOOKS as SIDE_BOOKS
from support.side_by_side import SETTINGS as SIDE_SETTINGS
from support.side_by_side import TIMING as SIDE_TIMING
from support.side_by_side import SideBySide
from test_c_session import sessions, timings, wire_near
from test_witnessed import (
    BOOKED_AT_10,
    CLIENT_CASES,
    CLIENT_IGNORED,
    CLIENT_REFUSED,
    CLIENT_STATES,
    DRAWING,
    FRESH,
    RC_AT_2_32,
    RESUMED,
    S_OPEN,
    SCENE,
    ST,
    SUP_CASES,
    SUP_EVENTS,
    SUP_IGNORED,
    SUP_REFUSED,
    SUP_STATES,
    T,
    admitted_node_answers_a_sync,
    answers_lost_then_stale_admits,
    late_resume_found_behind_then_the_first_image,
    resume,
    resume_after_a_lost_sync_answer,
    s8_supervisor,
    stale_admits_end_quiet,
    stale_sync_after_taken_counts_and_a_begin,
    stale_sync_taken_then_supervisor_image,
    unknown_rc_supervisor,
    window_supervisor,
)
from test_witnessed import _exchange as _exchange_py

from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.core import Client, Send, Supervisor
from canergy.core import witnessed as W
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import (
    Begin,
    BooksLost,
    CommandTimeout,
    GiveBack,
    PowerLoss,
    ReturnTimeout,
    Spend,
)
from canergy.core.state import ClientState, Phase, Session, SupervisorState
from canergy.core.timing import Timing
from canergy.live.supervisor.state_file import load_state, save_state
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    SYNC_CONFIRMED,
    Admit,
    Debit,
    Direction,
    Join,
    ReturnAck,
    Telemetry,
)
from firmware_model.nvstore import pack_record

CODEC = Codec()
TABLE = W.CLIENT
BUILDS = ("", "witnessed_only")
"""The library with both rule sets (the tests' default) and with the witnessed rules alone."""


def run_c(
    start: ClientState, event: object, now: int, build: str = ""
) -> tuple[CClient, Out | int]:
    """The witnessed C client (of ``build``) in ``start``, after ``event`` at ``now``."""
    c = CClient(start.node, timing=T, state=start, lib=library(build), rules="witnessed")
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


def assert_same_step(start: ClientState, event: object, now: int, build: str = "") -> Out:
    """The C client and the Python witnessed table agree on this step in every respect."""
    step = TABLE.step(T, start, event, now)
    c, out = run_c(start, event, now, build)
    assert isinstance(out, Out), f"C refused with {out}"
    assert c.view() == c_view(step.client)
    assert out_frames(out) == frames_of(CODEC, step.actions)
    assert out.events & ~(EV_ADMITTED | EV_RELEASED) == events_of(step.actions)
    starts = (Phase.JOINING, Phase.RESUMING, Phase.SYNCING)
    admitted = start.phase in starts and step.client.phase not in starts
    assert bool(out.events & EV_ADMITTED) == admitted
    assert bool(out.events & EV_RELEASED) == (step.client.spent > start.spent)
    record_changed = TABLE.persistent(start) != TABLE.persistent(step.client)
    if not isinstance(event, BooksLost):  # C never writes a blank record (client.h)
        assert bool(out.persist) == record_changed
    return out


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("case", params(CLIENT_CASES))
def test_cell(case: Case, build: str) -> None:
    assert isinstance(case.start, ClientState)
    assert_same_step(case.start, case.event, case.now, build)
    c, out = run_c(case.start, case.event, case.now, build)
    assert isinstance(out, Out)
    assert c.view() == c_view(case.end)  # type: ignore[arg-type]
    assert out_frames(out) == frames_of(CODEC, case.actions)


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("cell", sorted(CLIENT_IGNORED, key=str), ids=str)
def test_ignored(cell: tuple[Phase, type], build: str) -> None:
    start, event = CLIENT_STATES[cell[0]], client_cases.EVENTS[cell[1]]
    c, out = run_c(start, event, 10**9, build)
    assert isinstance(out, Out)
    assert c.view() == c_view(start) and out_frames(out) == [] and not out.persist
    assert out.events == 0


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("cell", sorted(CLIENT_REFUSED, key=str), ids=str)
def test_refused(cell: tuple[Phase, type], build: str) -> None:
    start, event = CLIENT_STATES[cell[0]], client_cases.EVENTS[cell[1]]
    c, out = run_c(start, event, 0, build)
    assert out == ERR_PHASE and c.view() == c_view(start)


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("state", [DRAWING, client_cases.RETURNING, RESUMED, FRESH], ids=str)
def test_one_debit_at_a_time_and_none_before_the_confirmation(
    state: ClientState, build: str
) -> None:
    c = CClient(state.node, timing=T, state=state, lib=library(build), rules="witnessed")
    assert c.lib.canergy_client_can_draw(c.c) == TABLE.can_spend(state)
    assert c.can_give_back() == TABLE.can_give_back(state)


@pytest.mark.parametrize(
    "event", [Spend(0), Spend(1500), Spend(65_536_000), GiveBack(0), GiveBack(11_000)], ids=str
)
@pytest.mark.parametrize("build", BUILDS)
def test_draws_and_returns_guarded_by_energy(event: object, build: str) -> None:
    c, out = run_c(FRESH, event, 0, build)
    assert out == ERR_AMOUNT and c.view() == c_view(FRESH)


@pytest.mark.parametrize("build", BUILDS)
def test_spend_is_refused_under_the_witnessed_rules(build: str) -> None:
    """Energy reaches the actuator only through an acknowledged draw."""
    c = CClient(FRESH.node, timing=T, state=FRESH, lib=library(build), rules="witnessed")
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
    assert out_frames(c.out) == [CODEC.encode(Debit(FRESH.node, 0, Debit.DRAW, 1, 2))]
    assert bytes(c.out.nv_image)[6 + 29] & FLAG_PENDING_DRAW
    image = bytearray()
    write_slot(image, c.out.nv_slot, bytes(c.out.nv_image))
    again = _booted(bytes(image), "witnessed")
    resume = Debit(FRESH.node, 0x77, Debit.START | Debit.DRAW, 1, 2)
    assert out_frames(again.out) == [CODEC.encode(resume)]
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


@pytest.mark.parametrize("ahead", [0, 1, 2, 5])
@pytest.mark.parametrize("window", [1, 64, 0x7FFF])
def test_a_session_begins_only_within_the_window(ahead: int, window: int) -> None:
    """k = tx + 1 <= W + B: at the window's end both begin, one beyond both refuse."""
    s = Session(1, tx=1000 + window - 2 + ahead, witness=1000)
    same(s, replace(ST, window=window), Begin(1000), 0, table=W.SUPERVISOR)


def test_the_compiled_supervisor_refuses_beyond_the_window_in_the_python_words() -> None:
    t = replace(ST, window=2)
    state = SupervisorState(J, J, 0, (Session(2, tx=7, witness=5),))
    errors = []
    for core in (Supervisor, compiled_core):
        sup = core([2], J, timing=t, state=state, variant="witnessed")
        with pytest.raises(LocalProtocolError) as err:
            sup.begin(2, 1000, 0)
        errors.append(str(err.value))
    assert errors[0] == errors[1] and "beyond the window" in errors[0]


@pytest.mark.parametrize("without", [(), (3,)])
def test_no_grant_before_every_node_has_confirmed_its_books_after_a_start(
    without: tuple[int, ...],
) -> None:
    """A start: node 2 answers its SYNC, node 3 does not; both cores refuse to grant even to
    node 2 (saying they wait for node 3), unless the operator started without node 3, and
    neither ever grants to node 3 before its answer. Node 2's books hold 5 mJ more than the
    restored record: Us goes below zero, and a grant beyond it is refused."""
    t = replace(ST, window=4)
    for core in (Supervisor, compiled_core):
        sup = core([2, 3], 2000, timing=t, variant="witnessed", start_without=without)
        sup.power_loss(0, nonce=0x1234)
        assert sup.unconfirmed() == tuple(n for n in (2, 3) if n not in without)
        sync = [a.message for a in sup.handle_timer(0) if isinstance(a, Send)]
        assert [m.node for m in sync] == [2, 3] and {m.nonce for m in sync} == {0x1234}
        sup.receive(Debit.books(2, 0x1234, 7), 1)  # Rc 7 mJ, Gs 0: Us 2 mJ -> -5 mJ
        answer = sup.receive(Debit.counts(2, 0x1234, 0, 9), 2)
        admit = [a.message for a in answer if isinstance(a, Send)]
        assert admit == [Admit(2, 0x1234 ^ SYNC_CONFIRMED, 9, 1)]
        assert sup.usable == -5000 and sup.session(2).witness == 9
        assert sup.unconfirmed() == tuple(n for n in (3,) if n not in without)
        with pytest.raises(
            LocalProtocolError, match="waiting for node" if not without else "usable"
        ):
            sup.begin(2, 1000, 3)
        sup.inject(6000)
        if without:
            sup.begin(2, 1000, 3)  # within the window W + B = 13: k = 10
        else:
            with pytest.raises(LocalProtocolError, match="waiting for node"):
                sup.begin(2, 1000, 3)
        with pytest.raises(LocalProtocolError):
            sup.begin(3, 1000, 3)  # its own session still waits for its books


def test_the_supervisor_record_version_5_round_trips_a_debt_and_refuses_version_4() -> None:
    """Us below zero, a SYNC's counts answered (bit 16 of the nonce) and the last JOIN admitted
    (its nonce, the k and C of its ADMIT) come back from the image; a start's waiting phase is
    stored as IDLE (every start is one); the same image marked version 4 is refused as another
    version (CANERGY_ERR_RECORD), not started over."""
    lib = library()
    cfg = SupervisorConfig(id_base=DEFAULT_ID_BASE, timing=SessionTiming(50_000, 3, 1, 0))
    nodes = cbuf(bytes([2]))
    sup = CSupervisor()
    assert lib.canergy_supervisor_init(ref(sup), ref(cfg), nodes, 1, 1000) == 0
    sup.usable_uj = -4000
    sup.sessions[0].phase, sup.sessions[0].resume_nonce = int(Phase.SYNC_BOOKS), 0x1ABCD
    sup.sessions[0].tx, sup.sessions[0].returns_credited = 70_000, 70_002
    sup.sessions[0].join_nonce, sup.sessions[0].join_tx = 0xBEEF, 65_540
    sup.sessions[0].join_seq = 70_001
    image = cbuf(2 * SUPERVISOR_SLOT)
    lib.canergy_supervisor_image(ref(sup), 1, image)
    assert bytes(image)[4] == 5

    def load(raw: bytes) -> tuple[int, CSupervisor]:
        back, counter, slot = CSupervisor(), library().new("uint32_t *"), library().new("uint8_t *")
        buf = cbuf(raw, len(raw))
        rc = lib.canergy_supervisor_load(
            ref(back), ref(cfg), nodes, 1, 0, buf, len(raw),
            ref(counter), ref(slot),
        )  # fmt: skip
        return rc, back

    rc, back = load(bytes(image))
    assert rc == 1 and back.usable_uj == -4000 and back.sessions[0].resume_nonce == 0x1ABCD
    joined = back.sessions[0].join_nonce, back.sessions[0].join_tx, back.sessions[0].join_seq
    assert joined == (0xBEEF, 65_540, 70_001)
    assert back.sessions[0].phase == int(Phase.SYNCING)  # loaded IDLE, then a start
    used = 40 + 56  # header, one session, CRC
    old = bytearray(bytes(image))
    old[4] = 4
    old[used - 4 : used] = struct.pack("<I", zlib.crc32(bytes(old[0 : used - 4])))
    assert load(bytes(old))[0] == ERR_RECORD


def test_the_hardened_session_ignores_a_debit() -> None:
    """DEBIT is taken only with the session's rules set to witnessed."""
    for event in (resume(4), Debit(3, 0, Debit.DRAW, 5, 2)):
        same(S_OPEN, ST, event, 0)


@st.composite
def witnessed_sessions(draw: Any) -> Session:
    """Records with a last RESUME answered near the session's count, as the rules leave it
    (Python's numbers are unbounded, C's modulo 2**32: they agree within 2**15 of each other),
    with counters in the proof's domain, below 2**30, where a start's void is held (``capped``:
    beyond it Python's cap and C's 32-bit wrap part, and no loader takes such a record)."""
    s = draw(sessions())
    top = COUNTER_BOUND - 1
    s = replace(s, tx=min(s.tx, top), returns_credited=min(s.returns_credited, top))
    near = st.integers(-3, 2).map(lambda d: s.returns_credited + d)
    far = st.sampled_from([-0x10000, 0x10000, 0x8000]).map(lambda d: s.returns_credited + d)
    return replace(
        s,
        resume_nonce=draw(st.sampled_from([0, 9, 9 | 1 << 16]) | st.integers(0, 0x1FFFF)),
        resume_from=draw(near | far),
        resume_to=draw(st.just(s.returns_credited) | st.just(0) | near),
    )


@settings(max_examples=400)
@given(witnessed_sessions(), timings, st.data())
def test_every_debit_cell_on_drawn_records(s: Session, t: Timing, data: st.DataObject) -> None:
    """Draws, resumes and a SYNC's counts near the session's counters (a repeat of the last
    start answered included, counts under its nonce or another) give in C the record, the frame,
    the budget, the resolution of witnessed.py."""
    seq = data.draw(wire_near(s.returns_credited))
    amount = data.draw(st.sampled_from([0, 1, 0xFFFF]) | st.integers(0, 0xFFFF))
    last = s.resume_nonce & 0xFFFF
    nonce = data.draw(st.just(last) | st.integers(0, 0xFFFF))
    repeat = (s.resume_from & 0xFFFF) if data.draw(st.booleans()) else seq
    for m in (
        Debit(s.node, 0, Debit.DRAW, seq, max(amount, 1)),
        Debit(s.node, nonce, Debit.START, seq, amount),
        Debit(s.node, nonce, Debit.START | Debit.DRAW, seq, amount),
        Debit(s.node, last, Debit.START, repeat, amount),
        Debit.counts(s.node, nonce, seq, amount),
        Debit.counts(s.node, last, repeat, amount),
        Join(s.node, nonce),
    ):
        same(s, t, m, data.draw(st.integers(0, 10**9)), table=W.SUPERVISOR)


@pytest.mark.parametrize("phase", [Phase.IDLE, Phase.WAIT_ACK])
@pytest.mark.parametrize("ltx", [3, 4, 70, 0x8003, 0xFFF0])
def test_counts_repeated_from_a_later_start_move_tx_up_in_c_as_in_python(
    phase: Phase, ltx: int
) -> None:
    """The last answered counts again (same nonce and q, C unchanged): C writes off what is
    open and moves tx (not W) up to an ltx above it, as witnessed.py (below or at tx and
    nothing open: the same answer)."""
    open_ = phase is not Phase.IDLE
    s = Session(
        1,
        phase=phase,
        tx=4,
        reserved=2000 if open_ else 0,
        delivered=3000,
        returns_credited=5,
        resume_nonce=9 | 1 << 16,
        resume_from=4,
        resume_to=5,
        witness=3,
        deadline=0 if open_ else None,
    )
    same(s, ST, Debit.counts(1, 9, 4, ltx), 0, table=W.SUPERVISOR)


@pytest.mark.parametrize("repeat", [True, False])
@pytest.mark.parametrize("tx", [COUNTER_BOUND - 30_000, COUNTER_BOUND - 5])
def test_counts_move_tx_no_further_than_the_bound_in_c_as_in_python(repeat: bool, tx: int) -> None:
    """Counts carry a 16-bit ltx, widened against tx: up to 32,767 ahead. Repeated without a
    key (the last answered again, or a RESUME's under its nonce) they walked tx (and W, when
    they moved it) past COUNTER_BOUND (a record no loader takes), C's int32 W negative at 2^31
    and its tx back to 0 at 2^32 (begins allowed again where Python refuses them). A counter
    moved by a start stays below the bound (``common.capped``), in both cores."""
    s = Session(
        1, tx=tx, witness=tx, delivered=3000, returns_credited=5,
        resume_nonce=9 | 1 << 16 if repeat else 9, resume_from=4, resume_to=5,
    )  # fmt: skip
    counts = Debit.counts(1, 9, 4, (tx + 0x7FFF) & 0xFFFF)
    w = tx  # counts outside a start move no W (the repeat's), nor found behind (q 4, C 5)
    after = W.SUPERVISOR.step(ST, s, counts, 0).session
    assert (after.tx, after.witness) == (COUNTER_BOUND - 1, w)
    same(s, ST, counts, 0, table=W.SUPERVISOR)
    again = W.SUPERVISOR.step(ST, after, counts, 0).session
    assert (again.tx, again.witness) == (COUNTER_BOUND - 1, w)


@pytest.mark.parametrize("phase", [Phase.IDLE, Phase.WAIT_ACK])
@pytest.mark.parametrize("ltx", [0x0000, 0x5555, 60_000, 0xAAAA])
def test_an_earlier_starts_counts_move_no_tx_in_c_as_in_python(phase: Phase, ltx: int) -> None:
    """Counts outside a start under a nonce that is not the last start's (a replay of an
    earlier SYNC's, which verifies with a key for the whole epoch) are ignored in C as in
    witnessed.py: their ltx widened against a tx moved on by more than 2^15 moved tx and W up
    to 2^15 - 1 ahead, wrote off what was open and found the node behind."""
    open_ = phase is not Phase.IDLE
    s = Session(
        1, phase=phase, tx=100_000, reserved=2000 if open_ else 0, delivered=9000,
        returns_credited=50, resume_nonce=0x0707 | 1 << 16, resume_from=49, resume_to=50,
        witness=100_000, deadline=0 if open_ else None,
    )  # fmt: skip
    replayed = Debit.counts(1, 0x0303, 10, ltx)
    assert W.SUPERVISOR.step(ST, s, replayed, 0).session is s
    same(s, ST, replayed, 0, table=W.SUPERVISOR)
    same(
        replace(s, resume_to=0, resume_nonce=0x0303 | 1 << 16), ST, replayed, 0, table=W.SUPERVISOR
    )


# -- issue 40, item 6: a C node restored from an older NV copy ---------------------------------

J = 1_000_000
NODE_ID = 2
SCENARIO = Timing(
    response_timeout_us=10_000, retries=2, command_timeout_us=20_000, return_retry_us=20_000
)


class _Node:
    """The C node as its port drives it (canergy_node_*), NV image kept in bytes."""

    def __init__(self, rules: str, raw: bytearray, nonce: int, now: int, build: str = "") -> None:
        self.lib = lib = library(build)
        self.raw = raw
        cfg = NodeConfig(
            ClientConfig(
                DEFAULT_ID_BASE,
                SCENARIO.command_timeout_us,
                SCENARIO.return_retry_us,
                NODE_ID,
                RULES[rules],
                lib=lib,
            ),
            1_000_000,
            0,
            0xFFFF_FFFF,  # keep all: no return policy
            lib=lib,
        )
        self.n, self.out, self.used = CNodeState(lib=lib), Out(lib=lib), 0
        buf = cbuf(bytes(raw), max(len(raw), 1), lib=lib)
        self.lib.canergy_node_start(self.n, ref(cfg), buf, len(raw), nonce, now, self.out)
        self.sent = self._done()

    def _done(self) -> list[tuple[int, bytes]]:
        if self.out.persist:
            write_slot(self.raw, self.out.nv_slot, bytes(self.out.nv_image))
        return [f for f in out_frames(self.out) if f[0] >> 8 & 0xF != 0xD]  # no TELEMETRY

    def frame(self, arbitration_id: int, data: bytes, now: int) -> list[tuple[int, bytes]]:
        frame, buf = rx(arbitration_id, data, lib=self.lib)
        self.lib.canergy_node_on_frame(self.n, ref(frame), now, self.out)
        del buf
        return self._done()

    def tick(self, wanted: int, now: int) -> list[tuple[int, bytes]]:
        self.used += self.lib.canergy_node_draw(self.n, wanted, now, self.out)
        return self._done()

    def held(self) -> int:
        """What the node holds for its actuator: usable, released, a draw still pending."""
        rec = self.n.client.rec
        pending = rec.return_pending_uj if rec.flags & FLAG_PENDING_DRAW else 0
        return rec.usable_uj + self.n.released_uj + pending


@pytest.mark.parametrize(
    ("rules", "build"), [("hardened", ""), ("witnessed", ""), ("witnessed", "witnessed_only")]
)
def test_the_c_nodes_telemetry_says_its_rules(rules: str, build: str) -> None:
    """Every TELEMETRY carries WITNESSED exactly under the witnessed rules (review rv3, F3: a
    supervisor with other rules then grants the node nothing)."""
    node = _Node(rules, bytearray(), 0x55, 0, build)
    for now in (0, 1_000_000, 2_000_000):  # joining, then each period
        node.lib.canergy_node_poll(node.n, now, node.out)
        (frame,) = [f for f in out_frames(node.out) if f[0] >> 8 & 0xF == 0xD]
        msg = CODEC.decode(*frame, direction=Direction.TO_SUPERVISOR)
        assert isinstance(msg, Telemetry) and msg.flags & Telemetry.JOINING
        assert bool(msg.flags & Telemetry.WITNESSED) == (rules == "witnessed")


class _CSup:
    """The C supervisor (canergy_supervisor_*) for the node, its rules set by timing.rules."""

    def __init__(self, rules: str, initial: int, build: str = "") -> None:
        self.lib = library(build)
        self.s, self.out = CSupervisor(lib=self.lib), SupervisorOut(lib=self.lib)
        timing = SessionTiming(
            SCENARIO.response_timeout_us, SCENARIO.retries, RULES[rules], lib=self.lib
        )
        cfg = SupervisorConfig(DEFAULT_ID_BASE, timing, lib=self.lib)
        nodes = cbuf(bytes([NODE_ID]), lib=self.lib)
        assert self.lib.canergy_supervisor_init(self.s, ref(cfg), nodes, 1, initial) == OK

    def _sent(self) -> list[tuple[int, bytes]]:
        frames = list(self.out.frames)[0 : self.out.frame_count]
        return [(f.id, bytes(f.data[0 : f.dlc])) for f in frames]

    def grant(self, amount: int, now: int) -> list[tuple[int, bytes]]:
        assert self.lib.canergy_supervisor_begin(self.s, NODE_ID, amount, now, self.out) == OK
        return self._sent()

    def frame(self, arbitration_id: int, data: bytes, now: int) -> list[tuple[int, bytes]]:
        frame, buf = rx(arbitration_id, data, lib=self.lib)
        self.lib.canergy_supervisor_on_frame(self.s, ref(frame), now, self.out)
        del buf
        sent = self._sent()
        for e in list(self.out.events)[0 : self.out.event_count]:
            if e.flags & 0x01:  # acknowledged: commit it
                self.lib.canergy_supervisor_decide(self.s, NODE_ID, True, now, self.out)
                sent += self._sent()
        return sent

    def taken(self) -> int:
        """What the books count as the node's: delivered minus returned."""
        s = self.s.sessions[0]
        return int(s.delivered_uj - s.returned_uj)


def _exchange(sent: list[tuple[int, bytes]], node: _Node, sup: _CSup, now: int) -> None:
    queue = list(sent)
    while queue:
        arbitration_id, data = queue.pop(0)
        to_node = not arbitration_id >> 8 & 0x8
        queue += (
            node.frame(arbitration_id, data, now)
            if to_node
            else sup.frame(arbitration_id, data, now)
        )


@pytest.mark.parametrize(
    ("rules", "build"), [("hardened", ""), ("witnessed", ""), ("witnessed", "witnessed_only")]
)
def test_a_c_node_restored_from_an_older_copy_creates_no_energy(rules: str, build: str) -> None:
    """2 J granted by the C supervisor, the C node's actuator uses 1.5 J, its NV is put back to
    the copy written after the grant and it starts from it: under the hardened rules the node
    uses the 1.5 J again (+1.5 J); under the witnessed rules its RESUME is found behind and
    everything the actuator used, plus what the node still holds, is at most what the books
    count as taken: 0 J created."""
    raw = bytearray()
    node, sup = _Node(rules, raw, 0x1111, 0, build), _CSup(rules, 2 * J, build)
    _exchange(node.sent, node, sup, 0)  # the JOIN of a node without books
    _exchange(sup.grant(2 * J, 1), node, sup, 1)
    assert node.held() == 2 * J
    copy = bytearray(raw)  # the NV image right after the commit
    now = 10
    while node.used < 1_500_000:
        _exchange(node.tick(500_000, now), node, sup, now)
        now += 10
    assert node.used == 1_500_000
    before = node.used
    node = _Node(rules, copy, 0x2222, now, build)  # restored from the older copy, started again
    node.used = before
    _exchange(node.sent, node, sup, now)
    for _ in range(8):
        now += 10
        _exchange(node.tick(500_000, now), node, sup, now)
    created = node.used + node.held() - sup.taken()
    if rules == "hardened":
        assert created == 1_500_000
    else:
        assert node.n.client.phase == PHASES[Phase.IDLE]
        assert node.n.client.rec.flags & FLAG_CREDITED_UNKNOWN  # found behind: admitted afresh
        assert created <= 0 and node.used == 1_500_000


def test_a_c_node_whose_lives_would_share_a_debit_number_creates_no_energy() -> None:
    """tests/test_witnessed.py's two lives on the C supervisor and C nodes: the books lost while
    DRAW(C + 1) is unacknowledged, the new life JOINs and draws 5 J, the old life's NV image is
    put back. The JOIN's admission voided C + 1, so the old image is found behind (when the
    admission left C + 1 free, the old image was confirmed and this sequence ended 1 J above the
    books)."""
    sup, now = _CSup("witnessed", 20 * J), 0
    node = _Node("witnessed", bytearray(), 0x1111, now)
    _exchange(node.sent, node, sup, now)
    _exchange(sup.grant(10 * J, 1), node, sup, 1)
    node.tick(J, 2)  # DRAW(C + 1) sent, lost
    image = bytearray(node.raw)
    new_life = _Node("witnessed", bytearray(), 0x2222, 3)  # no books: JOIN
    _exchange(new_life.sent, new_life, sup, 3)
    _exchange(sup.grant(5 * J, 4), new_life, sup, 4)
    now = 10
    while new_life.used < 5 * J and now < 1000:
        _exchange(new_life.tick(5 * J - new_life.used, now), new_life, sup, now)
        now += 10
    assert new_life.used == 5 * J
    old = _Node("witnessed", image, 0x3333, now)  # the old life's image, started again
    _exchange(old.sent, old, sup, now)
    assert old.n.client.rec.flags & FLAG_CREDITED_UNKNOWN  # found behind: admitted afresh
    _exchange(sup.grant(J, now + 1), old, sup, now + 1)
    for _ in range(4):
        now += 10
        _exchange(old.tick(J, now), old, sup, now)
    assert old.used + old.held() + new_life.used - sup.taken() <= 0


# -- the Linux ports --------------------------------------------------------------------------


def _port(target: str) -> Path:
    make(target)
    return FIRMWARE / target


@pytest.mark.parametrize("binary", ["canergy-node", "canergy-gateway"])
def test_the_ports_take_rules_and_refuse_others(binary: str, tmp_path: Path) -> None:
    port = _port(f"build/{binary}")
    assert (
        "--rules hardened|witnessed"
        in subprocess.run(
            [str(port), "--help"], capture_output=True, text=True, timeout=10, check=True
        ).stdout
    )
    run = subprocess.run(
        [str(port), "--rules", "trusting", "--node", "1"],
        capture_output=True,
        text=True,
        timeout=10,
        cwd=tmp_path,
    )
    assert run.returncode == 2
    assert run.stderr == (
        f"{binary}: error: argument --rules: invalid choice: 'trusting' "
        "(choose from 'hardened', 'witnessed')\n"
    )


def test_the_c_gateway_refuses_a_file_of_the_older_supervisor_record(tmp_path: Path) -> None:
    """Its supervisor record grew (version 3: the last RESUME answered); a file written before
    is refused by name before the buses open, never taken as a blank file."""
    gateway = _port("build/canergy-gateway")
    head = struct.pack("<IBBBBIQQQ", 0x534E5243, 2, 1, 0, 0, 1, 0, 0, 0)
    session = struct.pack("<BBBBIIIQQ", 2, 0, 0, 0, 9, 4, 0, 0, 0)
    sup = (head + session + struct.pack("<I", zlib.crc32(head + session))).ljust(40 + 32 * 127)
    body = struct.pack("<II", 0x47524E43, 1) + pack_record(ClientState(1, last_tx=5)) + sup
    (tmp_path / "g.nv").write_bytes(body + struct.pack("<I", zlib.crc32(body)))
    argv = [str(gateway), "--node", "1", "--nodes", "2", "-c", "nosuchcan0"]
    argv += ["--upstream-channel", "nosuchcan1", "--nv", "g.nv", "--rules", "witnessed"]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=10, cwd=tmp_path)
    assert run.returncode == 2
    assert run.stderr == (
        "canergy-gateway: error: --nv g.nv: written by an older canergy-gateway (supervisor "
        "record version 2); this one reads version 5 only\n"
    )


@pytest.mark.parametrize("version", [3, 4])
def test_the_c_gateway_refuses_a_file_of_supervisor_record_version_3_or_4(
    tmp_path: Path, version: int
) -> None:
    """Version 5 keeps the last JOIN admitted (12 bytes more per node), version 4 a SYNC's counts
    in the last answer's nonce (bit 16) and Us signed: a file of version 3 or 4 (44 bytes per
    node) is refused by name before the buses open, never taken as blank."""
    gateway = _port("build/canergy-gateway")
    head = struct.pack("<IBBBBIQQQ", 0x534E5243, version, 1, 0, 0, 1, 0, 0, 0)
    session = struct.pack("<BBBBIIIQQIIHxx", 2, 0, 0, 0, 9, 4, 0, 0, 0, 0, 0, 0)
    sup = (head + session + struct.pack("<I", zlib.crc32(head + session))).ljust(40 + 44 * 127)
    body = struct.pack("<II", 0x47524E43, 1) + pack_record(ClientState(1, last_tx=5)) + sup
    (tmp_path / "g.nv").write_bytes(body + struct.pack("<I", zlib.crc32(body)))
    argv = [str(gateway), "--node", "1", "--nodes", "2", "-c", "nosuchcan0"]
    argv += ["--upstream-channel", "nosuchcan1", "--nv", "g.nv", "--rules", "witnessed"]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=10, cwd=tmp_path)
    assert run.returncode == 2
    assert run.stderr == (
        "canergy-gateway: error: --nv g.nv: written by an older canergy-gateway (supervisor "
        f"record version {version}); this one reads version 5 only\n"
    )


# -- side by side: the hypothesis machine of support.side_by_side, under the witnessed rules ----


class WitnessedMemNv(MemNv):
    """firmware_model's store with the witnessed record: flag bit 1 of the record's flags byte
    (what the C client writes) says the pending debit is a draw."""

    FLAGS_AT = 6 + 29  # slot header (magic, counter), then the record's flags byte

    def save(self, c: ClientState) -> None:
        super().save(c)
        if c.pending_draw:
            at = self._newest_slot * SLOT
            slot = bytearray(self.raw[at : at + SLOT])
            slot[self.FLAGS_AT] |= FLAG_PENDING_DRAW
            slot[SLOT - 4 :] = struct.pack("<I", zlib.crc32(bytes(slot[0 : SLOT - 4])))
            self.raw[at : at + SLOT] = slot

    def load(self) -> ClientState | None:
        state = super().load()
        if state is None:
            return None
        flags = self.raw[self._newest_slot * SLOT + self.FLAGS_AT]
        return replace(state, pending_draw=bool(flags & FLAG_PENDING_DRAW))


class WitnessedSideBySide(SideBySide):
    """The Python witnessed client and supervisor and the C client with rules witnessed: every
    start RESUMEs, the actuator draws through DEBIT; same frames, persists, NV bytes, state."""

    def _new_supervisor(self, state: SupervisorState) -> Supervisor:
        """The books agree with the node's record, which it has shown persisted (W = tx)."""
        sessions = tuple(replace(s, witness=s.tx) for s in state.sessions)
        state = replace(state, sessions=sessions)
        return Supervisor([1], state.initial, timing=SIDE_TIMING, state=state, variant="witnessed")

    @initialize(
        initial_mj=st.integers(0, 40_000),
        nonce=st.integers(0, 0xFFFF),
        books=st.none() | SIDE_BOOKS,
    )
    def start(self, initial_mj: int, nonce: int, books: ClientState | None) -> None:
        SideBySide.start(self, initial_mj, nonce, books)

    def _may_begin(self, s: Session) -> bool:
        """Not while a start waits for the books, nor beyond the window."""
        return not self.sup.unconfirmed() and s.tx + 1 <= s.witness + SIDE_TIMING.window

    @rule(nonce=st.integers(0, 0xFFFF))
    def supervisor_start(self, nonce: int) -> None:
        """The supervisor starts again with a fresh nonce: a SYNC the node answers."""
        self.sup.power_loss(self.now, nonce=nonce)

    def _new_client(self) -> CClient:
        return CClient(1, timing=SIDE_TIMING, lib=library(), rules="witnessed")

    def _store(self, raw: bytearray) -> MemNv:
        return WitnessedMemNv(raw)

    def _boot(self, nonce: int) -> None:
        self.py_store = self._store(self.py_raw)
        record = self.py_store.load()
        self.py = Client(1, timing=SIDE_TIMING, state=record or ClientState(1), variant="witnessed")
        if record is not None:
            actions = self.py.power_loss(self.now, nonce=nonce)
        else:
            self.py.power_loss(self.now)
            actions = self.py.books_lost(nonce, self.now)
        fallbacks = self.c.start(bytes(self.c_raw), nonce, self.now)
        assert fallbacks == self.py_store.stats.fallbacks, "NV load differs"
        self._carry_out(actions, self.c.out)

    def _py_spend(self, amount: int) -> list[Any]:
        return self.py.spend(amount, self.now)

    def _c_spend(self, amount: int) -> int:
        return self.c.do_draw(amount, self.now)


TestWitnessedSideBySide = WitnessedSideBySide.TestCase
TestWitnessedSideBySide.settings = SIDE_SETTINGS


class WitnessedOnlySideBySide(WitnessedSideBySide):
    """The same, the C client built with the witnessed rules alone (the node port's build)."""

    def _new_client(self) -> CClient:
        return CClient(1, timing=SIDE_TIMING, lib=library("witnessed_only"), rules="witnessed")


TestWitnessedOnlySideBySide = WitnessedOnlySideBySide.TestCase
TestWitnessedOnlySideBySide.settings = SIDE_SETTINGS


def test_the_witnessed_only_build_refuses_the_hardened_rules_at_start() -> None:
    """A node port built with the witnessed rules alone never runs another set: a client, a
    node or a supervisor configured with the hardened rules is refused at start."""
    lib = library("witnessed_only")
    c = CClient(FRESH.node, timing=T, lib=lib, rules="hardened")
    assert c.start(b"", 0x77, 0) == lib.CANERGY_ERR_ARGUMENT
    node_cfg = NodeConfig(c.config, 1_000_000, 0, 0xFFFF_FFFF, lib=lib)
    n, out = CNodeState(lib=lib), Out(lib=lib)
    buf = cbuf(b"\0", lib=lib)
    assert lib.canergy_node_start(n, node_cfg, buf, 0, 1, 0, out) == lib.CANERGY_ERR_ARGUMENT
    timing = SessionTiming(50_000, 3, RULES["hardened"], lib=lib)
    cfg = SupervisorConfig(DEFAULT_ID_BASE, timing, lib=lib)
    sup = CSupervisor(lib=lib)
    nodes = cbuf(bytes([1]), lib=lib)
    assert lib.canergy_supervisor_init(sup, cfg, nodes, 1, 0) == lib.CANERGY_ERR_ARGUMENT


@pytest.mark.parametrize("seq", [0x12344, COUNTER_END - 4])
@pytest.mark.parametrize("ahead", [1, 2, 0x7FFF])
def test_an_admit_far_from_zero_confirms_or_finds_behind_alike(seq: int, ahead: int) -> None:
    """Q counted from the node's q (not from the blank books a behind node gets)."""
    start = replace(RESUMED, return_seq=seq, last_tx=0x2FFF0)
    admit = Admit(start.node, start.nonce, 0x0005, (seq + ahead) & 0xFFFF)
    assert_same_step(start, admit, 500)


@pytest.mark.parametrize(
    ("rc_mj", "unknown", "floor_mj"),
    [
        (0, False, 1 << 24),  # a known 0: kept as 2^24 mJ, the same 24 bits
        (1 << 32, False, (1 << 32) + (1 << 24)),  # 0 in the C record's u32
        (5, False, 5),
        (0, True, None),  # after a JOIN: no floor
        (7, True, 7),  # found behind again: the floor it kept
    ],
)
def test_a_record_found_behind_keeps_a_floor_its_books_report_in_c_as_in_python(
    rc_mj: int, unknown: bool, floor_mj: int | None
) -> None:
    """A confirmation that finds the books behind keeps the record's Rc as the floor the books
    report; only a record that had none (admitted after a JOIN, no fresh intention since) reports
    Rc unknown. Before, a known Rc of 0 mJ (in C: 0 modulo 2^32) read as unknown, and a
    supervisor started from an older image kept a Gs below what the node had received."""
    start = replace(RESUMED, credited=rc_mj * 1000, credited_unknown=unknown)
    admit = Admit(start.node, start.nonce, start.last_tx & 0xFFFF, (start.return_seq + 2) & 0xFFFF)
    assert_same_step(start, admit, 500)
    behind = TABLE.step(T, start, admit, 500).client
    assert behind.credited_unknown and behind.usable == 0
    sync = Admit(start.node, 0x0123, 0, 0)
    assert_same_step(behind, sync, 600)
    books = TABLE.step(T, behind, sync, 600).actions[0]
    assert isinstance(books, Send) and isinstance(books.message, Debit)
    assert books.message.rc_unknown == (floor_mj is None)
    if floor_mj is not None:
        assert books.message.credited_mj == floor_mj % (1 << 24)


def test_a_record_flagged_with_a_draw_of_nothing_is_no_books() -> None:
    """No client writes the draw flag without a pending amount: such a record is not books."""
    image = bytearray()
    MemNv(image).save(FRESH)
    slot = bytearray(image[0:SLOT])
    slot[WitnessedMemNv.FLAGS_AT] |= FLAG_PENDING_DRAW
    slot[SLOT - 4 :] = struct.pack("<I", zlib.crc32(bytes(slot[0 : SLOT - 4])))
    c = _booted(bytes(slot), "witnessed")
    assert c.state.phase is Phase.JOINING


@pytest.mark.parametrize("core", ["python", "c"])
def test_a_first_resume_with_nonce_0_is_answered_not_taken_for_a_repeat(
    core: str, tmp_path: Path
) -> None:
    """A new session (and one saved and loaded from the state file) has answered no RESUME yet:
    a node at debit 0 that starts with nonce 0 is confirmed, not sent a cached ADMIT it ignores
    (which stalled it until its next start)."""
    path = tmp_path / "s.json"
    save_state(path, SupervisorState(J, J, 0, (Session(2),)), "witnessed", fsync=False)
    state = load_state(path, "witnessed", (2,))
    make = Supervisor if core == "python" else compiled_core
    sup = make([2], J, state=state, variant="witnessed")
    node = Client(2, variant="witnessed", state=ClientState(2))
    _exchange_py(node.power_loss(0, nonce=0), sup, node, 0)  # type: ignore[arg-type]
    assert node.state.phase is Phase.IDLE and node.can_spend()
    assert sup.session(2).returns_credited == 1 == node.state.return_seq


# -- the review's two findings on the C cores -------------------------------------------------


class _CClientNode:
    """The C client behind the ``receive``/``power_loss``/``state`` the scenarios use."""

    def __init__(self, state: ClientState) -> None:
        self.c = CClient(state.node, timing=SCENE, state=state, rules="witnessed")

    def _sends(self, out: Out) -> list[Send]:
        return [Send(CODEC.decode(*f)) for f in out_frames(out)]

    def receive(self, msg: Any, now: int) -> list[Send]:
        return self._sends(self.c.message(msg, now))

    def power_loss(self, now: int, nonce: int) -> list[Send]:
        return self._sends(self.c.resume(nonce, now))

    def spend(self, amount: int, now: int) -> list[Send]:
        assert self.c.do_draw(amount, now) == OK
        return self._sends(self.c.out)

    def handle_timer(self, now: int) -> list[Send]:
        return self._sends(self.c.timers(now))

    @property
    def state(self) -> ClientState:
        return self.c.state


def test_an_admitted_c_node_answering_a_sync_leaves_the_c_supervisors_gs_alone() -> None:
    sup = unknown_rc_supervisor(compiled_core)
    node = _CClientNode(ClientState(1, phase=Phase.JOINING, nonce=7))
    admitted_node_answers_a_sync(sup, node)


@pytest.mark.parametrize("rc", [0, RC_AT_2_32], ids=["rc-0", "rc-to-2^32"])
def test_a_late_resume_found_behind_then_the_first_c_image_creates_nothing(rc: int) -> None:
    """S8 with the C node and the C supervisor: the node found behind reports its Rc as a floor,
    also where its record's u32 of mJ has come round to 0 (before: read as no floor, the
    restored supervisor's Gs left 1 J below what the node received)."""
    sup = s8_supervisor(compiled_core, rc)
    node = _CClientNode(ClientState(1, credited=rc))
    usable, held = late_resume_found_behind_then_the_first_image(compiled_core, sup, node)
    assert usable + held <= 10**6, f"Us {usable} + held and spent by the node {held} uJ > 1 J"


def test_a_c_resume_after_a_lost_sync_answer_catches_tx_up_and_a_resync_opens_the_window() -> None:
    resume_after_a_lost_sync_answer(window_supervisor(compiled_core), _CClientNode(BOOKED_AT_10))


def test_stale_admits_to_a_booked_c_node_end_quiet_with_the_c_supervisor() -> None:
    stale_admits_end_quiet(window_supervisor(compiled_core), _CClientNode(BOOKED_AT_10))


def test_a_c_node_whose_sync_answers_were_lost_is_not_left_waiting_by_the_c_supervisor() -> None:
    answers_lost_then_stale_admits(window_supervisor(compiled_core), _CClientNode(BOOKED_AT_10))


def test_a_c_node_answering_a_stale_sync_settles_past_its_counts_for_a_restored_c_supervisor() -> (
    None
):
    sup = window_supervisor(compiled_core)
    stale_sync_taken_then_supervisor_image(compiled_core, sup, _CClientNode(BOOKED_AT_10))


def test_a_c_node_answering_a_second_stale_sync_after_a_c_begin_is_not_left_waiting() -> None:
    sup = window_supervisor(compiled_core)
    stale_sync_after_taken_counts_and_a_begin(sup, _CClientNode(BOOKED_AT_10))


def test_the_c_gateway_takes_rules_above_and_refuses_others(tmp_path: Path) -> None:
    port = _port("build/canergy-gateway")
    shown = subprocess.run(
        [str(port), "--help"], capture_output=True, text=True, timeout=10, check=True
    ).stdout
    assert "--upstream-rules hardened|witnessed" in shown
    run = subprocess.run(
        [str(port), "--upstream-rules", "trusting", "--node", "1"],
        capture_output=True,
        text=True,
        timeout=10,
        cwd=tmp_path,
    )
    assert run.returncode == 2
    assert run.stderr == (
        "canergy-gateway: error: argument --upstream-rules: invalid choice: 'trusting' "
        "(choose from 'hardened', 'witnessed')\n"
    )


@pytest.mark.parametrize(
    "frame",
    [Join(1, 0x33), Debit(1, 0x34, Debit.START, 69_999 & 0xFFFF, 0)],
    ids=["join", "resume found behind"],
)
def test_an_admission_lifting_tx_leaves_w_in_c_as_in_python(frame: Join | Debit) -> None:
    """tx 10, W 10, C 70,000: a JOIN or a RESUME found behind lifts tx to 10 + 2^16 and leaves
    W at 10 in both cores (the admission is no evidence of the node's ltx), and both refuse the
    next begin as beyond the window (C: CANERGY_ERR_WINDOW) until a re-sync."""
    s = Session(1, tx=10, witness=10, returns_credited=70_000)
    admitted = W.SUPERVISOR.step(ST, s, frame, 0).session
    assert (admitted.tx, admitted.witness) == (10 + (1 << 16), 10)
    same(s, ST, frame, 0, table=W.SUPERVISOR)
    same(admitted, ST, Begin(1_000_000), 0, table=W.SUPERVISOR)


@pytest.mark.parametrize("nonce", [0x0707, 0x8707, 0])
@pytest.mark.parametrize(
    "s",
    [
        Session(1, tx=10 + (1 << 16), witness=10, returns_credited=70_001),
        Session(1, tx=5, witness=5, phase=Phase.WAIT_ACK, reserved=1000, tries=1, deadline=9),
        Session(1, tx=5, witness=5, phase=Phase.SYNCING, sync_nonce=0x51, deadline=9),
        Session(1, tx=5, witness=5, phase=Phase.SYNC_BOOKS, sync_nonce=0x51, resync=True),
        Session(1, tx=10, witness=10, returns_credited=50, resume_nonce=0x10707, resume_to=50),
    ],
    ids=["idle", "open", "start", "re-sync", "idle after an answer to 0x0707"],
)
def test_a_resync_in_c_as_in_python(s: Session, nonce: int) -> None:
    """``canergy_session_resync`` as ``witnessed.resync_session``: from IDLE the session waits
    in SYNCING under the nonce with SYNC_CONFIRMED cleared, its timer a response timeout on,
    SYNC(n, tx, C) sent; refused (CANERGY_ERR_PHASE, nothing changed) in any other phase."""
    lib = c_session.library()
    timing = c_session.timing_of(ST, "witnessed", lib)
    c, step = c_session.to_c(s), c_session.SessionStep()
    rc = lib.canergy_session_resync(
        c_session.ref(c), c_session.ref(timing), nonce, 5, c_session.ref(step)
    )
    try:
        py = W.resync_session(ST, s, nonce, 5)
    except LocalProtocolError:
        assert rc == ERR_PHASE and c_session.fields_of(c) == c_session.fields_of(s)
        return
    assert rc == OK and c_session.fields_of(c) == c_session.fields_of(py.session)
    expected = c_session.sent_of(py.actions)
    assert expected is not None and c_session.c_sent(step, expected) == expected


@pytest.mark.parametrize("resync", [True, False], ids=["re-sync", "start"])
def test_books_answering_a_resync_leave_gs_where_a_starts_raise_it(resync: bool) -> None:
    """Books with an Rc above Gs raise Gs at a start (the difference out of Us), and leave it at
    a re-sync: nothing was restored, Gs holds what the node received already, and a JOIN that
    ends the re-sync would otherwise leave Gs raised with no transaction number moved past the
    one whose ``H`` was fixed below it (``canergy prove --rules witnessed``, the supervisor's
    JOIN). Both end at the counts alike. The C session as Python's."""
    s = Session(
        1, tx=12, witness=12, returns_credited=7, delivered=3_000_000, phase=Phase.SYNCING,
        sync_nonce=0x0707, resync=resync, deadline=9,
    )  # fmt: skip
    books = Debit.books(1, 0x0707, 4_000)  # Rc 4 J
    step = W.SUPERVISOR.step(ST, s, books, 5)
    same(s, ST, books, 5, table=W.SUPERVISOR)
    assert step.session.phase is Phase.SYNC_BOOKS
    raised = 0 if resync else 1_000_000
    assert (step.session.delivered, step.credit) == (3_000_000 + raised, -raised)
    counts = Debit.counts(1, 0x0707, 7, 12)
    same(step.session, ST, counts, 6, table=W.SUPERVISOR)
    done = W.SUPERVISOR.step(ST, step.session, counts, 6).session
    assert (done.phase, done.delivered) == (Phase.IDLE, 3_000_000 + raised)
