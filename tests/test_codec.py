import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.strategies import messages

from canergy.codec import LAYOUTS, Codec, DecodeError, DecodeErrorReason
from canergy.messages import Ack, Commit, Direction, Intention, Message, MsgType, Return

CODEC = Codec()


@given(messages)
def test_roundtrip(msg: Message) -> None:
    arbitration_id, data = CODEC.encode(msg)
    assert len(data) <= 8
    assert CODEC.is_canergy_id(arbitration_id)
    assert CODEC.decode(arbitration_id, data, direction=msg.TYPE.direction) == msg


@given(messages, st.data())
def test_any_corruption_of_one_byte_is_refused(msg: Message, data: st.DataObject) -> None:
    arbitration_id, frame = CODEC.encode(msg)
    i = data.draw(st.integers(0, len(frame) - 1))
    corrupted = bytearray(frame)
    corrupted[i] ^= data.draw(st.integers(1, 255))
    with pytest.raises(DecodeError) as err:
        CODEC.decode(arbitration_id, corrupted)
    assert err.value.reason in (DecodeErrorReason.BAD_CRC, DecodeErrorReason.OUT_OF_RANGE)


@given(messages, st.integers(1, 127))
def test_frame_for_one_node_cannot_pass_as_another(msg: Message, other: int) -> None:
    _arbitration_id, frame = CODEC.encode(msg)
    if other == msg.node:
        return
    moved = CODEC.arbitration_id(msg.TYPE, other)
    with pytest.raises(DecodeError) as err:
        CODEC.decode(moved, frame)
    assert err.value.reason is DecodeErrorReason.BAD_CRC


@given(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8), st.booleans(), st.booleans())
def test_fuzz_raises_only_the_typed_error(
    arbitration_id: int, data: bytes, extended: bool, remote: bool
) -> None:
    try:
        msg = CODEC.decode(arbitration_id, data, extended=extended, remote=remote)
    except DecodeError:
        return
    assert CODEC.encode(msg) == (arbitration_id, data)  # whatever passes is a canonical frame


def test_wire_layout_of_an_intention() -> None:
    arbitration_id, data = CODEC.encode(Intention(5, 0x0102, 500, 0x030405))
    assert arbitration_id == 0x0CE00105
    assert data[1:] == bytes([0x02, 0x01, 0xF4, 0x01, 0x05, 0x04, 0x03])
    assert len(data) == 8


def test_every_message_fits_a_classic_frame() -> None:
    assert all(1 < layout.dlc <= 8 for layout in LAYOUTS.values())


def _frame(msg: Message) -> tuple[int, bytearray]:
    arbitration_id, data = CODEC.encode(msg)
    return arbitration_id, bytearray(data)


@pytest.mark.parametrize(
    ("arbitration_id", "data", "kwargs", "reason"),
    [
        (0x705, b"\x05", {"extended": False}, DecodeErrorReason.FOREIGN),  # CANopen heartbeat
        (0x0CE00105, b"", {"extended": False}, DecodeErrorReason.FOREIGN),
        (0x18FEF100, bytes(8), {}, DecodeErrorReason.FOREIGN),
        (0x0CE00005, bytes(3), {}, DecodeErrorReason.UNKNOWN_TYPE),
        (0x0CE00100, bytes(8), {}, DecodeErrorReason.BAD_NODE),
        (0x0CE00185, bytes(8), {}, DecodeErrorReason.BAD_NODE),
        (*_frame(Ack(3, 1)), {"remote": True}, DecodeErrorReason.REMOTE_FRAME),
        (*_frame(Ack(3, 1)), {"direction": Direction.TO_CLIENT}, DecodeErrorReason.WRONG_DIRECTION),
        (_frame(Ack(3, 1))[0], _frame(Ack(3, 1))[1] + b"\x00", {}, DecodeErrorReason.WRONG_DLC),
        (
            _frame(Commit(3, 1, 9))[0],
            _frame(Commit(3, 1, 9))[1][:4],
            {},
            DecodeErrorReason.WRONG_DLC,
        ),
    ],
)
def test_refusals(
    arbitration_id: int, data: bytes, kwargs: dict, reason: DecodeErrorReason
) -> None:
    with pytest.raises(DecodeError) as err:
        CODEC.decode(arbitration_id, data, **kwargs)
    assert err.value.reason is reason


def test_zero_amount_is_out_of_range_even_with_a_good_crc() -> None:
    from canergy.codec import XOR_OUT, _prefix_register
    from canergy.crc import crc8_update

    body = bytes([1, 0, 0, 0])  # seq 1, amount 0
    crc = crc8_update(_prefix_register(MsgType.RETURN, 4), body) ^ XOR_OUT
    with pytest.raises(DecodeError) as err:
        CODEC.decode(CODEC.arbitration_id(MsgType.RETURN, 4), bytes([crc]) + body)
    assert err.value.reason is DecodeErrorReason.OUT_OF_RANGE


@pytest.mark.parametrize(
    "msg", [Return(1, 0, 0), Commit(1, 0, 0x10000), Ack(0, 1), Ack(128, 1), Ack(1, 0x10000)]
)
def test_encode_refuses_fields_that_do_not_fit(msg: Message) -> None:
    with pytest.raises(ValueError):
        CODEC.encode(msg)


@pytest.mark.parametrize("base", [0x123, -1, 0x20000000])
def test_bad_id_base(base: int) -> None:
    with pytest.raises(ValueError):
        Codec(base)


def test_configurable_base_and_filters() -> None:
    codec = Codec(0x1F000000)
    arbitration_id, data = codec.encode(Ack(9, 7))
    assert arbitration_id == 0x1F000909
    assert codec.accepts(codec.supervisor_filters(), arbitration_id, True)
    assert not codec.accepts(codec.client_filters(9), arbitration_id, True)
    intention_id, _ = codec.encode(Intention(9, 1, 1, 0))
    assert codec.accepts(codec.client_filters(9), intention_id, True)
    assert not codec.accepts(codec.client_filters(8), intention_id, True)
    assert not codec.accepts(codec.can_filters(), 0x709, False)
    with pytest.raises(DecodeError):
        CODEC.decode(arbitration_id, data)  # the default base does not own that block
