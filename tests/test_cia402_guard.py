"""The CiA 402 guard against the emulated drive in virtual time (``firmware_model.drive.cosim``):
the supervisor service, the guard and the host loop as ``canergy supervisor --cia402`` runs them.

Every scenario checks the guarantee: what the drive drew (the emulator's exact figure) never
exceeds what the supervisor granted plus peak power × (PDO period + host reaction + stop time).
"""

from __future__ import annotations

import pytest

from canergy.cia402.meter import overshoot_bound_uj
from canergy.ledger import ledger_from_status
from canergy.units import UJ_PER_J
from firmware_model.drive.cosim import STEP_US, Result, Scenario, run

POWERLESS = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "FAULT")


def within_bound(r: Result, silence_us: int = 0) -> bool:
    bound = r.bound_uj + overshoot_bound_uj(round(r.peak_power_w * 1e6), silence_us, 0, 0)
    return r.drawn_uj <= r.granted_uj + bound


@pytest.mark.parametrize("pdo_ms", [1, 10, 50])
def test_a_velocity_profile_exhausts_2_j_and_the_drive_stops_inside_the_bound(pdo_ms: int) -> None:
    r = run(Scenario(pdo_period_us=pdo_ms * 1000))
    assert r.granted_uj == 2 * UJ_PER_J
    assert "OPERATION ENABLED" in r.states  # it ran ...
    assert r.states[-1] in POWERLESS  # ... and was stopped
    assert r.guard["stop_reason"] == "budget exhausted"
    assert abs(r.drive["velocity_rad_s"]) < 0.01
    assert r.stop_us is not None and r.tail_uj is not None
    assert within_bound(r)
    assert r.tail_uj <= r.bound_uj  # the stop itself cost less than the bound allows
    assert r.guard["usable_uj"] == 0 and r.guard["spent_uj"] == r.granted_uj
    assert ledger_from_status(r.supervisor, []).passive  # the books close over the proxy


def test_without_its_stop_commands_the_drive_runs_far_past_the_bound() -> None:
    """The check above can fail: stop commands that never arrive let the drive run on."""
    r = run(Scenario(drop_stops=True))
    assert r.states[-1] == "OPERATION ENABLED"
    assert r.stop_us is None
    nominal = overshoot_bound_uj(round(r.peak_power_w * 1e6), 10_000, 2_000 + STEP_US, 200_000)
    assert r.drawn_uj > r.granted_uj + nominal


def test_a_reserve_as_large_as_the_bound_keeps_the_drive_inside_its_grant() -> None:
    first = run(Scenario(pdo_period_us=10_000))
    r = run(Scenario(budget_uj=5 * UJ_PER_J, reserve_uj=first.bound_uj))
    assert r.states[-1] in POWERLESS and r.guard["stop_reason"] == "budget exhausted"
    assert r.drawn_uj <= r.granted_uj
    assert r.guard["overrun_uj"] == 0


def test_top_ups_keep_the_drive_running() -> None:
    r = run(Scenario(budget_uj=50 * UJ_PER_J, target_uj=UJ_PER_J, duration_us=4_000_000))
    assert ledger_from_status(r.supervisor, []).passive
    enabled = r.states.index("OPERATION ENABLED")
    assert r.states[enabled:] == ["OPERATION ENABLED"]  # never stopped once running
    assert r.guard["stops"] == 0
    assert r.granted_uj > 3 * UJ_PER_J  # far more than one target's worth went through
    assert within_bound(r)


def test_lost_tpdos_stop_the_drive_and_latch() -> None:
    sc = Scenario(budget_uj=50 * UJ_PER_J, target_uj=UJ_PER_J, pdo_loss_at_us=1_500_000)
    r = run(sc)
    assert r.guard["stop_reason"] == "TPDOs stopped" and r.guard["latched"]
    assert r.states[-1] in POWERLESS
    assert abs(r.drive["velocity_rad_s"]) < 0.05
    # the silence before the timeout was not metered: it joins the bound
    assert within_bound(r, silence_us=max(5 * sc.pdo_period_us, 50_000))


def test_a_drive_fault_freezes_its_budget() -> None:
    sc = Scenario(budget_uj=50 * UJ_PER_J, target_uj=UJ_PER_J, fault_at_us=1_500_000)
    r = run(sc)
    assert r.states[-1] == "FAULT"
    after = [row for row in r.timeline if row[0] >= sc.fault_at_us + 500_000]
    assert after and {row[1] for row in after} == {after[0][1]}  # nothing granted any more
    assert {row[2] for row in after} == {after[0][2]}  # nothing spent, nothing returned
    assert after[0][2] > 0  # and the budget it held is still there
    assert r.guard["alive"] is False
    assert within_bound(r)


def test_a_host_crash_stops_the_drive_through_its_heartbeat_consumer() -> None:
    sc = Scenario(
        budget_uj=50 * UJ_PER_J,
        target_uj=UJ_PER_J,
        host_crash_at_us=1_500_000,
        consumer_timeout_ms=200,
    )
    r = run(sc)
    assert r.states[-1] == "FAULT"
    assert r.drive["fault_reason"] == "heartbeat consumer timeout"
    history = r.drive["history"]
    reaction = next(h["time_us"] for h in history if h["state"] == "FAULT REACTION ACTIVE")
    # the last heartbeat came at most one heartbeat period (50 ms) before the crash
    assert sc.host_crash_at_us < reaction <= sc.host_crash_at_us + 200_000 + STEP_US
    fault = next(h["time_us"] for h in history if h["state"] == "FAULT")
    silence = reaction - sc.host_crash_at_us + sc.pdo_period_us
    bound = overshoot_bound_uj(round(r.peak_power_w * 1e6), silence, 0, fault - reaction)
    assert r.drawn_uj <= r.granted_uj + bound


def test_tpdos_that_come_back_find_the_stop_finished_and_the_drive_left_off() -> None:
    r = run(
        Scenario(
            budget_uj=50 * UJ_PER_J,
            target_uj=UJ_PER_J,
            pdo_loss_at_us=1_000_000,
            pdo_back_at_us=1_300_000,
        )
    )
    assert r.guard["guard"] == "stopped" and r.guard["latched"]
    assert r.states[-1] in POWERLESS  # the guard does not enable it again
    assert r.guard["usable_uj"] > 0  # though it holds budget


def test_a_drive_enabled_without_budget_is_stopped_at_once() -> None:
    sc = Scenario(budget_uj=0, auto_enable=False, app_enables_at_us=500_000, duration_us=1_500_000)
    r = run(sc)
    assert "OPERATION ENABLED" in r.states and r.states[-1] in POWERLESS
    assert r.granted_uj == 0 and r.guard["stops"] == 1
    assert r.drawn_uj <= r.bound_uj


def test_enabling_never_cuts_a_quick_stop_short() -> None:
    from canergy.live.cia402_link import enable_step

    assert enable_step("QUICK STOP ACTIVE") == 0x0000  # disable voltage, not enable operation
    assert enable_step("SWITCH ON DISABLED") == 0x0006  # shutdown
    assert enable_step("SWITCHED ON") == 0x000F
    assert enable_step("FAULT") is None and enable_step("FAULT REACTION ACTIVE") is None


def test_tpdos_lost_while_stopped_latch_too() -> None:
    """A drive stopped for want of budget whose TPDOs then stop is never enabled by the guard."""
    from canergy.cia402.guard import DriveGuard, GuardConfig
    from canergy.cia402.meter import MeterConfig

    guard = DriveGuard(10, GuardConfig(MeterConfig(rated_torque_mnm=500), auto_enable=True), 0, 1)
    guard.on_ready(0)
    guard.on_values(10_000, {0x6041: 0x40, 0x6077: 0, 0x606C: 0}, "SWITCH ON DISABLED")
    assert guard.phase.value == "stopped" and not guard.latched
    guard.on_wakeup(10_000 + guard.config.pdo_timeout_us + 1)
    assert guard.latched and guard.stop_reason == "no budget yet"
