"""The CiA 402 guard against the emulated drive in virtual time (``firmware_model.drive.cosim``):
the supervisor service, the guard and the host loop as ``canergy supervisor --cia402`` runs them.

Every scenario checks the guarantee of the sound modes: what the drive drew (the emulator's exact
figure) never exceeds what the supervisor granted plus the bound the guard showed, and with the
bound held back as the guard does, not even what was granted.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from canergy.cia402.envelope import StopKind
from canergy.cia402.guard import DriveGuard, GuardConfig
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.ledger import ledger_from_status
from canergy.units import UJ_PER_J
from firmware_model.drive.cosim import ENABLE, STEP_US, Result, Scenario, pulsing, run

POWERLESS = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "FAULT")
SOUND = [
    pytest.param(MeterKind.ENVELOPE, "drive", id="envelope"),
    pytest.param(MeterKind.COUNTER, "drive", id="counter-on-drive"),
    pytest.param(MeterKind.COUNTER, "meter", id="counter-on-meter-node"),
]


def within_bound(r: Result) -> bool:
    assert r.bound_uj is not None
    return r.drawn_uj <= r.granted_uj + r.bound_uj


@pytest.mark.parametrize(("kind", "where"), SOUND)
@pytest.mark.parametrize("pdo_ms", [5, 20, 50])
def test_a_velocity_profile_exhausts_2_j_and_the_drive_stops_inside_its_grant(
    kind: MeterKind, where: str, pdo_ms: int
) -> None:
    r = run(Scenario(meter=kind, counter_on=where, pdo_period_us=pdo_ms * 1000))
    assert r.granted_uj == 2 * UJ_PER_J
    assert "OPERATION ENABLED" in r.states  # it ran ...
    assert r.states[-1] in POWERLESS  # ... and was stopped
    assert r.guard["stop_reason"] == "budget exhausted"
    assert within_bound(r)
    assert r.drawn_uj <= r.granted_uj  # the guard held its bound back
    assert r.guard["taper_level"] > 0  # the limits were lowered on the way
    assert ledger_from_status(r.supervisor, []).passive  # the books close over the proxy


@pytest.mark.parametrize(("kind", "where"), SOUND)
def test_limits_writes_left_unanswered_are_written_again_and_charged_as_taken(
    kind: MeterKind, where: str
) -> None:
    """Found on vcan0: an application's SDO writes, as fast as they go, garbled every attempt
    of one of the guard's limits writes on the drive's shared SDO server; taken as a refusal,
    it latched the drive off for good. Unanswered (half of them taken by the drive all the
    same), the writes are tried again, and the drive runs and stops inside its bound."""
    r = run(Scenario(meter=kind, counter_on=where, unanswered_limits=6))
    assert "OPERATION ENABLED" in r.states and r.states[-1] in POWERLESS
    assert r.guard["stop_reason"] == "budget exhausted" and r.guard["refused"] is None
    assert within_bound(r)


@pytest.mark.parametrize(("kind", "where"), SOUND)
@pytest.mark.parametrize("pdo_ms", [5, 10, 20, 50])
def test_pulses_between_tpdos_are_charged(kind: MeterKind, where: str, pdo_ms: int) -> None:
    """The application sets 100 rad/s just after each TPDO and 0 at mid-period, at 10,000
    rad/s² both ways: a sampled meter sees none of it; the sound modes charge all of it."""
    r = run(pulsing(Scenario(meter=kind, counter_on=where, pdo_period_us=pdo_ms * 1000)))
    assert within_bound(r) and r.drawn_uj <= r.granted_uj
    assert r.metered_uj >= r.drawn_uj - 1_000  # every pulse was charged (a count at most left)


def test_a_sampled_meter_is_fooled_by_pulses_between_tpdos() -> None:
    """What the README's warning says: the sampled modes guarantee nothing."""
    sampled = Scenario(
        meter=MeterKind.SAMPLED_MECHANICAL, stop=StopKind.QUICK, pdo_period_us=50_000
    )
    r = run(pulsing(sampled, offset_us=500))
    assert r.bound_uj is None  # and it claims none
    assert r.drawn_uj > 2 * r.granted_uj
    assert r.metered_uj < r.drawn_uj / 2


@pytest.mark.parametrize(("kind", "where"), SOUND)
def test_without_its_stop_commands_the_drive_runs_far_past_the_bound(
    kind: MeterKind, where: str
) -> None:
    """The checks above can fail: stops and closings that never arrive let the drive run on."""
    r = run(Scenario(meter=kind, counter_on=where, drop_stops=True))
    assert r.states[-1] == "OPERATION ENABLED"
    assert r.bound_uj is not None and r.drawn_uj > r.granted_uj + r.bound_uj


def test_the_bound_at_a_15_w_envelope_and_20_ms_tpdos_is_at_most_half_a_joule() -> None:
    for kind in (MeterKind.ENVELOPE, MeterKind.COUNTER):
        r = run(Scenario(meter=kind, pdo_period_us=20_000))
        assert r.guard["envelope_w"] == 0  # closed at the end
        assert r.bound_uj is not None and r.bound_uj <= UJ_PER_J // 2


def test_a_reserve_smaller_than_the_bound_refuses_the_drive() -> None:
    r = run(Scenario(reserve_uj=100_000, pdo_period_us=20_000))
    assert r.guard["refused"] is not None and "exceeds --cia402-reserve" in r.guard["refused"]
    assert "--cia402-max-torque" in r.guard["refused"]  # which figure to change
    assert "OPERATION ENABLED" not in r.states and r.drawn_uj == 0


def test_a_reserve_is_kept_on_top_of_the_bound() -> None:
    r = run(Scenario(budget_uj=3 * UJ_PER_J, reserve_uj=UJ_PER_J, pdo_period_us=20_000))
    assert r.guard["refused"] is None and r.guard["stop_reason"] == "budget exhausted"
    assert r.drawn_uj <= r.granted_uj - UJ_PER_J


def test_an_envelope_is_charged_while_enabled_even_standing_still() -> None:
    r = run(Scenario(velocity=0, budget_uj=UJ_PER_J, duration_us=2_000_000))
    assert r.drawn_uj < 10_000  # it hardly drew anything ...
    assert r.granted_uj == UJ_PER_J and r.guard["stop_reason"] == "budget exhausted"
    assert r.metered_uj > UJ_PER_J // 2  # ... and paid for what it could have drawn


def test_an_envelope_is_closed_while_the_drive_is_off() -> None:
    r = run(Scenario(auto_enable=False, budget_uj=UJ_PER_J, duration_us=2_000_000))
    assert "OPERATION ENABLED" not in r.states
    assert r.guard["limits"] == {"0x6072": 0, "0x6073": 0, "0x6080": 100_500}
    assert r.metered_uj == 0 and r.guard["usable_uj"] == UJ_PER_J


def test_an_application_that_enables_the_drive_gets_torque_once_the_guard_opens_it() -> None:
    sc = Scenario(
        auto_enable=False,
        budget_uj=UJ_PER_J,
        app=tuple((500_000 + i * 1_000, index, value) for i, (index, value) in enumerate(ENABLE)),
        duration_us=2_000_000,
    )
    r = run(sc)
    assert "OPERATION ENABLED" in r.states and r.drawn_uj > 0
    assert within_bound(r) and r.drawn_uj <= r.granted_uj


def test_what_is_drawn_past_the_budget_is_a_debt_the_next_grant_pays_first() -> None:
    """A sampled meter holds no bound back: its quick stops meter past the budget."""
    sampled = {"meter": MeterKind.SAMPLED_MECHANICAL, "stop": StopKind.QUICK}
    r = run(Scenario(**sampled, duration_us=1_500_000))
    assert r.overrun_uj > 0  # metered past the budget while the drive stopped
    assert r.debt_uj == r.overrun_uj  # and nothing paid it yet: no grant came
    assert r.guard["spent_uj"] == r.granted_uj  # the proxy never spent more than it held
    books = ledger_from_status(r.supervisor, [])
    assert books.drive_debt == r.debt_uj  # the ledger counts the debt as spent
    no_debt = dict(r.supervisor, cia402={"drives": {}})
    assert books.dissipated == ledger_from_status(no_debt, [{**r.guard}]).dissipated - r.debt_uj
    topped = run(
        Scenario(**sampled, budget_uj=50 * UJ_PER_J, target_uj=200_000, max_grant_uj=200_000)
    )
    assert topped.guard["stops"] > 1 and topped.overrun_uj > 0
    assert topped.debt_uj == 0  # each grant paid the debt first
    assert topped.guard["spent_uj"] >= topped.metered_uj - topped.guard["usable_uj"]
    assert ledger_from_status(topped.supervisor, []).passive


@pytest.mark.parametrize(
    ("kind", "pause_at_us"), [(MeterKind.COUNTER, 600_000), (MeterKind.ENVELOPE, 300_000)]
)
def test_a_sound_mode_books_a_host_pause_past_the_budget_as_debt(
    kind: MeterKind, pause_at_us: int
) -> None:
    """The times the bound allows do not hold (the host away for a second): what the drive
    drew meanwhile is charged when the host is back, past the budget, as a debt; the bound is
    raised to the gap seen, so granted plus the bound still holds."""
    paused = {"meter": kind, "pauses": ((pause_at_us, 1_000_000),)}
    r = run(Scenario(**paused))
    assert r.overrun_uj > 0 and r.debt_uj == r.overrun_uj
    assert ledger_from_status(r.supervisor, []).drive_debt == r.debt_uj
    assert within_bound(r) and r.bound_uj is not None and r.bound_uj > 1_000_000  # 1 s seen
    assert r.states[-1] == "FAULT"  # its heartbeat consumer saw the host go: no grant since


def test_a_debt_of_a_sound_mode_is_paid_by_the_next_grant() -> None:
    """A 150 ms host pause (past the 25 ms gap allowed, inside the drive's 200 ms consumer
    time) with the drive topped up to 1 J: charged at the envelope past its level; paid."""
    r = run(
        Scenario(
            meter=MeterKind.ENVELOPE,
            pauses=((600_000, 150_000),),
            budget_uj=50 * UJ_PER_J,
            target_uj=UJ_PER_J,
            max_grant_uj=500_000,
        )
    )
    assert r.overrun_uj > 0 and r.debt_uj == 0  # metered past the level, and paid first
    assert ledger_from_status(r.supervisor, []).passive


def test_top_ups_keep_the_drive_running() -> None:
    r = run(
        Scenario(
            meter=MeterKind.COUNTER,
            budget_uj=50 * UJ_PER_J,
            target_uj=UJ_PER_J,
            duration_us=4_000_000,
        )
    )
    assert ledger_from_status(r.supervisor, []).passive
    enabled = r.states.index("OPERATION ENABLED")
    assert r.states[enabled:] == ["OPERATION ENABLED"]  # never stopped once running
    assert r.guard["stops"] == 0
    assert r.granted_uj > 3 * UJ_PER_J  # far more than one target's worth went through
    assert within_bound(r)


def lost(sc_period: int, start_us: int, end_us: int) -> frozenset[int]:
    return frozenset(range(start_us // sc_period, end_us // sc_period))


@pytest.mark.parametrize(("kind", "where"), SOUND)
def test_lost_tpdos_stop_the_drive_and_latch(kind: MeterKind, where: str) -> None:
    sc = Scenario(
        meter=kind,
        counter_on=where,
        budget_uj=50 * UJ_PER_J,
        target_uj=UJ_PER_J,
        pdo_lost=lost(20_000, 1_500_000, 3_000_000),
    )
    r = run(sc)
    assert r.guard["stop_reason"] == "TPDOs stopped" and r.guard["latched"]
    assert r.states[-1] in POWERLESS
    assert within_bound(r)


def test_a_drive_fault_freezes_its_budget() -> None:
    sc = Scenario(
        meter=MeterKind.COUNTER, budget_uj=50 * UJ_PER_J, target_uj=UJ_PER_J, fault_at_us=1_500_000
    )
    r = run(sc)
    assert r.states[-1] == "FAULT"
    after = [row for row in r.timeline if row[0] >= 2_000_000]
    assert after and {row[1] for row in after} == {after[0][1]}  # nothing granted any more
    assert {row[2] for row in after} == {after[0][2]}  # nothing spent, nothing returned
    assert after[0][2] > 0  # and the budget it held is still there
    assert r.guard["alive"] is False
    assert within_bound(r)


def test_a_host_crash_stops_the_drive_through_its_heartbeat_consumer() -> None:
    sc = Scenario(
        meter=MeterKind.COUNTER,
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
    # a crash replaces the gap by the consumer time: the envelope over it, and the stop
    envelope_w = 15.07
    silence_s = (reaction - sc.host_crash_at_us + sc.heartbeat_us + sc.pdo_period_us) / 1e6
    assert r.drawn_uj <= r.granted_uj + envelope_w * silence_s * 1e6 + r.guard["bound_stop_uj"]


def test_tpdos_that_come_back_find_the_stop_finished_and_the_drive_left_off() -> None:
    r = run(
        Scenario(
            budget_uj=50 * UJ_PER_J,
            target_uj=UJ_PER_J,
            pdo_lost=lost(20_000, 1_000_000, 1_300_000),
        )
    )
    assert r.guard["guard"] == "stopped" and r.guard["latched"]
    assert r.states[-1] in POWERLESS  # the guard does not enable it again
    assert r.guard["usable_uj"] > 0  # though it holds budget


def test_a_drive_enabled_without_budget_is_stopped_and_has_no_torque() -> None:
    app = tuple((500_000 + i * 1_000, index, value) for i, (index, value) in enumerate(ENABLE))
    sc = Scenario(budget_uj=0, auto_enable=False, app=app, duration_us=1_500_000)
    r = run(sc)
    assert "OPERATION ENABLED" in r.states and r.states[-1] in POWERLESS
    assert r.granted_uj == 0 and r.guard["stops"] == 1
    assert r.drawn_uj == 0  # its limits were closed from set-up on


def test_enabling_never_cuts_a_quick_stop_short() -> None:
    from canergy.live.canopen.cia402_link import enable_step

    assert enable_step("QUICK STOP ACTIVE") == 0x0000  # disable voltage, not enable operation
    assert enable_step("SWITCH ON DISABLED") == 0x0006  # shutdown
    assert enable_step("SWITCHED ON") == 0x000F
    assert enable_step("FAULT") is None and enable_step("FAULT REACTION ACTIVE") is None


def test_tpdos_lost_while_stopped_latch_too() -> None:
    """A drive stopped for want of budget whose TPDOs then stop is never enabled by the guard."""
    config = GuardConfig(MeterConfig(rated_torque_mnm=500), auto_enable=True)
    guard = DriveGuard(10, config, 0, 1)
    guard.on_ready(0)
    guard.on_values(10_000, {0x6041: 0x40, 0x6077: 0, 0x606C: 0}, "SWITCH ON DISABLED")
    assert guard.phase.value == "stopped" and not guard.latched
    guard.on_wakeup(10_000 + guard.config.pdo_timeout_us + 1)
    assert guard.latched and guard.stop_reason == "no budget yet"


@pytest.mark.parametrize("reaction_ms", [2, 19])
def test_limits_toggled_at_every_tpdo_are_all_charged(reaction_ms: int) -> None:
    """Found in review: an application that enables the drive just after each TPDO and
    disables it just before every other one makes the guard open and close the limits at every
    TPDO; the envelope charged up to each limits write and read-back was metered but never
    spent (a flywheel at 100 rad/s, cyclic torque 3000 ‰ against 0.07 N·m drew 1.3 J past
    granted + bound)."""
    period, duration = 20_000, 4_000_000
    app: list[tuple[int, int, int]] = [(0, 0x6060, 10), (0, 0x6071, 3000)]
    for t0 in range(0, duration, 2 * period):
        app += [(t0 + 500 + i, index, value) for i, (index, value) in enumerate(ENABLE)]
        app += [(t0 + period - 500, 0x6040, 0x06)]
        app += [(t0 + period + 500 + i, index, value) for i, (index, value) in enumerate(ENABLE)]
    r = run(
        Scenario(
            pdo_period_us=period,
            reaction_us=reaction_ms * 1000,
            app=tuple(app),
            auto_enable=False,
            velocity=0,
            inertia=0.01,
            initial_rad_s=100.0,
            load_nm=0.07,
            duration_us=duration,
            budget_uj=200 * UJ_PER_J,
            target_uj=5 * UJ_PER_J,
            max_grant_uj=5 * UJ_PER_J,
        )
    )
    assert r.metered_uj == r.guard["spent_uj"] + r.debt_uj  # every charge spent or owed
    assert within_bound(r)


def _transfers(*outcomes: Exception | int) -> tuple[list[int], Callable[[], int]]:
    """A transfer that raises or returns ``outcomes`` in turn; the list counts its calls."""
    calls: list[int] = []

    def transfer() -> int:
        outcome = outcomes[len(calls)]
        calls.append(1)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    return calls, transfer


def test_a_shared_sdo_server_abort_is_the_drives_answer_only_when_it_comes_twice() -> None:
    import canopen

    from canergy.live.canopen.cia402_link import shared_sdo

    garbled = canopen.SdoCommunicationError("Unexpected response 0x60")
    another_masters = canopen.SdoAbortedError(0x06090030)
    calls, transfer = _transfers(garbled, another_masters, garbled, 7)
    assert shared_sdo(transfer, lambda _s: None) == 7 and len(calls) == 4
    refused = canopen.SdoAbortedError(0x06010002)
    calls, transfer = _transfers(refused, refused, 7)
    with pytest.raises(canopen.SdoAbortedError):
        shared_sdo(transfer, lambda _s: None)
    assert len(calls) == 2
    calls, transfer = _transfers(*[garbled] * 5, 7)
    with pytest.raises(canopen.SdoCommunicationError):
        shared_sdo(transfer, lambda _s: None)
    assert len(calls) == 5


@pytest.mark.parametrize("stop", [StopKind.DISABLE, StopKind.QUICK])
def test_a_budget_below_the_full_limits_bound_starts_the_drive_at_tapered_limits(
    stop: StopKind,
) -> None:
    """A 200 ms PDO timeout puts the full limits' bound (about 3 J) above the 2 J granted: the
    guard starts the drive at the tapered level what it holds covers, and keeps its bound (it
    once compared the budget with the full limits' bound while stopped, and never started)."""
    r = run(Scenario(meter=MeterKind.COUNTER, pdo_timeout_us=200_000, stop=stop))
    assert r.granted_uj == 2 * UJ_PER_J
    assert "OPERATION ENABLED" in r.states, r.guard
    assert r.guard["taper_level"] > 0
    assert within_bound(r)
