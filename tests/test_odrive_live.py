"""``canergy supervisor --odrive`` on python-can's virtual bus, black-box: the emulated ODrive
axis (``firmware_model.odrive``, the CiA 402 drive's motor physics) and an application of our own
sending CAN Simple frames. Wall clock, generous timeouts; the bound is the guard's own, with the
reaction and latency it measured in the same run.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path
from typing import Any

import can
import pytest
from support.stops import budget_stop

from canergy.cli import main
from canergy.devices.odrive import Cmd, can_id, set_limits
from canergy.ledger import ledger_from_status
from firmware_model.odrive.live_bench import (
    AXIS,
    ENDPOINTS,
    LIMITS,
    AxisBench,
    guarded_axis,
    wait_for,
)

BUDGET = ("--initial", "20J", "--target", "5J")
"""The envelope (6.77 W) is charged while the axis runs or may run: 20 J last 3 s."""


def exhausted(bench: AxisBench) -> dict[str, Any] | None:
    d = bench.axis_status()
    done = (
        d is not None
        and budget_stop(d["stop_reason"])
        and d["guard"] == "stopped"
        and d["usable_uj"] < d["stop_at_uj"]
    )
    return d if done else None


def ready(bench: AxisBench) -> bool:
    """Set up, and granted: the limits the guard opened once it had budget. (Until then the
    closed limits, no current, are in force: an application that enters closed loop before
    is stopped, and on a loaded machine a test that did so once ran out its budget with the
    axis stopped, 0 J drawn.)"""
    d = bench.axis_status()
    return d is not None and d["ready"] and d["limits_confirmed"] and d["guard"] == "running"


def granted_and_axis(final: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    books = final["nodes"][str(AXIS)]
    axis = final["cia402"]["devices"]["odrive"][str(AXIS)]
    return books["delivered_uj"] - books["returns_credited_uj"], axis


def test_the_budget_runs_out_and_the_axis_stops_inside_the_bound(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)  # 1 N·m asked: the current limit holds it to 0.1 N·m
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        wait_for(lambda: exhausted(b), timeout=60)
        wait_for(lambda: (d := b.axis_status()) and d["drive_state"] == "IDLE")
        final = b.stop()
    granted, axis = granted_and_axis(final)
    # the supervisor's Notifier ends with it (an empty canopen.Network is falsy: it once did not)
    left = [t.name for t in threading.enumerate() if t.name.startswith("Notifier for bus")]
    assert not [name for name in left if "odrive-" in name], left
    assert "CLOSED_LOOP_CONTROL" in [s for _, s in b.model.history]  # it ran ...
    assert b.model.state.name == "IDLE"  # ... and was stopped
    assert axis["limits_verified"] is True and axis["stuck"] is None
    assert axis["credited_uj"] == granted == axis["spent_uj"] + axis["usable_uj"]
    assert b.drawn() > 0
    assert b.drawn() <= granted + axis["bound_uj"], (b.drawn(), granted, axis["bound_uj"])
    assert final["conservation"]["holds"]
    books = ledger_from_status(final, [])  # charged past the grant: inside the bound
    assert books.drive_debt <= axis["bound_uj"]
    assert "odrive axis 3: stopping (budget exhausted" in capsys.readouterr().err


def test_an_application_raising_its_own_limits_is_charged_for_them(tmp_path: Path) -> None:
    """Behind the guard, every 5 ms, the application writes Set_Limits 20 rev/s, 20 A, clears
    the errors, enters closed loop and asks for ±1 N·m, reversing (20 A: 200 W of copper losses
    alone). Each Set_Limits is charged at its envelope (450 W) from when it was seen until the
    guard's own limits, written after it, read back; what the axis drew stays inside granted +
    bound. Without that charge and the guard's limits written again it drew 578 J of 20 J."""
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        done = threading.Event()

        def attack() -> None:
            sign = 1.0
            while not done.wait(0.005):
                b.send(Cmd.SET_LIMITS, struct.pack("<ff", 20.0, 20.0))
                b.run_closed_loop(sign)  # back into closed loop after every stop, reversing
                sign = -sign

        before = wait_for(b.axis_status)["stops"]  # a status with the attack may show its stop
        attacker = threading.Thread(target=attack, daemon=True)
        attacker.start()
        try:
            wait_for(lambda: (d := b.axis_status()) and d["writes_seen"], timeout=60)
            wait_for(  # stopped (or refused) since the attack began
                lambda: (d := b.axis_status()) and (d["stops"] > before or d["refused"]),
                timeout=60,
            )
        finally:
            done.set()
            attacker.join()
        wait_for(lambda: (d := b.axis_status()) and d["drive_state"] == "IDLE")
        final = b.stop()
    granted, axis = granted_and_axis(final)
    assert axis["writes_seen"] > 0
    print(
        f"drawn {b.drawn()} µJ, granted {granted} µJ, bound {axis['bound_uj']} µJ, metered "
        f"{axis['metered_uj']} µJ, writes seen {axis['writes_seen']}, {axis['stop_reason']}"
    )
    assert b.drawn() <= granted + axis["bound_uj"], (b.drawn(), granted, axis["bound_uj"])
    assert axis["metered_uj"] >= b.drawn()


def test_an_applications_limits_that_never_read_back_stop_the_axis_for_good(tmp_path: Path) -> None:
    """The application writes Set_Limits 20 rev/s, 20 A behind the guard, and from then the
    axis answers no endpoint read: the guard's own limits, written over the application's at
    once, never read back. The application's are charged (at their envelope, 450 W) all along,
    and past the feedback timeout (2 s here) the axis is stopped for good, the write named.
    Before that deadline the guard wrote its limits again every 100 ms and the axis ran on."""
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        with b.face.lock:
            b.model.answers_reads = False
        b.send(Cmd.SET_LIMITS, struct.pack("<ff", 20.0, 20.0))
        b.run_closed_loop(1.0)
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=30)
        wait_for(lambda: (d := b.axis_status()) and d["drive_state"] == "IDLE")
        final = b.stop()
    granted, axis = granted_and_axis(final)
    assert d["refused"] == (
        "a write behind the guard (limits velocity_rev_s 20, current_a 20) not verified in time"
    )
    assert d["latched"] and axis["guard"] != "running" and axis["alive"] is False
    assert axis["writes_seen"] == 1
    assert b.drawn() <= granted + axis["bound_uj"], (b.drawn(), granted, axis["bound_uj"])
    assert axis["metered_uj"] >= b.drawn()


def test_limits_changed_off_the_bus_are_found_by_the_periodic_read_back(tmp_path: Path) -> None:
    """The axis's current limit changes where the guard cannot see it (over USB, say: set in
    the emulator directly) while it runs: the guard's read-back every second finds it and stops
    the axis for good, naming the limit. Without that read-back the axis ran on at 20 A."""
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        with b.face.lock:
            b.model.current_limit = 20.0
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=30)
        wait_for(lambda: (d := b.axis_status()) and d["drive_state"] == "IDLE")
        b.stop()
    assert d["refused"] == (
        "limits changed behind the guard (a periodic read-back): current limit reads 20 A, "
        "written 2"
    )
    assert d["latched"] and d["writes_seen"] == 0


def test_a_limit_that_does_not_read_back_is_refused_at_set_up(tmp_path: Path) -> None:
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET, current_cap=1.0) as b:
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=30)
        final = b.stop()
    assert d["refused"] == "limits not taken: current limit reads 1 A, written 2"
    assert d["latched"] and d["guard"] != "running"
    granted, axis = granted_and_axis(final)
    assert granted == 0 and axis["alive"] is False


def test_an_axis_that_ignores_the_stop_is_stuck(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET, ignores_stop=True) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        d = wait_for(lambda: (d := b.axis_status()) and d["guard"] == "stuck" and d, timeout=60)
        b.stop()
    assert d["stuck"] == "still powered 2000 ms after the stop"
    assert d["alive"] is False
    assert "odrive axis 3: STUCK (still powered 2000 ms after the stop" in capsys.readouterr().err


def test_firmware_0_5_limits_are_unverified_and_need_trust(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["supervisor", "-i", "virtual", "-c", "x", "--odrive", "3", "--odrive-firmware"]
    argv += ["0.5", "--odrive-torque-constant", "0.05", *LIMITS, "--state", str(tmp_path / "s")]
    assert main(argv) == 2
    assert "firmware 0.5 has no way to read a limit back" in capsys.readouterr().err
    trust = ("--odrive-trust-limits", *BUDGET)
    with guarded_axis(tmp_path, *LIMITS, *trust, firmware="0.5") as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: exhausted(b), timeout=60)
        final = b.stop()
    granted, axis = granted_and_axis(final)
    assert axis["limits_verified"] is False and axis["firmware"] == "0.5"
    assert b.drawn() <= granted + axis["bound_uj"]


def test_a_supervisor_held_off_as_a_write_behind_it_arrives_stays_inside_the_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The attack of tests/test_vcan_odrive.py (Set_Limits 20 rev/s, 20 A, closed loop, ±1 N·m
    every 5 ms) on a supervisor held off as a host under load holds it: its frames wait 0.5 s
    before it takes in the first write behind it (the Notifier's thread stalled, as user-mode
    Linux stalls a process), the axis running at 20 A meanwhile. The bound includes that wait.
    Without it (reaction and latency alone: 450 W × 15 ms) the axis drew 34.6 J of 10 J granted
    and a 6.8 J bound with two such stalls of 0.12 and 0.06 s."""
    from canergy.live.devices.odrive_link import OdriveLink

    stalls: list[float] = []
    take = OdriveLink.on_message_received

    def held_off(link: OdriveLink, frame: can.Message) -> None:
        limits = frame.arbitration_id == can_id(AXIS, Cmd.SET_LIMITS)
        if limits and bytes(frame.data) == set_limits(20.0, 20.0) and not stalls:  # theirs
            stalls.append(0.5)
            time.sleep(0.5)  # the link's Notifier held off: the write waits to be taken in
        take(link, frame)

    monkeypatch.setattr(OdriveLink, "on_message_received", held_off)
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, "--initial", "10J", "--target", "5J") as b:
        wait_for(lambda: ready(b), timeout=60)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        done = threading.Event()
        sent = [0]

        def attack() -> None:
            sign = 1.0
            while not done.wait(0.005):
                b.send(Cmd.SET_LIMITS, struct.pack("<ff", 20.0, 20.0))
                sent[0] += 1
                b.run_closed_loop(sign)
                sign = -sign

        attacker = threading.Thread(target=attack, daemon=True)
        attacker.start()
        try:
            wait_for(lambda: (d := b.axis_status()) and d["writes_seen"], timeout=60)
            wait_for(lambda: (d := b.axis_status()) and d["stops"] > 0, timeout=60)
        finally:
            done.set()
            attacker.join()
        # every write taken in, then the axis stopped
        wait_for(lambda: (d := b.axis_status()) and d["writes_seen"] == sent[0], timeout=30)
        wait_for(lambda: (d := b.axis_status()) and d["drive_state"] == "IDLE", timeout=30)
        final = b.stop()
    granted, axis = granted_and_axis(final)
    print(
        f"drawn {b.drawn()} µJ, granted {granted} µJ, bound {axis['bound_uj']} µJ, metered "
        f"{axis['metered_uj']} µJ, writes seen {axis['writes_seen']}, timings "
        f"{axis['bound_timings_us']}"
    )
    assert stalls and axis["bound_timings_us"]["intake"] >= 500_000
    assert b.drawn() > 20 * 200_000  # it ran at 20 A (200 W) for part of the stall at least
    assert b.drawn() <= granted + axis["bound_uj"], (b.drawn(), granted, axis["bound_uj"])
    assert axis["metered_uj"] >= b.drawn()


def test_a_write_taken_in_late_is_metered_in_the_pass_that_takes_it_in(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One burst behind the guard (Set_Limits 20 rev/s, 20 A, closed loop, 1 N·m) whose frames
    wait 0.3 s to be taken in (the Notifier held off), the axis at 20 A meanwhile; the
    supervisor stops at the end of the pass that takes them in (a SIGTERM that found it held
    off: nothing runs the guard's clock again before the last status). What the intake
    charges back over that wait is metered in that pass: it once stayed in the clock's
    remainder until the clock next ran, so the last status (tests/test_vcan_odrive.py, user-mode
    Linux) showed 3.1 J metered of 16.8 J drawn, the writer's limits still in force."""
    from canergy.live.canopen.cia402_host import GuardedSupervisor
    from canergy.live.devices.odrive_link import OdriveLink

    theirs = set_limits(20.0, 20.0)
    take = OdriveLink.on_message_received
    wake = GuardedSupervisor.on_wakeup

    def held_off(link: OdriveLink, frame: can.Message) -> None:
        limits = frame.arbitration_id == can_id(AXIS, Cmd.SET_LIMITS)
        if limits and bytes(frame.data) == theirs:
            time.sleep(0.3)  # the link's Notifier held off: the write waits to be taken in
        take(link, frame)

    def stopped_after_intake(handler: GuardedSupervisor, now: int) -> Any:
        out = wake(handler, now)
        if any(device.writes_seen for device, _ in handler.guarded.devices.values()):
            handler.service.stop(now)  # quiescent: the loop ends before it runs the guard again
        return out

    monkeypatch.setattr(OdriveLink, "on_message_received", held_off)
    monkeypatch.setattr(GuardedSupervisor, "on_wakeup", stopped_after_intake)
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, "--initial", "10J", "--target", "5J") as b:
        wait_for(lambda: ready(b), timeout=60)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        b.send(Cmd.SET_LIMITS, theirs)
        b.run_closed_loop(1.0)
        b.supervisor.thread.join(timeout=60)
        assert b.supervisor.result == [0]
        final = b.status()
        assert final is not None
        wait_for(lambda: b.model.state.name == "IDLE", timeout=30)  # the exit's stop
    granted, axis = granted_and_axis(final)
    print(
        f"drawn {b.drawn()} µJ, granted {granted} µJ, metered {axis['metered_uj']} µJ, writes "
        f"seen {axis['writes_seen']}, timings {axis['bound_timings_us']}"
    )
    assert axis["writes_seen"] == 1 and axis["bound_timings_us"]["intake"] >= 300_000
    assert b.drawn() > 1_000_000  # it ran at 20 A (up to the velocity limit) meanwhile
    assert b.drawn() <= axis["metered_uj"] + axis["uncontained_uj"], (b.drawn(), axis)
    assert final["conservation"]["holds"]


def test_the_exit_halts_the_axis_and_meters_what_its_link_still_holds_before_the_last_status(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The supervisor's loop is held off (its passes run no guard: a loaded host) while an
    application writes Set_Limits 20 rev/s, 20 A behind the guard and runs the axis at 1 N·m:
    its frames wait in the link's queue, the axis drawing at 20 A. Then the supervisor is told
    to stop. Its exit halts the axis (Estop on the bus) and meters what the link held, up to the
    halt, before it writes the last status. It once wrote that status first, with the axis still
    running and the queue never taken in, and halted the axis after it (tests/test_vcan_odrive.py
    under load: 11.2 J metered of 16.3 J drawn)."""
    from canergy.live.canopen.cia402_host import GuardedSupervisor
    from canergy.live.devices.odrive_link import OdriveLink
    from canergy.live.supervisor.service import SupervisorService

    held = threading.Event()
    links: list[OdriveLink] = []
    wake = GuardedSupervisor.on_wakeup
    take = OdriveLink.on_message_received
    write = SupervisorService.write_status
    estop = can_id(AXIS, Cmd.ESTOP)
    seen: list[int] = []  # the frames the application's bus heard (the supervisor's too)
    halted_at_writes: list[bool] = []

    def held_off(handler: GuardedSupervisor, now: int) -> Any:
        return () if held.is_set() else wake(handler, now)

    def listened(link: OdriveLink, frame: can.Message) -> None:
        if link not in links:
            links.append(link)
        take(link, frame)

    def written(service: SupervisorService) -> None:
        if held.is_set():  # the bench is up
            while (frame := b.app.recv(0)) is not None:
                seen.append(frame.arbitration_id)
            halted_at_writes.append(estop in seen)
        write(service)

    monkeypatch.setattr(GuardedSupervisor, "on_wakeup", held_off)
    monkeypatch.setattr(OdriveLink, "on_message_received", listened)
    monkeypatch.setattr(SupervisorService, "write_status", written)
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, "--initial", "10J", "--target", "5J") as b:
        wait_for(lambda: ready(b), timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        held.set()
        while b.app.recv(0) is not None:  # the guard's own stops so far (a restop at set-up)
            pass
        (link,) = links
        frames = link.frames_in
        start = b.drawn()
        b.send(Cmd.SET_LIMITS, set_limits(20.0, 20.0))
        b.run_closed_loop(1.0)
        wait_for(lambda: b.drawn() - start > 2_000_000, timeout=60)  # 2 J at 20 A, not metered
        assert link.pending() and link.frames_in > frames  # waiting to be taken in
        final = b.stop()
        assert final is not None
        wait_for(lambda: b.model.state.name == "IDLE", timeout=30)
        drawn = b.drawn()
    granted, axis = granted_and_axis(final)
    print(
        f"drawn {drawn} µJ ({drawn - start} µJ while held), granted {granted} µJ, metered "
        f"{axis['metered_uj']} µJ, uncontained {axis['uncontained_uj']} µJ, guard "
        f"{axis['guard']}, writes seen {axis['writes_seen']}"
    )
    assert drawn <= axis["metered_uj"] + axis["uncontained_uj"], (drawn, axis)
    assert halted_at_writes[-1], "the last status was written before the axis was halted"
    assert axis["writes_seen"] == 1 and axis["stop_reason"] == "supervisor stopping"
    assert axis["feedback_age_us"] >= 0  # the status at the exit's time, not the last pass's
    level = final["nodes"][str(AXIS)]["level_uj"]  # its last TELEMETRY, at the exit
    assert level <= axis["usable_uj"] < level + 1000, (level, axis["usable_uj"])
    assert final["conservation"]["holds"]
