"""The moteus profile (``canergy.devices.moteus``), sans-IO: identifiers, subframes (the protocol
document's own example frames), malformed frames, the envelope of the configuration limits, and
the device guard with it in explicit time."""

from __future__ import annotations

import math
from fractions import Fraction

from hypothesis import given
from hypothesis import strategies as st

from canergy.devices.guard import DeviceConfig, DeviceGuard, GuardPhase
from canergy.devices.moteus import (
    FEEDBACK,
    Kind,
    MoteusLimits,
    MoteusMotor,
    MoteusProfile,
    Poll,
    Read,
    Reg,
    Reply,
    Stream,
    Write,
    can_id,
    conf_set,
    decode,
    encode,
    split_id,
    stream_lines,
    write_mode,
)
from canergy.devices.profile import Stop, WriteLimits

FULL = MoteusLimits(power_w=20.0, current_a=4.0, velocity=3.0, timeout_s=0.1)
MOTOR = MoteusMotor(Fraction(1, 10), Fraction(1, 2), Fraction(2), Fraction(24))


def test_identifiers_follow_source_destination_and_the_reply_bit() -> None:
    assert can_id(0, 1, reply=True) == 0x8001
    assert split_id(0x100) == (1, 0, False, 0)
    assert split_id(can_id(0x7E, 5, True, 0x1ABC)) == (0x7E, 5, True, 0x1ABC)


def test_the_documents_example_frame_decodes_as_written() -> None:
    """The protocol page's command and reply, byte for byte."""
    command = bytes.fromhex("01000a07206000200150ff140400130d")
    subframes, error = decode(command)
    assert error is None
    mode, targets, query, query2 = subframes
    assert mode == Write(Kind.INT8, Reg.MODE, (10.0,))
    assert isinstance(targets, Write) and targets.start == 0x20
    assert [round(v, 6) for v in targets.values] == [0.0096, 0.072, -1.76]
    assert query == Read(Kind.INT16, 0, 4) and query2 == Read(Kind.INT8, 0x0D, 3)
    reply = bytes.fromhex("2404000a005000000170ff230d181400")
    (r16, r8), error = decode(reply)
    assert error is None and isinstance(r16, Reply) and isinstance(r8, Reply)
    assert r16.items()[Reg.MODE] == 10.0 and round(r16.items()[Reg.TORQUE], 6) == -1.44
    assert r8.items() == {0x0D: 12.0, 0x0E: 20.0, 0x0F: 0.0}


def test_encode_pads_to_a_can_fd_length_with_nops_and_round_trips() -> None:
    data = encode(*FEEDBACK)
    assert data == bytes.fromhex("1c05001d071f0d")  # 7 bytes: a CAN FD length as it is
    assert decode(data) == (list(FEEDBACK), None)
    ten = (Write(Kind.FLOAT, Reg.COMMAND_POSITION, (1.0,)), Read(Kind.INT8, 0, 2), Poll(1, 9))
    data = encode(*ten)
    assert len(data) == 12 and data[11] == 0x50  # 11 bytes and a NOP
    assert decode(data) == (list(ten), None)
    assert write_mode(0) == b"\x01\x00\x00"
    diag = encode(Stream(False, 1, conf_set("servo.max_power_W", 20.0)))
    (stream,), _ = decode(diag)
    assert isinstance(stream, Stream) and stream.data == b"conf set servo.max_power_W 20\n"
    assert decode(encode(Poll(1, 48)))[0] == [Poll(1, 48)]


def test_the_unset_integer_is_nan_and_values_saturate() -> None:
    (w,), _ = decode(encode(Write(Kind.INT16, Reg.COMMAND_POSITION, (math.nan, 1e9))))
    assert isinstance(w, Write) and math.isnan(w.values[0])
    assert w.values[1] == 32767 * 0.00025  # 0x021, a velocity: the largest int16


def test_a_malformed_frame_keeps_what_parsed_before_it_and_says_why() -> None:
    """A controller acts on the subframes before a bad one: the guard must see them too."""
    good = encode(Write(Kind.INT8, Reg.MODE, (7.0,)))[:3]
    subframes, error = decode(good + b"\x0c\x05\x20\x00")  # float values past the end
    assert subframes == [Write(Kind.INT8, Reg.MODE, (7.0,))]
    assert error is not None and "past the frame's end" in error
    assert decode(b"\x77")[1] == "unknown subframe 0x77 at byte 1"
    assert decode(b"\x10\xff\xff\xff\xff\xff")[1] is not None  # a varuint of 6 bytes


@given(st.binary(max_size=64))
def test_any_bytes_decode_or_say_why_never_raise(data: bytes) -> None:
    subframes, error = decode(data)
    assert error is None or isinstance(error, str)
    assert all(not isinstance(s, str) for s in subframes)


def test_stream_lines_join_pieces_and_drop_carriage_returns() -> None:
    buffer = bytearray()
    assert stream_lines(buffer, b"20.00") == []
    assert stream_lines(buffer, b"0\r\nOK\r\nrest") == ["20.000", "OK"]
    assert buffer == b"rest"


def test_the_envelope_is_the_smallest_of_power_motor_and_supply_terms() -> None:
    profile = MoteusProfile(MOTOR)
    omega = 2 * math.pi * (3.0 + 2.0)
    motor_w = 0.1 * 4.0 * omega + 1.5 * 0.5 * 16  # 24.57 W, above the 20 W power limit
    e = profile.envelope(FULL)
    assert e.fw == 20 * 10**15 and e.parts["motor_term_w"] >= motor_w
    slow = MoteusLimits(power_w=100.0, current_a=4.0, velocity=0.5, timeout_s=0.1)
    w = 0.1 * 4.0 * 2 * math.pi * 2.5 + 12
    assert w * 1e15 <= profile.envelope(slow).fw <= w * 1e15 * (1 + 1e-6)
    assert profile.envelope(profile.closed(FULL)).fw == 0
    unset = MoteusLimits(math.nan, math.nan, math.nan, math.nan)
    assert profile.envelope(unset).fw == 2**62  # nothing bounds it


def test_mismatch_names_the_configuration_value() -> None:
    profile = MoteusProfile(MOTOR)
    assert profile.mismatch(FULL, FULL) is None
    assert profile.mismatch(FULL, FULL.with_conf("servo.max_current_A", 3.0)) == (
        "servo.max_current_A reads 3, written 4"
    )
    fine = MoteusLimits(123.456789, 4.0, 3.0, 0.1)
    assert profile.mismatch(fine, fine.with_conf("servo.max_power_W", 123.457)) is None  # text
    assert profile.mismatch(fine, fine.with_conf("servo.max_power_W", 123.46)) is not None
    nan = FULL.with_conf("servo.default_timeout_s", math.nan)
    assert profile.mismatch(FULL, nan) == "servo.default_timeout_s reads nan, written 0.1"


def guard() -> DeviceGuard[MoteusLimits]:
    config = DeviceConfig(limits=FULL, latency_us=5_000, reaction_us=10_000)
    return DeviceGuard(3, MoteusProfile(MOTOR), config, 0, 1)


def test_a_limit_that_does_not_read_back_refuses_the_controller_by_name() -> None:
    g = guard()
    g.on_ready(10_000, 0, FULL.with_conf("servo.max_power_W", 40.0), g.profile.closed(FULL))
    assert g.refused == "limits not taken: servo.max_power_W reads 40, written 20"
    assert not g.alive(10_000)


def test_a_power_limit_raised_behind_the_guard_is_charged_and_written_over() -> None:
    g = guard()
    g.on_ready(10_000, 0, FULL, g.profile.closed(FULL))
    raised = FULL.with_conf("servo.max_power_W", 200.0)
    before = g.metered_uj
    g.on_foreign_limits(100_000, 90_000, raised)
    (write,) = [c for c in g.commands if isinstance(c, WriteLimits)][-1:]
    g.on_limits(102_000, write.limits, write.limits, write.at)
    g.on_wakeup(200_000)
    # the set-up's full limits until its latency ran out (10 to 15 ms), the closed ones (0 W)
    # after, and the raised ones from when they were seen (90 ms) to the latency after the
    # guard's own read back (107 ms): at their envelope, the motor term (24.6 W, not 200)
    raised_fw = g.profile.envelope(raised).fw
    assert 24.5e15 < raised_fw < 24.6e15
    expected = (20 * 10**15 * 5_000 + raised_fw * 17_000) / 10**15
    assert abs(g.metered_uj - before - expected) <= 2


def test_a_controller_powered_after_its_stop_is_stuck() -> None:
    g = guard()
    g.on_ready(10_000, 0, FULL, g.profile.closed(FULL))
    g.on_feedback(20_000, 20_000, True, "POSITION")
    assert g.phase is GuardPhase.STOPPING and isinstance(g.commands[-1], Stop)
    t = g.phase_at
    while t < g.phase_at + 600_000:
        t += 50_000
        g.on_feedback(t, t, True, "POSITION")
        g.on_wakeup(t)
    assert g.phase is GuardPhase.STUCK and g.stuck == "still powered 500 ms after the stop"


def test_flow_controlled_stream_subframes_decode() -> None:
    """0x43 and 0x44 carry a packet number after the channel (the moteus tools' flow control)."""
    assert decode(b"\x43\x01\x05\x02ok") == ([Stream(True, 1, b"ok")], None)
    assert decode(b"\x44\x01\x05\x30") == ([Poll(1, 48)], None)


def test_limits_written_behind_the_guard_during_its_set_up_are_charged_once_it_is_ready() -> None:
    """A conf set after a value's read-back but before the set-up ended shows in no read-back:
    the guard takes it in when the set-up is done, charged from when it was seen, and writes its
    own limits again (they were once dropped: charged nothing, never written over)."""
    g = guard()
    raised = FULL.with_conf("servo.max_current_A", 20.0).with_conf("servo.max_power_W", 200.0)
    assert g.profile.envelope(raised).fw == 200 * 10**15  # P_max binds: 200 W
    g.on_foreign_limits(8_000, 6_000, raised)
    g.on_ready(10_000, 0, FULL, g.profile.closed(FULL))
    assert g.writes_seen == 1 and g.foreign == raised
    # the full limits' 20 W from the set-up's start, and the raised ones' surplus from 6 ms on
    surplus = (g.profile.envelope(raised).fw - g.profile.envelope(FULL).fw) * 4_000
    g.on_wakeup(11_000)  # and the raised ones' 200 W from 10 to 11 ms
    assert isinstance(g.commands[-1], WriteLimits)  # its own limits again
    assert g.metered_uj == (20 * 10**15 * 10_000 + surplus + 200 * 10**15 * 1_000) // 10**15
