"""The C authenticated frames (firmware/include/canergy/auth.h) against Python's ``FrameAuth``
(src/canergy/auth/frames.py): for both layouts and every message type, the C frames are the
Python frames byte for byte and each side accepts the other's; a flipped bit, a stale FV, a
frame without a MAC come to the same outcome on both sides, for counters near every wrap."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import can
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from support.c_binding import (
    REASONS,
    RX_OTHER_NODE,
    CLib,
    CNodeState,
    Frame,
    Msg,
    NodeConfig,
    Out,
    Struct,
    library,
    ref,
    rx,
)

from canergy.auth.frames import AuthFailure, FrameAuth, Layout, freshness
from canergy.codec import DEFAULT_ID_BASE, Codec, DecodeError
from canergy.messages import (
    AMOUNT_MAX_MJ,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    Direction,
    FinalAck,
    Intention,
    Join,
    Message,
    MsgType,
    Return,
    ReturnAck,
    StatusRequest,
    Telemetry,
)
from canergy.seqnum import unwrap

NODE = 5
U32 = 0xFFFF_FFFF
KEY = bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")
CODEC = Codec()
_C = library()
LAYOUTS = {Layout.FD: _C.CANERGY_AUTH_FD, Layout.CLASSIC: _C.CANERGY_AUTH_CLASSIC}
C_DIRECTIONS = {
    Direction.TO_CLIENT: _C.CANERGY_TO_CLIENT,
    Direction.TO_SUPERVISOR: _C.CANERGY_TO_SUPERVISOR,
}
PENDING = _C.CANERGY_AUTH_PENDING
FAILURES = {getattr(_C, f"CANERGY_AUTH_{f.name}"): f for f in AuthFailure}
"""C result -> Python's AuthFailure, by name."""


AuthFrame, Auth = Struct("auth_frame"), Struct("auth")


def lib() -> CLib:
    return library()


class CAuth:
    """One side's C auth context for node 5: the frames it builds, the outcome of each frame."""

    def __init__(self, layout: Layout, receives: Direction, key: bytes = KEY) -> None:
        self.ctx = Auth()
        result = lib().canergy_auth_init(
            ref(self.ctx),
            key,
            DEFAULT_ID_BASE,
            NODE,
            LAYOUTS[layout],
            C_DIRECTIONS[receives],
        )
        assert result == 0

    def frames(self, msg: Message, tx: int, seq: int) -> list[can.Message]:
        arbitration_id, data = CODEC.encode(msg)
        plain = Frame(arbitration_id, len(data), list(data))
        out = lib().new("struct canergy_auth_frame[2]")
        n = lib().canergy_auth_protect(ref(self.ctx), ref(plain), tx & U32, seq & U32, out)
        assert n in (1, 2)
        return [_can(f.id, bytes(f.data[0 : f.len])) for f in list(out)[0:n]]

    def outcome(self, frame: can.Message, tx: int, seq: int) -> str:
        """ "ok" (the verified frame must be the classic one), "pending", or the refusal."""
        r, _buf = rx(frame.arbitration_id, bytes(frame.data))
        verified = Frame()
        status = lib().canergy_auth_accept(
            ref(self.ctx), ref(r), tx & U32, seq & U32, ref(verified)
        )
        if status == 0:
            self.verified = (verified.id, bytes(verified.data[0 : verified.dlc]))
            return "ok"
        if status == PENDING:
            return "pending"
        if status == RX_OTHER_NODE:
            return "other node"
        return str((FAILURES[status] if status in FAILURES else REASONS[status]).value)


def _can(arbitration_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_fd=len(data) > 8)


def py_auth(layout: Layout, receives: Direction, tx: int, seq: int, key: bytes = KEY) -> FrameAuth:
    return FrameAuth(CODEC, layout, lambda n: key, receives, lambda m: freshness(m, tx, seq))


def py_outcome(auth: FrameAuth, frame: can.Message) -> str:
    try:
        verdict = auth.accept(frame)
    except DecodeError as err:
        return err.reason.value
    if verdict.failure is not None:
        return verdict.failure.value
    return "pending" if verdict.message is None else "ok"


# -- strategies -------------------------------------------------------------------------------

u16 = st.integers(0, 0xFFFF)
u24 = st.integers(0, 0xFF_FFFF)
amounts = st.integers(1, AMOUNT_MAX_MJ)
near_wraps = st.one_of(
    st.integers(65530, 65545),
    st.integers(0x7FF0, 0x8010),
    st.integers(0, 20),
    st.integers(U32 - 10, U32 + 20),
    st.integers(0, 2**40),
)
"""Counters as the Python side holds them (unbounded): near 2^16, 2^15, 0, 2^32, anywhere."""
layouts = st.sampled_from(Layout)


def messages(tx: int, seq: int) -> st.SearchStrategy[Message]:
    """Every message type, its wire counter near (or far from) the sender's own."""
    wire_tx = st.one_of(
        st.integers(-40, 40).map(lambda d: (tx + d) & 0xFFFF),
        st.sampled_from([(tx + 0x8000) & 0xFFFF, (tx + 0x7FFF) & 0xFFFF]),  # the halfway ties
        u16,
    )
    wire_seq = st.one_of(st.integers(-40, 40).map(lambda d: (seq + d) & 0xFFFF), u16)
    n = st.just(NODE)
    return st.one_of(
        st.builds(Intention, n, wire_tx, amounts, u24),
        st.builds(Commit, n, wire_tx, amounts),
        st.builds(Abort, n, wire_tx, amounts),
        st.builds(ReturnAck, n, wire_seq),
        st.builds(StatusRequest, n, wire_tx),
        st.builds(FinalAck, n, wire_tx),
        st.builds(Admit, n, u16, wire_tx, wire_seq),
        st.builds(Ack, n, wire_tx),
        st.builds(Committed, n, wire_tx),
        st.builds(Aborted, n, wire_tx),
        st.builds(Return, n, wire_seq, amounts),
        st.builds(Telemetry, n, u24, st.integers(0, 7), wire_seq, st.integers(0, 0xFF)),
        st.builds(Join, n, u16),
    )


@st.composite
def cases(draw: Callable[..., Any]) -> tuple[Layout, Message, int, int]:
    tx, seq = draw(near_wraps), draw(near_wraps)
    return draw(layouts), draw(messages(tx, seq)), tx, seq


ALL_TYPES: list[Message] = [
    Intention(NODE, 2, 500, 1000),
    Commit(NODE, 2, 500),
    Abort(NODE, 2, 500),
    ReturnAck(NODE, 0xFFFF),
    StatusRequest(NODE, 2),
    FinalAck(NODE, 2),
    Admit(NODE, 0xBEEF, 2, 0xFFFF),
    Ack(NODE, 2),
    Committed(NODE, 2),
    Aborted(NODE, 2),
    Return(NODE, 0xFFFF, 120),
    Telemetry(NODE, 500, 2, 0xFFFF, 0xFF),
    Join(NODE, 0xBEEF),
    Debit(NODE, 0, Debit.DRAW, 0xFFFF, 120),
    Debit(NODE, 0xBEEF, Debit.START | Debit.DRAW, 0x8001, 0),
    Debit.books(NODE, 0xBEEF, 0xA08001),  # a SYNC's answer: fresh by its nonce, not by Rc
    Debit.counts(NODE, 0xBEEF, 0x8001, 0x7FFF),
]


def _receiver(msg: Message) -> Direction:
    return msg.TYPE.direction


# -- the tests --------------------------------------------------------------------------------


def test_data_lengths_are_the_codecs() -> None:
    for code in range(17):
        try:
            want = Codec.data_length(MsgType(code))
        except (ValueError, KeyError):
            want = 0
        assert lib().canergy_data_length(code) == want, code


@pytest.mark.parametrize("msg", ALL_TYPES, ids=lambda m: type(m).__name__)
def test_fd_frames_are_the_smallest_fd_length_that_holds_data_fv_and_mac(msg: Message) -> None:
    data_length = Codec.data_length(msg.TYPE)
    (frame,) = CAuth(Layout.FD, _receiver(msg)).frames(msg, 0, 0)
    want = 16 if data_length + 12 <= 16 else 20
    assert len(frame.data) == want and (msg.TYPE is not MsgType.TELEMETRY or want == 20)


@pytest.mark.parametrize("layout", list(Layout))
@pytest.mark.parametrize("msg", ALL_TYPES, ids=lambda m: type(m).__name__)
def test_every_type_both_ways_at_the_16_bit_wrap(layout: Layout, msg: Message) -> None:
    _both_ways(layout, msg, 0x1_FFFF, 0x1_FFFF)


@given(cases())
@example((Layout.CLASSIC, Commit(NODE, 0x8000, 300), 0, 0))  # the halfway tie: FV 0xFFFF8000
@example((Layout.FD, Ack(NODE, 0), 65535, 0))
@example((Layout.FD, Return(NODE, 0, 1), 0, 65535))
def test_c_frames_are_python_frames_and_each_side_accepts_the_other(
    case: tuple[Layout, Message, int, int],
) -> None:
    _both_ways(*case)


JOIN_FV = 0xBEEF_0007
A = TypeVar("A", FrameAuth, CAuth)


def _joined(auth: A, msg: Message) -> A:
    """``auth`` with the JOIN FV set, for a TELEMETRY sent without books (bound to its JOIN)."""
    if isinstance(msg, Telemetry) and msg.flags & Telemetry.JOINING:
        if isinstance(auth, CAuth):
            lib().canergy_auth_set_join(ref(auth.ctx), JOIN_FV >> 16, JOIN_FV & 0xFFFF)
        else:
            auth.join_fv[msg.node] = JOIN_FV
    return auth


def _both_ways(layout: Layout, msg: Message, tx: int, seq: int) -> None:
    receiver = _receiver(msg)
    sender = Direction.TO_CLIENT if receiver is Direction.TO_SUPERVISOR else Direction.TO_SUPERVISOR
    c_frames = _joined(CAuth(layout, sender), msg).frames(msg, tx, seq)
    py_frames = _joined(py_auth(layout, sender, tx, seq), msg).frames(msg)
    assert [(f.arbitration_id, bytes(f.data)) for f in c_frames] == [
        (f.arbitration_id, bytes(f.data)) for f in py_frames
    ]
    assert [f.is_fd for f in c_frames] == [f.is_fd for f in py_frames]
    # Python accepts the C frames, C accepts the Python frames, with the same counters
    python = _joined(py_auth(layout, receiver, tx, seq), msg)
    verdicts = [python.accept(f) for f in c_frames]
    taken = msg
    if isinstance(msg, Admit):  # the full counters: the FV's high half (its k's, next to tx)
        high = unwrap(msg.tx, tx, 16) & 0xFFFF_0000
        taken = Admit(msg.node, msg.nonce, high | msg.tx, high | msg.seq)
    assert verdicts[-1].message == taken and all(v.failure is None for v in verdicts)
    c_side = _joined(CAuth(layout, receiver), msg)
    outcomes = [c_side.outcome(f, tx, seq) for f in py_frames]
    assert outcomes == ["pending", "ok"] if layout is Layout.CLASSIC else ["ok"]
    assert c_side.verified == CODEC.encode(msg)


@given(cases(), st.data())
def test_a_flipped_bit_is_refused_for_the_same_reason_on_both_sides(
    case: tuple[Layout, Message, int, int], data: st.DataObject
) -> None:
    layout, msg, tx, seq = case
    receiver = _receiver(msg)
    frames = py_auth(layout, receiver, tx, seq).frames(msg)
    which = data.draw(st.integers(0, len(frames) - 1))
    body = bytearray(frames[which].data)
    bit = data.draw(st.integers(0, 8 * len(body) - 1))
    body[bit // 8] ^= 1 << bit % 8
    frames[which] = _can(frames[which].arbitration_id, bytes(body))
    python, c_side = py_auth(layout, receiver, tx, seq), CAuth(layout, receiver)
    py_outcomes = [py_outcome(python, f) for f in frames]
    c_outcomes = [c_side.outcome(f, tx, seq) for f in frames]
    assert c_outcomes == py_outcomes
    assert py_outcomes[-1] != "ok"  # never accepted


@given(cases(), st.sampled_from([0x1_0000, -0x1_0000, 1, -1, 0x8000, 2**32]))
def test_a_stale_fv_is_refused_on_both_sides(
    case: tuple[Layout, Message, int, int], shift: int
) -> None:
    """The sender's counters are `shift` away from the receiver's: a replay from 65,536
    transactions ago, say. Only the FV of JOIN, ADMIT (the nonce) and an FD TELEMETRY (its
    window is the supervisor's to judge) still verifies then; a classic TELEMETRY's low half
    extends to another FV, so its MAC fails; both sides agree for every shift (a small one may
    still extend to the same FV)."""
    layout, msg, tx, seq = case
    receiver = _receiver(msg)
    frames = py_auth(layout, receiver, tx, seq).frames(msg)
    rtx, rseq = tx + shift, seq + shift
    python, c_side = py_auth(layout, receiver, rtx, rseq), CAuth(layout, receiver)
    py_outcomes = [py_outcome(python, f) for f in frames]
    assert [c_side.outcome(f, rtx, rseq) for f in frames] == py_outcomes
    if isinstance(msg, Telemetry) and msg.flags & Telemetry.JOINING:  # no JOIN FV to bind
        assert py_outcomes[-1] != "ok"
    elif abs(shift) == 0x1_0000:  # one whole wire period away: always stale
        if isinstance(msg, Telemetry) and layout is Layout.CLASSIC:
            assert py_outcomes[-1] == AuthFailure.MAC_BAD.value
        else:
            fresh_anyway = isinstance(msg, Join | Admit | Telemetry)
            assert py_outcomes[-1] == ("ok" if fresh_anyway else AuthFailure.STALE.value)
    elif shift == 2**32:  # the same counters modulo 2^32: the same FV
        assert py_outcomes[-1] == "ok"


@given(layouts, near_wraps, near_wraps)
def test_the_freshness_value_is_pythons(layout: Layout, tx: int, seq: int) -> None:
    for msg in ALL_TYPES:
        arbitration_id, data = CODEC.encode(msg)
        m = Msg()
        frame, _buf = rx(arbitration_id, data)  # the buffer outlives the call
        assert lib().canergy_decode(DEFAULT_ID_BASE, frame, 0, m) == 0
        assert (
            lib().canergy_auth_freshness(ref(m), tx & U32, seq & U32)
            == freshness(msg, tx, seq) & U32
        )


@pytest.mark.parametrize("layout", list(Layout))
def test_a_frame_without_a_mac_and_a_lone_mac_frame(layout: Layout) -> None:
    forged = _can(*CODEC.encode(Commit(NODE, 1, 65535)))
    python, c_side = py_auth(layout, Direction.TO_CLIENT, 0, 0), CAuth(layout, Direction.TO_CLIENT)
    lone_mac = _can(DEFAULT_ID_BASE | NODE, bytes([2, 0, 0, 1, 2, 3, 4, 5]))
    short_mac = _can(DEFAULT_ID_BASE | NODE, bytes([2, 0, 0, 1, 2, 3, 4]))
    their_mac = _can(DEFAULT_ID_BASE | 0x800 | NODE, bytes(8))
    fd_padded = _can(forged.arbitration_id, bytes(forged.data) + bytes(15))
    fd_dirty = _can(forged.arbitration_id, bytes(forged.data) + bytes([1]) + bytes(14))
    frames = [
        forged,
        lone_mac,
        forged,
        short_mac,
        lone_mac,
        forged,
        forged,  # classic: the first never got its MAC frame
        their_mac,
        fd_padded,
        fd_dirty,
    ]
    py_outcomes = [py_outcome(python, f) for f in frames]
    assert [c_side.outcome(f, 0, 0) for f in frames] == py_outcomes
    if layout is Layout.FD:
        assert py_outcomes[0] == AuthFailure.UNAUTHENTICATED.value
    else:
        assert py_outcomes[0:7] == [
            "pending",
            AuthFailure.MAC_BAD.value,
            "pending",
            AuthFailure.MALFORMED.value,
            AuthFailure.NO_DATA.value,
            "pending",
            AuthFailure.UNAUTHENTICATED.value,
        ]


@pytest.mark.parametrize("layout", list(Layout))
def test_a_c_node_is_granted_through_python_frames_and_refuses_forgeries(layout: Layout) -> None:
    """The node layer in authenticated mode: a Python supervisor's ADMIT, INTENTION and COMMIT
    reach it; its own replies verify at the supervisor; forged frames move nothing. Admitted
    past transaction 65,535 (its NV lost there), the node takes the supervisor's full counters
    from the ADMIT's FV, so its freshness meets the supervisor's."""
    node, out = CNodeState(), Out()
    cfg = NodeConfig()
    cfg.client.id_base, cfg.client.node = DEFAULT_ID_BASE, NODE
    cfg.client.command_timeout_us = cfg.client.return_retry_us = 100_000
    cfg.telemetry_period_us, cfg.return_above_uj = 1_000_000, U32
    c = lib()
    assert c.canergy_node_start(ref(node), ref(cfg), c.ffi.NULL, 0, 0x1234, 0, ref(out)) == 0
    c_auth = CAuth(layout, Direction.TO_CLIENT)
    sup = {"tx": 0x3_FFFF, "seq": 0x3_0002}
    supervisor = FrameAuth(
        CODEC,
        layout,
        lambda n: KEY,
        Direction.TO_SUPERVISOR,
        lambda m: freshness(m, sup["tx"], sup["seq"]),
    )

    def deliver(frames: list[can.Message], now: int) -> list[int]:
        results = []
        for f in frames:
            r, _buf = rx(f.arbitration_id, bytes(f.data))
            results.append(
                c.canergy_auth_node_frame(
                    ref(c_auth.ctx),
                    ref(node),
                    ref(r),
                    now,
                    ref(out),
                )
            )
        return results

    def replies() -> list[Message]:
        got = []
        for plain in list(out.frames)[0 : out.frame_count]:
            frames = c.new("struct canergy_auth_frame[2]")
            n = c.canergy_auth_node_protect(ref(c_auth.ctx), ref(node), ref(plain), frames)
            for f in list(frames)[0:n]:
                v = supervisor.accept(_can(f.id, bytes(f.data[0 : f.len])))
                assert v.failure is None
                if v.message is not None:
                    got.append(v.message)
        return got

    assert deliver(supervisor.frames(Admit(NODE, 0x1234, 0xFFFF, 2)), 10)[-1] == 0
    assert node.client.phase == 0 and node.client.rec.last_tx == 0x3_FFFF
    assert node.client.rec.return_seq == 0x3_0002
    sup["tx"] = 0x4_0000
    assert deliver(supervisor.frames(Intention(NODE, 0, 700, 700)), 20)[-1] == 0
    assert replies() == [Ack(NODE, 0)]
    before = node.client.rec.usable_uj
    forged = _can(*CODEC.encode(Commit(NODE, 0, AMOUNT_MAX_MJ)))
    no_mac = _C.CANERGY_AUTH_UNAUTHENTICATED
    assert deliver([forged], 25)[-1] == (PENDING if layout is Layout.CLASSIC else no_mac)
    assert node.client.rec.usable_uj == before
    assert deliver(supervisor.frames(Commit(NODE, 0, 700)), 30)[-1] == 0
    assert node.client.rec.usable_uj == before + 700_000
    assert Committed(NODE, 0) in replies()
    # the COMMIT again, 65,536 transactions later: the same frames do not verify
    replay = supervisor.frames(Commit(NODE, 0, 700))
    node.client.rec.last_tx += 0x1_0000
    assert deliver(replay, 40)[-1] == _C.CANERGY_AUTH_STALE
    assert node.client.rec.usable_uj == before + 700_000
    # a RETURN in its name and (classic) a MAC frame 0x8: witnessed, moving nothing; in the
    # FD layout 0x8 is no MAC frame but an unknown type, as in Python
    spoof = _can(*CODEC.encode(Return(NODE, 1, AMOUNT_MAX_MJ)))
    mac_frame = _can(DEFAULT_ID_BASE | 0x800 | NODE, bytes([MsgType.RETURN, 0, 0, 1, 2, 3, 4, 5]))
    results = deliver([spoof, mac_frame], 50)
    wrong_way = [REASONS[r].name == "WRONG_DIRECTION" for r in results]
    assert wrong_way == [True, layout is Layout.CLASSIC] and out.frame_count == 0
    assert node.witness == sum(wrong_way) and node.client.rec.usable_uj == before + 700_000
    assert c.canergy_node_deadline(ref(node)) <= 50  # due: its TELEMETRY at the next poll


@pytest.mark.parametrize("layout", list(Layout))
def test_a_c_node_joins_with_32_bits_of_freshness(layout: Layout) -> None:
    """The C node's JOIN carries 16 random bits above its nonce, as the Python node's does; the
    Python supervisor binds its JOIN FV in the ADMIT's MAC; an ADMIT of an earlier life with
    the same 16-bit nonce fails its MAC at the C node."""
    c_node = CAuth(layout, Direction.TO_CLIENT)
    lib().canergy_auth_set_join(ref(c_node.ctx), 0xBEEF, 7)
    sup = py_auth(layout, Direction.TO_SUPERVISOR, 0, 0)
    join = c_node.frames(Join(NODE, 7), 0, 0)
    assert [py_outcome(sup, f) for f in join][-1] == "ok" and sup.join_fv[NODE] == 0xBEEF0007
    admit = sup.frames(Admit(NODE, 7, 1, 0))
    assert [c_node.outcome(f, 0, 0) for f in admit][-1] == "ok"
    earlier = py_auth(layout, Direction.TO_SUPERVISOR, 0, 0)
    earlier.join_fv[NODE] = 0x1234 << 16 | 7
    replayed = earlier.frames(Admit(NODE, 7, 1, 0))
    assert [c_node.outcome(f, 0, 0) for f in replayed][-1] == AuthFailure.MAC_BAD.value
