"""The C codec against canergy.codec: any identifier, length, flags and bytes give the same
message or the same refusal reason; every message encodes to the same frame, and what Python
refuses to encode C refuses too."""

from __future__ import annotations

import functools

import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from support.c_binding import DIRECTIONS, OK, REASONS, Frame, Msg, cbuf, library, ref, rx
from support.strategies import messages

from canergy.codec import DEFAULT_ID_BASE, Codec, DecodeError, DecodeErrorReason
from canergy.messages import (
    Abort,
    Ack,
    Admit,
    Commit,
    Debit,
    Direction,
    Intention,
    Join,
    Message,
    MsgType,
    Return,
    Telemetry,
)

DEBIT_KINDS = [
    Debit.DRAW,
    Debit.START,
    Debit.START | Debit.DRAW,
    Debit.START | Debit.SYNC,
    Debit.START | Debit.SYNC | Debit.RC_UNKNOWN,
    Debit.BOOKS,
    Debit.BOOKS | Debit.RC_UNKNOWN,
]
BASES = [DEFAULT_ID_BASE, 0, 0x1FFFF000, 0x12345000]
ALL_MESSAGES = (
    messages
    | st.builds(
        Admit,
        st.integers(1, 127),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
    )
    | st.builds(Join, st.integers(1, 127), st.integers(0, 0xFFFF))
    | st.builds(  # every DEBIT kind and what is none (Python encodes it, decoding refuses it)
        Debit,
        st.integers(1, 127),
        st.sampled_from([0, 1, 0xFFFF]) | st.integers(0, 0xFFFF),
        st.sampled_from(DEBIT_KINDS) | st.integers(0, 0xFF),
        st.integers(0, 0xFFFF),
        st.sampled_from([0, 1, 0xFFFF]) | st.integers(0, 0xFFFF),
    )
)


@functools.cache
def codec(base: int) -> Codec:
    return Codec(base)


C_FIELDS = ("delivered_mj", "level_mj", "tx", "seq", "nonce", "amount_mj", "flags", "witness")


def fields(msg: Message) -> dict[str, int]:
    """A Python message in the C struct's terms (unused fields zero; TELEMETRY's return_seq is
    the struct's seq)."""
    f = dict.fromkeys(C_FIELDS, 0)
    f.update({k: getattr(msg, k) for k in f if hasattr(msg, k)})
    if isinstance(msg, Telemetry):
        f["seq"] = msg.return_seq
    f["type"], f["node"] = int(msg.TYPE), msg.node
    return f


def c_fields(m: Msg) -> dict[str, int]:
    return {name: getattr(m, name) for name in Msg.fields}


def c_decode(
    base: int, arbitration_id: int, data: bytes, extended: bool, remote: bool, direction: str | None
) -> tuple[int, Msg]:
    frame, buf = rx(arbitration_id, data, extended, remote)
    m = Msg()
    status = library().canergy_decode(base, ref(frame), DIRECTIONS[direction], ref(m))
    del buf
    return status, m


def assert_same_decoding(
    base: int, arbitration_id: int, data: bytes, extended: bool, remote: bool, direction: str | None
) -> None:
    py_direction = {
        None: None,
        "to_client": Direction.TO_CLIENT,
        "to_supervisor": Direction.TO_SUPERVISOR,
    }[direction]
    status, m = c_decode(base, arbitration_id, data, extended, remote, direction)
    try:
        msg = codec(base).decode(
            arbitration_id, data, extended=extended, remote=remote, direction=py_direction
        )
    except DecodeError as err:
        assert REASONS.get(status) is err.reason
        return
    assert status == OK and c_fields(m) == fields(msg)


ids = (
    st.integers(0, 2**32 - 1)
    | st.integers(0, 0x7FF)
    | st.builds(lambda t, n: t << 8 | n, st.integers(0, 15), st.integers(0, 255))
    | st.builds(
        lambda hi, t, n: hi << 29 | t << 8 | n,
        st.integers(1, 7),
        st.integers(0, 15),
        st.integers(0, 255),
    )
)


@given(
    base=st.sampled_from(BASES),
    low=ids,
    data=st.binary(max_size=12),
    extended=st.booleans(),
    remote=st.booleans(),
    direction=st.sampled_from(list(DIRECTIONS)),
    in_block=st.booleans(),
)
@example(
    base=DEFAULT_ID_BASE,
    low=0x705,
    data=b"\x05",
    extended=False,
    remote=False,
    direction=None,
    in_block=False,
)
def test_fuzzed_frames_decode_alike(
    base: int,
    low: int,
    data: bytes,
    extended: bool,
    remote: bool,
    direction: str | None,
    in_block: bool,
) -> None:
    arbitration_id = (base | (low & 0xE0000FFF)) if in_block else low
    assert_same_decoding(base, arbitration_id, data, extended, remote, direction)


@given(
    base=st.sampled_from(BASES),
    msg=ALL_MESSAGES,
    damage=st.none() | st.tuples(st.integers(0, 7), st.integers(1, 255)),
    length=st.none() | st.integers(0, 64),
    direction=st.sampled_from(list(DIRECTIONS)),
    remote=st.booleans(),
)
def test_valid_and_damaged_frames_decode_alike(
    base: int,
    msg: Message,
    damage: tuple[int, int] | None,
    length: int | None,
    direction: str | None,
    remote: bool,
) -> None:
    arbitration_id, data = codec(base).encode(msg)
    frame = bytearray(data)
    if damage is not None:
        frame[damage[0] % len(frame)] ^= damage[1]
    if length is not None:
        frame = (frame + bytes(64))[0:length]  # CAN FD lengths and short frames
    assert_same_decoding(base, arbitration_id, bytes(frame), True, remote, direction)


def c_encode(base: int, f: dict[str, int]) -> tuple[int, tuple[int, bytes]]:
    m = Msg(**f)
    out = Frame()
    status = library().canergy_encode(base, ref(m), ref(out))
    return status, (out.id, bytes(out.data[0 : out.dlc]))


@given(base=st.sampled_from(BASES), msg=ALL_MESSAGES)
def test_messages_encode_alike(base: int, msg: Message) -> None:
    status, frame = c_encode(base, fields(msg))
    assert status == OK and frame == codec(base).encode(msg)


@pytest.mark.parametrize(
    "msg",
    [
        Telemetry(5, 500, 2, 0x1234, 3),
        Telemetry(127, 0xFFFFFF, 0xFF, 0xFFFF, 0xFF),
        Telemetry(1, 0),
    ],
    ids=str,
)
def test_telemetry_is_eight_bytes_in_both_codecs(msg: Telemetry) -> None:
    """level u24, flags, the return number, the witness: canergy.codec's "<HBBHB", DLC 8."""
    arbitration_id, data = Codec().encode(msg)
    assert len(data) == Codec.data_length(MsgType.TELEMETRY) == 8
    status, frame = c_encode(DEFAULT_ID_BASE, fields(msg))
    assert status == OK and frame == (arbitration_id, data)
    status, m = c_decode(DEFAULT_ID_BASE, arbitration_id, data, True, False, "to_supervisor")
    assert status == OK and c_fields(m) == fields(msg)
    for short in (data[0:5], data[0:7]):  # the old 5-byte layout, a truncated frame
        assert c_decode(DEFAULT_ID_BASE, arbitration_id, short, True, False, None)[0] != OK


@pytest.mark.parametrize(
    "msg",
    [
        Commit(1, 0, 0),
        Abort(1, 0, 0),
        Return(1, 0, 0),
        Intention(1, 0, 0, 5),
        Intention(1, 0, 1, 0x1000000),
        Telemetry(1, 0x1000000, 0),
        Ack(0, 1),
        Ack(128, 1),
        Ack(255, 1),
    ],
    ids=str,
)
def test_what_python_refuses_to_encode_c_refuses(msg: Message) -> None:
    with pytest.raises(ValueError):
        Codec().encode(msg)
    status, _ = c_encode(DEFAULT_ID_BASE, fields(msg))
    assert status != OK


@pytest.mark.parametrize("code", [0x0, 0x8, 0x10, 0xFF])
def test_unknown_types_do_not_encode(code: int) -> None:
    status, _ = c_encode(DEFAULT_ID_BASE, {"type": code, "node": 1, "tx": 1, "amount_mj": 1})
    assert status != OK
    assert code > 0xF or code not in MsgType._value2member_map_


@pytest.mark.parametrize("base", [0x123, 0x20000000, 0x0CE00001, 0xFFFFFFFF])
def test_bad_id_bases_are_refused(base: int) -> None:
    assert not library().canergy_id_base_valid(base)
    status, _ = c_encode(base, fields(Ack(1, 1)))
    assert status != OK
    with pytest.raises(ValueError):
        Codec(base)


@given(st.binary(max_size=64))
def test_crcs_agree_with_python_and_zlib(data: bytes) -> None:
    import zlib

    from canergy.crc import crc8

    buf = cbuf(data, max(len(data), 1))
    assert library().canergy_crc8(0xFF, buf, len(data)) ^ 0xFF == crc8(data)
    assert library().canergy_crc32(0, buf, len(data)) == zlib.crc32(data)


@pytest.mark.parametrize(
    "msg",
    [
        Debit(1, 0, 0, 1, 5),  # neither flag
        Debit(1, 7, Debit.DRAW, 1, 5),  # a draw with a nonce
        Debit(1, 0, Debit.DRAW, 1, 0),  # a draw of nothing
        Debit(1, 0, Debit.START | 0x10, 1, 5),  # an unknown flag on a resume
        Debit(1, 0, 0x80, 1, 5),
        Debit(1, 3, Debit.SYNC, 1, 5),  # SYNC without START
        Debit(1, 3, Debit.START | Debit.SYNC | Debit.DRAW, 1, 5),  # counts with a draw
        Debit(1, 3, Debit.BOOKS | Debit.START, 1, 5),  # books and a resume
        Debit(1, 3, Debit.BOOKS | Debit.DRAW, 1, 5),
        Debit(1, 3, Debit.BOOKS, 0xFFFF, 0x100),  # books beyond 24 bits
        Debit(1, 3, Debit.BOOKS, 0, 0xFFFF),
        Debit(1, 3, Debit.BOOKS | Debit.RC_UNKNOWN, 1, 0),  # no Rc, yet one carried
        Debit(1, 3, Debit.BOOKS | Debit.RC_UNKNOWN, 0, 1),
        Debit(1, 3, Debit.RC_UNKNOWN, 0, 0),  # alone
    ],
    ids=str,
)
def test_a_debit_of_no_known_kind_is_refused_by_both(msg: Debit) -> None:
    arbitration_id, data = Codec().encode(msg)
    with pytest.raises(DecodeError) as err:
        Codec().decode(arbitration_id, data)
    assert err.value.reason is DecodeErrorReason.OUT_OF_RANGE
    status, _ = c_decode(DEFAULT_ID_BASE, arbitration_id, data, True, False, None)
    assert REASONS.get(status) is DecodeErrorReason.OUT_OF_RANGE


@pytest.mark.parametrize(
    "msg",
    [
        Debit(1, 0, Debit.DRAW, 0xFFFF, 1),
        Debit(127, 0xBEEF, Debit.START | Debit.DRAW, 3, 0),
        Debit.books(5, 0x8001, 0xFFFFFF),  # the most books a frame carries
        Debit.books(5, 0, 0),
        Debit.books(5, 0x4321, None),  # Rc unknown
        Debit.counts(5, 0xFFFF, 0xFFFF, 0xFFFF),
        Debit.counts(5, 0, 0, 0),
    ],
    ids=str,
)
def test_every_debit_kind_decodes_in_c(msg: Debit) -> None:
    arbitration_id, data = Codec().encode(msg)
    status, m = c_decode(DEFAULT_ID_BASE, arbitration_id, data, True, False, "to_supervisor")
    assert status == OK and c_fields(m) == fields(msg)
