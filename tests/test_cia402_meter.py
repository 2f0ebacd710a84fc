"""The drive meters: sampled power (exact integers, never under-metered where power is monotone),
the envelope of a drive's limits and its bound, and a wrapping energy counter."""

from __future__ import annotations

from fractions import Fraction

import pytest
from hypothesis import given
from hypothesis import strategies as st

from canergy.cia402.counter import CounterConfig, CounterMeter
from canergy.cia402.envelope import Limits, Ratings, StopKind, Timings, bound
from canergy.cia402.meter import (
    CURRENT_ACTUAL,
    DC_LINK_VOLTAGE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    EnergyMeter,
    MeterConfig,
    MeterKind,
)
from canergy.cia402.profile import Cia402Profile
from canergy.units import UJ_PER_J

MECH = MeterConfig(rated_torque_mnm=500, rated_current_ma=5000)


def values(torque: int, velocity: int, current: int = 0) -> dict[int, int]:
    return {TORQUE_ACTUAL: torque, VELOCITY_ACTUAL: velocity, CURRENT_ACTUAL: current}


def test_constant_mechanical_power_is_exact() -> None:
    meter = EnergyMeter(MECH)
    # 500 ‰ of 0.5 N·m = 0.25 N·m at 100 rad/s (100,000 mrad/s): 25 W; each value may be one
    # unit off, so the meter charges 501 ‰ at 100.001 rad/s = 25.05025 W: 25.05025 J in 1 s
    for t in range(0, 1_000_001, 10_000):
        meter.sample(t, values(500, 100_000))
    assert meter.metered_uj == 25_050_250


def test_copper_losses_from_current_and_resistance() -> None:
    meter = EnergyMeter(
        MeterConfig(rated_torque_mnm=500, rated_current_ma=5000, resistance_mohm=1000)
    )
    # rated current 5 A through 1 Ω, standing still: 1001 ‰ of 5 A = 5.005 A, 25.050025 W; the
    # torque and velocity allowance adds 1 ‰ × 0.5 N·m × 1 mrad/s = 0.5 µW
    meter.sample(0, values(0, 0, 1000))
    meter.sample(2_000_000, values(0, 0, 1000))
    assert meter.metered_uj == 50_100_051


def test_electrical_metering() -> None:
    meter = EnergyMeter(
        MeterConfig(kind=MeterKind.SAMPLED_ELECTRICAL, bus_current_index=0x2010),
    )
    meter.sample(0, {DC_LINK_VOLTAGE: 24_000, 0x2010: 1_000})
    meter.sample(500_000, {DC_LINK_VOLTAGE: 24_000, 0x2010: 1_000})
    assert meter.metered_uj == 12_012_500  # 24.001 V × 1.001 A for 0.5 s


def test_nothing_metered_until_every_needed_value_was_seen() -> None:
    meter = EnergyMeter(MECH)
    assert meter.sample(0, {TORQUE_ACTUAL: 1000}) == 0
    assert meter.sample(1_000_000, {TORQUE_ACTUAL: 1000}) == 0
    assert meter.samples == 0


def test_power_flowing_back_is_not_credited_unless_configured() -> None:
    plain = EnergyMeter(MECH)
    credit = EnergyMeter(MeterConfig(rated_torque_mnm=500, credit_regen=True))
    for meter in (plain, credit):
        meter.sample(0, values(-500, 100_000))  # braking: -25 W
        meter.sample(1_000_000, values(-500, 100_000))
        meter.sample(2_000_000, values(500, 100_000))  # driving: +25 W
        meter.sample(3_000_000, values(500, 100_000))
    # braking counts at its smallest magnitude (499 ‰ at 99.999 rad/s: 24.9497505 W), driving at
    # its largest (25.05025 W); the braking-to-driving interval at its larger end
    assert plain.metered_uj == 50_100_501  # 2 s × 25.05025 W
    assert plain.regen_uj == 24_949_750
    # the 24.95 J that flowed back paid for most of a second of driving
    assert credit.metered_uj == 25_150_750


def test_a_fractional_power_rounds_up() -> None:
    meter = EnergyMeter(MeterConfig(rated_torque_mnm=1, velocity_unit_rad_s=Fraction(1, 3)))
    # 1 ‰ of 1 mN·m at 1/3 rad/s, each one unit up: 2e-6 N·m × 2/3 rad/s = 1,333,333,333.3 fW
    assert meter.config.power_fw(values(1, 1)) == 1_333_333_334
    meter.sample(0, values(1, 1))
    meter.sample(3_000_000, values(1, 1))  # 3 s of it: just over 4 µJ
    assert meter.metered_uj == 4


@given(
    st.lists(
        st.tuples(st.integers(1, 50_000), st.integers(-3000, 3000), st.integers(-300_000, 300_000)),
        min_size=2,
        max_size=60,
    )
)
def test_never_below_the_energy_of_linear_power_between_samples(
    rows: list[tuple[int, int, int]],
) -> None:
    """Power that moves linearly between samples (monotone) is never under-metered, and the
    meter charges at most the larger end of each interval, each value one unit up."""
    meter = EnergyMeter(MECH)
    t, reference, ceiling, last = 0, Fraction(0), Fraction(0), None
    for dt, torque, velocity in rows:
        t += dt
        meter.sample(t, values(torque, velocity))
        power = Fraction(torque * 500 * velocity, 10**9)  # W
        high = Fraction((abs(torque) + 1) * 500 * (abs(velocity) + 1), 10**9)
        if last is not None:
            lt, lp, lh = last
            reference += max((lp + power) / 2, Fraction(0)) * (t - lt) / 10**6
            ceiling += max(lh, high) * (t - lt) / 10**6
        last = (t, power, high)
    assert meter.metered_uj >= reference * 10**6 - 1
    assert meter.metered_uj <= ceiling * 10**6


RATINGS = Ratings(500, 5000, Fraction(1, 1000), 1000)
"""The emulator's motor: 0.5 N·m and 5 A rated, velocity in mrad/s, 1 Ω."""


def test_the_envelope_is_torque_times_speed_plus_copper() -> None:
    # 265 ‰ of 0.5 N·m = 0.1325 N·m at 100.5 rad/s: 13.31625 W; 1.325 A² × 1 Ω = 1.755625 W
    assert RATINGS.envelope_fw(Limits(265, 265, 100_500)) == 15_071_875 * 10**9
    assert RATINGS.envelope_fw(Limits(265, 265, 100_500).closed()) == 0
    assert RATINGS.envelope_fw(Limits(1, 0, 1)) == 500_000_000  # 0.5 mN·m × 1 mrad/s, exact
    halves = [RATINGS.envelope_fw(Limits(265, 265, 100_500).tapered(k)) for k in range(4)]
    assert halves == sorted(halves, reverse=True) and halves[3] < halves[0] // 7


def test_the_bound_is_the_envelope_over_the_notice_time_plus_the_stop() -> None:
    limits = Limits(265, 265, 100_500)
    timings = Timings(gap_us=25_000, reaction_us=2_500, latency_us=500, stop_timeout_us=100_000)
    coast = bound(Cia402Profile(RATINGS), limits, timings)
    assert coast.notice_uj == 422_013  # 15.071875 W × 28 ms, rounded up
    assert coast.stop_uj == 0 and coast.total_uj == 422_013
    quick = bound(Cia402Profile(RATINGS, StopKind.QUICK, 2_000_000), limits, timings)
    # copper 1.755625 W × 103 ms + 0.1325 N·m × (100.5 rad/s)² / (2 × 2,000 rad/s²)
    assert quick.stop_uj == round(1.755625 * 0.103 * 1e6 + 0.1325 * 100.5**2 / 4000 * 1e6) + 1
    slow = bound(Cia402Profile(RATINGS, StopKind.QUICK, 1), limits, timings)
    assert slow.stop_uj == -(-15_071_875 * 103_000 // 10**6)  # never above the envelope
    counted = bound(Cia402Profile(RATINGS), limits, timings, resolution_uj=1000)
    assert counted.total_uj == coast.total_uj + 1000


def test_a_counter_is_read_across_its_wrap() -> None:
    meter = CounterMeter(CounterConfig(0x2100, node=20, bits=16, unit_uj=1000))
    assert meter.sample(0, 65_000, envelope_fw=15 * 10**15) == 0  # the first reading: a start
    assert meter.sample(20_000, 65_300, envelope_fw=15 * 10**15) == 300_000
    assert meter.sample(40_000, 100, envelope_fw=15 * 10**15) == 336_000  # 65,536 + 100 - 65,300
    assert meter.ambiguous == 0 and meter.metered_uj == 636_000


def test_a_counter_that_may_have_turned_over_is_charged_at_the_most() -> None:
    meter = CounterMeter(CounterConfig(0x2100, bits=8, unit_uj=1000))  # 256 mJ a turn
    meter.sample(0, 10, envelope_fw=10**15)
    # 1 W for 600 ms may be 600 mJ: 20 counts read could be 20, 276 or 532 mJ
    assert meter.sample(600_000, 30, envelope_fw=10**15) == 532_000
    assert meter.ambiguous == 1


@given(st.lists(st.integers(0, 70_000_000), min_size=1, max_size=40))
def test_a_counter_never_charges_less_than_was_drawn(steps: list[int]) -> None:
    """Whatever is drawn between readings (within the envelope), a 16-bit mJ counter charges at
    least that, minus the count it has not shown yet."""
    meter = CounterMeter(CounterConfig(0x2100, bits=16, unit_uj=1000))
    drawn, t = 0, 0
    meter.sample(t, 0, envelope_fw=0)
    for step in steps:  # at most 70 J in 1 s: 70 W
        drawn += step
        t += 1_000_000
        meter.sample(t, drawn // 1000, envelope_fw=70 * 10**15)
    assert drawn - 1000 < meter.metered_uj <= 70 * UJ_PER_J * len(steps)


def test_a_cia402_drive_is_a_device_profile() -> None:
    """The profile interface on CiA 402's objects: the envelope with its parts in SI units
    (they give its figure back), closed limits allow nothing, a limit read back otherwise is
    named with both values, a coasting stop draws nothing and a quick stop its ramp."""
    limits = Limits(265, 265, 100_500)
    profile = Cia402Profile(RATINGS, StopKind.QUICK, 2_000_000)
    env = profile.envelope(limits)
    p = env.parts
    assert env.fw == RATINGS.envelope_fw(limits)
    assert p["torque_nm"] * p["speed_rad_s"] + p["resistance_ohm"] * p["current_a"] ** 2 == (
        pytest.approx(env.fw / 1e15)
    )
    assert profile.envelope(profile.closed(limits)).fw == 0
    assert profile.mismatch(limits, limits) is None
    assert profile.mismatch(limits, Limits(265, 3000, 100_500)) == (
        "0x6073 read back 3000, written 265"
    )
    assert Cia402Profile(RATINGS).stop_fw_us(limits, 100_000) == 0
    assert 0 < profile.stop_fw_us(limits, 100_000) < env.fw * 100_000
