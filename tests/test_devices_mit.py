"""MIT-mode frames and the clamp (``canergy.devices.mit``), sans-IO and exact: the bit layout of
commands and replies, the torque cap a power allows, and a clamped command whose worst-case
torque never exceeds the cap (hence whose power never exceeds the budget's)."""

from __future__ import annotations

from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.devices.mit import (
    ENTER,
    EXIT,
    FW_PER_W,
    MODELS,
    UNM_PER_NM,
    Command,
    MitLimits,
    MitProfile,
    cap_for_power,
    clamp,
    decode,
    encode,
    pack_reply,
    power,
    unpack_reply,
    worst_torque,
)

AK = MODELS["AK80-9"]
DM = MODELS["DM4310"]
R = Fraction(1, 5)

commands = st.builds(
    Command,
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFFF),
    st.integers(0, 0xFFF),
    st.integers(0, 0xFFF),
    st.integers(0, 0xFFF),
)


def test_the_command_layout_is_the_manuals() -> None:
    """p 16 bits, v 12, kp 12, kd 12, t_ff 12, big-endian, packed without gaps."""
    cmd = Command(0x1234, 0xABC, 0xDEF, 0x123, 0x456)
    assert cmd.pack() == bytes.fromhex("1234abcdef123456")
    assert Command.unpack(bytes.fromhex("1234abcdef123456")) == cmd


@given(commands)
def test_commands_round_trip(cmd: Command) -> None:
    data = cmd.pack()
    if data in (ENTER, EXIT) or data[:7] == b"\xff" * 7:
        return
    assert Command.unpack(data) == cmd


def test_special_frames_and_short_frames_are_not_commands() -> None:
    with pytest.raises(ValueError, match="special frame \\(exit\\)"):
        Command.unpack(EXIT)
    with pytest.raises(ValueError, match="6 bytes"):
        Command.unpack(b"\x00" * 6)


def test_the_ranges_map_linearly_with_the_ends_exact() -> None:
    lowest = decode(AK, Command(0, 0, 0, 0, 0))
    highest = decode(AK, Command(0xFFFF, 0xFFF, 0xFFF, 0xFFF, 0xFFF))
    assert (lowest.p, lowest.v, lowest.kp, lowest.kd, lowest.t) == (-12.5, -50, 0, 0, -18)
    assert (highest.p, highest.v, highest.kp, highest.kd, highest.t) == (12.5, 50, 500, 5, 18)
    assert abs(decode(DM, encode(DM, 1.0, -3.0, 20.0, 1.0, 2.0)).kp - 20) <= Fraction(500, 2 * 4095)


def test_replies_name_the_motor_and_damiao_its_state() -> None:
    ak = unpack_reply(AK, pack_reply(AK, 3, 0xFFFF, 0x800, 0x000))
    assert (ak.node, ak.p, ak.torque, ak.state) == (3, Fraction(25, 2), -18, None)
    dm = unpack_reply(DM, pack_reply(DM, 5, 0, 0xFFF, 0xFFF, state=1))
    assert (dm.node, dm.state, dm.v, dm.torque) == (5, 1, 30, 10)
    with pytest.raises(ValueError):
        unpack_reply(AK, b"\x01\x02")


@given(st.integers(0, 2_000 * FW_PER_W), st.sampled_from(sorted(MODELS)))
def test_the_cap_a_power_allows_is_the_largest_within_it(fw: int, name: str) -> None:
    model = MODELS[name]
    unm = cap_for_power(model, fw, R)
    assert power(model, Fraction(unm, UNM_PER_NM), R) * FW_PER_W <= fw
    if unm < model.t_max * UNM_PER_NM:
        assert power(model, Fraction(unm + 1, UNM_PER_NM), R) * FW_PER_W > fw


@settings(max_examples=500)
@given(
    commands,
    st.integers(0, 200 * FW_PER_W),
    st.integers(0, 60_000_000),
    st.fractions(-20, 20),
    st.integers(0, 100_000),
    st.integers(0, 100_000),
    st.sampled_from(sorted(MODELS)),
)
def test_a_clamped_command_never_asks_for_more_than_the_budget_allows(
    cmd: Command, fw: int, vcap: int, theta: Fraction, age: int, horizon: int, name: str
) -> None:
    model = MODELS[name]
    limits = MitLimits(cap_for_power(model, fw, R), vcap)
    out = clamp(model, cmd, limits, theta, age, horizon)
    if out.command is None:
        assert out.why
        return
    sent = decode(model, out.command)
    worst = worst_torque(model, sent, theta, age, horizon)
    assert worst == out.worst <= Fraction(limits.torque_unm, UNM_PER_NM)
    assert power(model, worst, R) * FW_PER_W <= fw
    assert abs(sent.v) <= Fraction(vcap, UNM_PER_NM)
    assert out.clamped == (out.command != cmd)
    assert sent.p == decode(model, cmd).p  # the set point is the application's


def test_the_largest_gains_are_scaled_down_to_the_cap() -> None:
    """kp 500, kd 5 and 18 N·m asked: 643 N·m in the worst case over 2 ms, clamped to 20."""
    cmd = encode(AK, 12.5, 50.0, 500.0, 5.0, 18.0)
    limits = MitLimits(20 * UNM_PER_NM, 50 * UNM_PER_NM)
    out = clamp(AK, cmd, limits, Fraction(124, 10), 1_000, 2_000)
    assert out.clamped and out.command is not None
    assert 19 < out.worst <= 20
    sent = decode(AK, out.command)
    assert 15 < sent.kp < 16 and 0 < sent.kd < Fraction(16, 100) and 0 < sent.t < 1
    # far from the set point, the smallest kp step alone is over a small cap: kp goes to 0
    far = clamp(AK, cmd, MitLimits(2 * UNM_PER_NM, 50 * UNM_PER_NM), Fraction(-12), 0, 20_000)
    assert far.command is not None and decode(AK, far.command).kp == 0


def test_the_position_may_drift_over_the_horizon() -> None:
    """At the position asked for, a stiff command can still ask for kp·Ω·horizon."""
    cmd = encode(DM, 0.0, 0.0, 100.0, 0.0, 0.0)
    theta = decode(DM, cmd).p
    near = worst_torque(DM, decode(DM, cmd), theta, 0, 0)
    later = worst_torque(DM, decode(DM, cmd), theta, 0, 10_000)
    assert near < Fraction(1, 100) and later > 29  # 100 · 30 rad/s · 10 ms
    out = clamp(DM, cmd, MitLimits(UNM_PER_NM, 30 * UNM_PER_NM), theta, 0, 10_000)
    assert out.command is not None and decode(DM, out.command).kp < Fraction(35, 10)


def test_a_command_inside_the_cap_passes_untouched_and_no_cap_refuses() -> None:
    cmd = encode(DM, 0.5, 1.0, 0.0, 0.1, 0.5)
    full = MitLimits(10 * UNM_PER_NM, 30 * UNM_PER_NM)
    assert clamp(DM, cmd, full, Fraction(0), 0, 20_000).command == cmd
    refused = clamp(DM, cmd, MitLimits(0, 0), Fraction(0), 0, 20_000)
    assert refused.command is None and refused.why is not None


def test_the_envelope_is_mechanical_plus_copper_rounded_up() -> None:
    profile = MitProfile(DM)
    env = profile.envelope(MitLimits(2 * UNM_PER_NM, 0))
    exact = 2 * 30 + Fraction(3, 2) * Fraction(85, 100) * (2 / Fraction(945, 1000)) ** 2
    assert env.fw >= exact * FW_PER_W > env.fw - 1
    with pytest.raises(ValueError, match="no phase resistance"):
        MitProfile(AK)
    assert MitProfile(AK, Fraction(1, 5)).resistance == Fraction(1, 5)


def test_frames_that_reach_the_motor_outside_mit_mode_are_named() -> None:
    from canergy.devices.mit import side_channel

    assert side_channel(DM, 1, 0x201, False) == "Damiao mode frame 0x201 (not MIT)"
    assert side_channel(DM, 1, 0x7FF, False) == "Damiao parameter frame 0x7FF"
    assert side_channel(DM, 1, 0x202, False) is None and side_channel(DM, 1, 0x001, False) is None
    assert side_channel(AK, 3, 0x303, True) == "CubeMars servo-mode frame 0x303 (not MIT)"
    assert side_channel(AK, 3, 0x0CE00103, True) is None  # a canergy frame
    assert side_channel(AK, 3, 0x303, False) is None
