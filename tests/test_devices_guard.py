"""The device guard (``canergy.devices.guard``) with the ODrive profile, sans-IO, in explicit
time: the envelope's formula, limits read back at set-up, limits written behind the guard
charged from the moment they were seen, and a stop that is not obeyed made STUCK."""

from __future__ import annotations

import math
from fractions import Fraction

from canergy.devices.clock import STRETCHES_KEPT, ClockCharge
from canergy.devices.guard import DeviceConfig, DeviceGuard, GuardPhase
from canergy.devices.odrive import MotorConstants, OdriveLimits, OdriveProfile
from canergy.devices.profile import ReadLimits, Stop, WriteLimits

FULL = OdriveLimits(5.0, 2.0)
MOTOR = MotorConstants(Fraction(1, 20), Fraction(1, 2), Fraction(6, 5), Fraction(24))


def guard(trust: bool = False) -> DeviceGuard[OdriveLimits]:
    config = DeviceConfig(limits=FULL, trust_limits=trust, latency_us=5_000, reaction_us=10_000)
    return DeviceGuard(3, OdriveProfile(MOTOR), config, 0, 1)


def ready(g: DeviceGuard[OdriveLimits]) -> None:
    g.on_ready(10_000, 0, FULL, OdriveLimits(5.0, 0.0))


def test_the_envelope_is_the_smaller_of_motor_and_supply_terms_never_below_the_true_one() -> None:
    profile = OdriveProfile(MOTOR)
    e = profile.envelope(FULL)
    omega = 2 * math.pi * 1.2 * 5.0
    motor_w = 0.05 * 2.0 * omega + 1.5 * 0.5 * 2.0**2  # 6.7699 W, below 24 V · 2 A
    assert motor_w * 1e15 <= e.fw <= motor_w * 1e15 * (1 + 1e-6)
    assert e.parts["supply_term_w"] == 48.0
    # a low supply bounds a fast motor: V_bus·i_lim
    low = OdriveProfile(MotorConstants(MOTOR.torque_constant, MOTOR.resistance, bus_voltage=2))
    assert low.envelope(FULL).fw == 4 * 10**15
    low.observe({"bus_voltage_v": 3.0})
    low.observe({"bus_voltage_v": 1.0})  # raised to what was measured, never lowered
    assert low.envelope(FULL).fw == 6 * 10**15


def test_a_limit_that_does_not_read_back_is_refused_by_name() -> None:
    g = guard()
    g.on_ready(10_000, 0, OdriveLimits(4.0, 2.0), OdriveLimits(5.0, 0.0))
    assert g.refused == "limits not taken: velocity limit reads 4 rev/s, written 5"
    assert g.latched and not g.alive(10_000)


def test_limits_that_cannot_be_read_back_need_trust() -> None:
    g = guard()
    g.on_ready(10_000, 0, None, None)
    assert g.refused is not None and "--odrive-trust-limits" in g.refused
    trusted = guard(trust=True)
    trusted.on_ready(10_000, 0, None, None)
    assert trusted.refused is None and trusted.verified is False


def test_limits_written_behind_the_guard_are_charged_from_when_they_were_seen() -> None:
    g = guard()
    ready(g)
    g.on_wakeup(50_000)
    setup_uj = g.metered_uj  # the full limits from the set-up's start to the closed ones
    assert abs(setup_uj - g.profile.envelope(FULL).fw * 15_000 / 10**15) < 1
    raised = OdriveLimits(20.0, 20.0)
    g.on_foreign_limits(100_000, 90_000, raised)
    (write,) = [c for c in g.commands if isinstance(c, WriteLimits)][-1:]
    assert write.at == 100_000  # the guard's own limits again, at once
    g.on_limits(102_000, write.limits, write.limits, write.at)  # read back: the device took them
    g.on_wakeup(200_000)
    raised_fw = g.profile.envelope(raised).fw
    # 90 ms to 102 ms at the raised envelope, then the latency (5 ms) before it counts as lowered
    expected = setup_uj + raised_fw * (107_000 - 90_000) / 10**15
    assert abs(g.metered_uj - expected) <= 2
    assert g.foreign is None and g.bound_max_uj >= g.bound(raised).total_uj  # type: ignore[union-attr]


def test_an_axis_powered_after_its_stop_is_stuck_and_the_stop_is_repeated() -> None:
    g = guard()
    ready(g)
    g.on_feedback(20_000, 20_000, True, "CLOSED_LOOP_CONTROL")  # powered: the guard holds it
    assert g.phase is GuardPhase.STOPPING and isinstance(g.commands[-1], Stop)
    stop_at = g.phase_at
    # a heartbeat sent before the stop could act shows nothing
    g.on_feedback(stop_at + 1_000, stop_at + 1_000, False, "IDLE")
    assert g.phase is GuardPhase.STOPPING
    t = stop_at
    while t < stop_at + 600_000:
        t += 50_000
        g.on_feedback(t, t, True, "CLOSED_LOOP_CONTROL")
        g.on_wakeup(t)
    assert g.phase is GuardPhase.STUCK
    assert g.stuck == "still powered 500 ms after the stop"
    assert sum(isinstance(c, Stop) for c in g.commands) >= 5  # every 100 ms
    assert not g.alive(t) and g.status(t)["guard"] == "stuck"
    g.on_feedback(t + 50_000, t + 50_000, False, "IDLE")  # it obeys at last, it seems
    assert g.phase is GuardPhase.STUCK  # one quiet reply: not yet (a whole notice quiet)
    g.on_feedback(t + 100_000, t + 100_000, False, "IDLE")
    assert g.phase is GuardPhase.STOPPED and g.stuck is None


def test_a_stop_heard_only_within_its_notice_is_stuck_as_such_not_as_unheard() -> None:
    """A notice longer than the stop timeout (a slow reaction) leaves every reply that comes
    before the timeout too early to show the stop's effect: STUCK, named for what was heard."""
    config = DeviceConfig(limits=FULL, latency_us=5_000, reaction_us=600_000)
    g = DeviceGuard(3, OdriveProfile(MOTOR), config, 0, 1)
    ready(g)
    g.on_feedback(20_000, 20_000, True, "CLOSED_LOOP_CONTROL")
    stop_at = g.phase_at
    t = stop_at
    while g.phase is GuardPhase.STOPPING:
        t += 50_000
        g.on_feedback(t, t, False, "IDLE")  # powerless, but within the notice
        g.on_wakeup(t)
    assert t == stop_at + 550_000 and g.notice_us() > 500_000
    notice = g.notice_us() / 1000
    assert g.stuck == f"heard 500 ms after the stop only within its notice ({notice:g} ms)"
    unheard = guard()
    ready(unheard)
    unheard.on_feedback(20_000, 20_000, True, "CLOSED_LOOP_CONTROL")
    unheard.on_wakeup(unheard.phase_at + 600_000)
    assert unheard.stuck == "not heard for 500 ms after the stop"


def test_limits_written_behind_the_guard_that_never_read_back_stop_the_device_for_good() -> None:
    """The guard writes its own limits over an application's at once; while no read-back
    shows them in force, the application's are charged, and past the feedback timeout (300 ms)
    the device is stopped for good, the write named."""
    g = guard()
    ready(g)
    g.on_feedback(20_000, 20_000, False, "IDLE")
    raised = OdriveLimits(20.0, 20.0)
    g.on_foreign_limits(100_000, 99_000, raised)
    (write,) = [c for c in g.commands if isinstance(c, WriteLimits)][-1:]
    assert g.next_wakeup() <= 100_000 + 300_000 + 1
    t = 100_000
    while t < 450_000:  # the device answers no read-back
        t += 50_000
        g.on_limits(t, write.limits, None, write.at)
        g.on_feedback(t, t, False, "IDLE")
        g.on_wakeup(t)
        assert g.foreign == raised  # charged meanwhile
    assert g.latched and g.refused == (
        "a write behind the guard (limits velocity_rev_s 20, current_a 20) not verified in time"
    )
    assert g.status(t)["unverified"] == "limits velocity_rev_s 20, current_a 20"
    assert not g.alive(t) and g.phase is not GuardPhase.RUNNING


def test_limits_changed_where_the_guard_cannot_see_are_found_by_the_periodic_read_back() -> None:
    """Every ``reread_us`` the guard reads its limits back without writing them: limits that
    differ from those it last confirmed stop the device for good, named; a read asked before
    the guard's own write was confirmed shows nothing."""
    config = DeviceConfig(limits=FULL, reread_us=1_000_000)
    g = DeviceGuard(3, OdriveProfile(MOTOR), config, 0, 1)
    ready(g)
    closed = OdriveLimits(5.0, 0.0)
    assert g.next_wakeup() <= 1_000_000
    g.on_wakeup(1_000_000)
    (ask,) = [c for c in g.commands if isinstance(c, ReadLimits)]
    g.on_read(1_002_000, closed)  # as confirmed: nothing
    assert g.refused is None
    g.on_wakeup(2_000_000)
    g.on_limits(2_001_000, closed, closed, 2_000_500)  # confirmed after the read was asked
    g.on_read(2_002_000, OdriveLimits(5.0, 20.0))  # may predate it: shows nothing
    assert g.refused is None
    g.on_wakeup(3_000_000)
    g.on_read(3_002_000, OdriveLimits(5.0, 20.0))  # changed over USB, say
    assert g.latched and g.refused == (
        "limits changed behind the guard (a periodic read-back): current limit reads 20 A, "
        "written 0"
    )
    assert ask.why == "periodic read-back"


def test_limits_the_periodic_read_back_finds_are_charged_from_the_read_on() -> None:
    """Found changed, the limits read are in force (since the read was asked at the latest)
    until the guard's own, written at once, read back: charged at their envelope and in the
    bound, not at the closed limits the guard last confirmed (0 W)."""
    config = DeviceConfig(limits=FULL, reread_us=1_000_000)
    g = DeviceGuard(3, OdriveProfile(MOTOR), config, 0, 1)
    ready(g)
    usb = OdriveLimits(50.0, 40.0)
    g.on_wakeup(1_000_000)
    before = g.metered_uj + g.uncontained_uj
    g.on_read(1_002_000, usb)
    assert g.latched and g.refused is not None
    assert g.in_force_fw(1_002_000) >= g.profile.envelope(usb).fw > 0
    g.charge(1_012_000)  # 12 ms on, not read back yet: charged from the read's ask on
    charged = g.metered_uj + g.uncontained_uj - before
    assert charged * 10**15 >= g.profile.envelope(usb).fw * 12_000
    bound = g.status(1_012_000)["bound_uj"]
    assert bound is not None and bound >= g.bound(usb).total_uj  # type: ignore[union-attr]


def test_a_periodic_read_back_left_unanswered_stops_the_device_for_good() -> None:
    """Reads the device never answers (firmware with other endpoints, a read filtered away):
    past the feedback timeout from the first unanswered one, the device is stopped for good,
    as an unverified write is; before, the guard asked every second for ever, still
    ``limits_verified``."""
    config = DeviceConfig(limits=FULL, reread_us=1_000_000, feedback_timeout_us=300_000)
    g = DeviceGuard(3, OdriveProfile(MOTOR), config, 0, 1)
    ready(g)
    t = 1_000_000
    while t <= 5_000_000:
        g.on_feedback(t, t, powered=True)
        if t % 1_000_000 == 0:
            g.on_wakeup(t)
            g.on_read(t + 2_000, None)  # the link found no answer
        t += 50_000
    assert g.latched and g.refused is not None
    assert "periodic read-back unanswered" in g.refused, g.refused


def _stuck_for(quiet_every_other: bool) -> tuple[DeviceGuard[OdriveLimits], int]:
    """An axis powered behind the guard that ignores the stop for 5 s (feedback every 50 ms),
    or, ``quiet_every_other``, shows its power stage off in one reply of two once STUCK."""
    g = DeviceGuard(3, OdriveProfile(MOTOR), DeviceConfig(limits=FULL, stuck_limits=WHOLE), 0, 1)
    ready(g)
    g.on_feedback(20_000, 20_000, powered=True)  # powered behind the guard: stopped
    t, end = 20_000, 5_000_000
    while t < end:
        t += 50_000
        quiet = quiet_every_other and g.phase is GuardPhase.STUCK and (t // 50_000) % 2 == 0
        g.on_feedback(t, t, powered=not quiet)
        g.on_wakeup(t)
    g.charge(end)
    return g, end


WHOLE = OdriveLimits(50.0, 40.0)


def test_a_stuck_device_that_shows_its_power_off_for_a_moment_is_still_stuck() -> None:
    """One quiet reply between powered ones is no stop: the device stays STUCK, booked
    uncontained at its whole envelope all along, as one that never showed it off. Before, each
    quiet reply booked it STOPPED and each return to STUCK restarted the booking later (about
    12 % less in the review's run)."""
    flicker, end = _stuck_for(True)
    steady, _ = _stuck_for(False)
    assert flicker.phase is GuardPhase.STUCK and steady.phase is GuardPhase.STUCK
    assert flicker.uncontained_uj == steady.uncontained_uj > 0
    fw = flicker.profile.envelope(WHOLE).fw
    assert flicker.uncontained_uj * 10**15 >= fw * (end - 20_000 - flicker.notice_us())


def test_limits_seen_late_are_charged_back_against_what_each_stretch_was_charged_at() -> None:
    """A write behind the guard seen at 90 ms and taken in at 100 ms, after another one (lower)
    seen and taken in at 95 ms had raised the envelope in force: 90-95 ms was charged at the
    closed limits, not at the envelope in force at 100 ms, and is charged back from there (as
    a guard that never saw the lower write charges it)."""
    first, second = OdriveLimits(20.0, 10.0), OdriveLimits(20.0, 20.0)
    both, alone = guard(), guard()
    for g in (both, alone):
        ready(g)
        g.on_wakeup(50_000)
    both.on_foreign_limits(95_000, 95_000, first)
    for g in (both, alone):
        g.on_foreign_limits(100_000, 90_000, second)
        g.on_wakeup(101_000)
    assert both.metered_uj >= alone.metered_uj > 0
    # 90-101 ms at the higher write's envelope at least, over the closed limits' charge
    closed_fw = alone.profile.envelope(OdriveLimits(5.0, 0.0)).fw
    lacking = (alone.profile.envelope(second).fw - closed_fw) * 11_000 // 10**15
    assert both.metered_uj >= lacking


def test_a_late_finding_older_than_the_stretches_kept_counts_that_time_as_charged_at_nothing() -> (
    None
):
    clock = ClockCharge()
    clock.start(0, 1)
    for t in range(1, STRETCHES_KEPT + 11):  # an envelope of 1 or 2 fW, changed every µs
        clock.run(t, lambda t: 1 + t % 2)
    oldest = clock.charged[0][0]
    assert len(clock.charged) == STRETCHES_KEPT and oldest == 10
    clock.remainder = 0
    clock.back_charge(0, 5)
    end = STRETCHES_KEPT + 10
    # kept: (5 - 1 or 2) each µs from 10 on; before them: all 5
    lacking = sum(5 - (1 + t % 2) for t in range(oldest, end))
    assert clock.remainder == lacking + 5 * oldest


def test_time_charged_back_is_not_charged_back_again_by_a_later_finding_over_it() -> None:
    """Writes behind the guard queued behind one stall are taken in one after another, each
    found late over the same time: the second charges only what the first left lacking (before,
    each charged it again: 10.9 kJ metered for 111 J drawn after a 0.5 s stall)."""
    clock = ClockCharge()
    clock.start(0, 1)
    clock.run(100, lambda t: 1)
    clock.remainder = 0  # what the run charged: only what is charged back counts below
    clock.back_charge(10, 5)
    once = clock.remainder
    assert once == 4 * 90
    clock.back_charge(20, 5)  # the same envelope again, over time already charged back
    assert clock.remainder == once
    clock.back_charge(50, 7)  # a higher one: what 5 lacks from 50 on
    assert clock.remainder == once + 2 * 50
    clock.back_charge(0, 7)  # before 10 (charged at 1) and 10-50 (charged at 5)
    total = once + 2 * 50 + 6 * 10 + 2 * 40
    assert clock.remainder == total
    clock.run(150, lambda t: 1)  # charged on at 1, then found late again over all of it
    clock.back_charge(0, 7)
    assert clock.remainder == total + 50 + 6 * 50


def test_limits_seen_late_are_metered_and_booked_when_taken_in() -> None:
    """A write behind the guard taken in 80 ms after its frame arrived: what it charges back
    over those 80 ms is metered and booked in that same call. It once waited in the clock's
    remainder for the clock's next run, which a host that exits first never makes (the last
    status of a run of tests/test_vcan_odrive.py showed 3.1 J metered of 16.8 J drawn)."""
    g = guard()
    ready(g)
    g.on_wakeup(100_000)
    before = g.metered_uj
    raised = OdriveLimits(20.0, 20.0)
    g.on_foreign_limits(180_000, 100_000, raised)  # the clock ran to 180 ms before it
    closed_fw = g.profile.envelope(OdriveLimits(5.0, 0.0)).fw
    lacking = (g.profile.envelope(raised).fw - closed_fw) * 80_000 // 10**15
    assert lacking > 30_000_000  # 450 W over 80 ms
    assert g.metered_uj - before >= lacking
    assert g.clock.remainder < 10**15  # no whole µJ left for later
    assert g.client.state.spent + g.debt_uj == g.metered_uj  # booked: spent, or debt


def test_the_exit_charges_up_to_the_latency_past_the_stop_and_books_it() -> None:
    """The host exits at 160 ms, its stop on the bus, an application's limits taken in late and
    not written over yet: charged at their envelope up to the device's latency (5 ms) past
    then, and booked; nothing would charge it after (the last status is written next)."""
    g = guard()
    ready(g)
    g.on_wakeup(50_000)
    before = g.metered_uj
    raised = OdriveLimits(20.0, 20.0)
    g.on_foreign_limits(150_000, 90_000, raised)  # seen at 90 ms, taken in at 150 ms
    g.halt(150_000)
    g.on_exit(160_000)
    raised_fw = g.profile.envelope(raised).fw
    assert g.metered_uj - before >= raised_fw * (165_000 - 90_000) // 10**15
    assert g.clock.until == 165_000 and g.unbooked_uj == 0
    assert g.client.state.spent + g.debt_uj == g.metered_uj  # booked: spent, or debt


def test_the_exit_charges_the_last_power_reading_up_to_the_stop() -> None:
    g = DeviceGuard(3, OdriveProfile(MOTOR), DeviceConfig(limits=FULL, sampled=True), 0, 1)
    g.on_ready(10_000, 0, None, None)
    g.on_feedback(20_000, 20_000, True, None, 100.0)  # 100 W from 20 ms on
    g.halt(40_000)
    g.on_exit(50_000)
    assert g.metered_uj == 3_000_000  # 100 W × 30 ms
    assert g.client.state.spent + g.debt_uj == g.metered_uj
