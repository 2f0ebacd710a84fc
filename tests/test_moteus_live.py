"""``canergy supervisor --moteus`` on python-can's virtual bus (CAN FD frames), black-box: the
emulated moteus (``firmware_model.moteus``, the CiA 402 drive's motor physics) and an
application of our own sending register frames and diagnostic lines. Wall clock, generous
timeouts; the bound is the guard's own, with the reaction and latency it measured in the run.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Any

import can
import pytest

from canergy.cli import main
from canergy.devices.moteus import (
    DIAGNOSTIC_CHANNEL,
    Kind,
    Mode,
    Reg,
    Stream,
    Write,
    can_id,
    encode,
    extended,
    padded,
    write_mode,
)
from canergy.ledger import ledger_from_status
from canergy.live.supervisor.control import request
from firmware_model.moteus.live_bench import LIMITS, SERVO, ServoBench, guarded_servo, wait_for

BUDGET = ("--initial", "20J", "--target", "5J")
"""The envelope (8.03 W) is charged while the controller may run: 20 J last about 2.5 s."""


def exhausted(bench: ServoBench) -> dict[str, Any] | None:
    d = bench.servo_status()
    done = (
        d is not None
        and d["stop_reason"] == "budget exhausted"
        and d["guard"] == "stopped"
        and d["usable_uj"] < d["stop_at_uj"]
    )
    return d if done else None


def ready(bench: ServoBench) -> bool:
    d = bench.servo_status()
    return d is not None and d["ready"] and d["limits_confirmed"]


def granted_and_servo(final: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    books = final["nodes"][str(SERVO)]
    servo = final["cia402"]["devices"]["moteus"][str(SERVO)]
    return books["delivered_uj"] - books["returns_credited_uj"], servo


def keep_commanding(b: ServoBench, done: threading.Event, torque: float = 1.0) -> None:
    """The application: a position command every 20 ms (its watchdog is 100 ms)."""
    while not done.wait(0.02):
        b.position(torque)


def test_the_budget_runs_out_and_the_controller_stops_inside_the_bound(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        done = threading.Event()
        app = threading.Thread(target=keep_commanding, args=(b, done), daemon=True)
        app.start()
        try:
            wait_for(lambda: (d := b.servo_status()) and d["guard"] == "running", timeout=60)
            wait_for(lambda: exhausted(b), timeout=60)
            wait_for(lambda: (d := b.servo_status()) and d["drive_state"] == "STOPPED")
        finally:
            done.set()
            app.join()
        final = b.stop()
    granted, servo = granted_and_servo(final)
    with capsys.disabled():
        print(f"drawn {b.drawn()} µJ, granted {granted} µJ, bound {servo['bound_uj']} µJ")
    assert "POSITION" in [s for _, s in b.model.history]  # it ran ...
    # ... and was stopped (or timed out since: the application's last command came after the
    # guard's last stop; the emulator's timeout mode has the power stage off)
    assert b.model.mode in (Mode.STOPPED, Mode.TIMEOUT)
    assert servo["limits_verified"] is True and servo["stuck"] is None
    assert servo["credited_uj"] == granted == servo["spent_uj"] + servo["usable_uj"]
    assert b.drawn() > 0
    assert b.drawn() <= granted + servo["bound_uj"], (b.drawn(), granted, servo["bound_uj"])
    assert final["conservation"]["holds"]
    books = ledger_from_status(final, [])
    assert books.drive_debt <= servo["bound_uj"]
    assert "moteus axis 1: stopping (budget exhausted" in capsys.readouterr().err


def test_a_target_below_where_the_guard_stops_parks_the_controller_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--target`` 50 mJ, below where the guard stops the controller (the bound at its limits,
    about 0.12 J): the supervisor warns at the start. A one-shot grant releases it; once it ran
    that down the guard holds it with budget in hand, and the supervisor, which sees it at its
    target, tops it up no more. The status says so (``held: ... J in hand, ... J needed``,
    naming ``--target``), not "budget exhausted", and stderr says it is parked."""
    with guarded_servo(tmp_path, *LIMITS, "--initial", "20J", "--target", "50mJ") as b:
        wait_for(lambda: ready(b), timeout=60)
        answer = request(b.supervisor.control, {"grant": {"node": SERVO, "amount_uj": 450_000}}, 30)
        assert answer["outcome"] == "COMMITTED", answer
        wait_for(
            lambda: (d := b.servo_status()) and d["stops"] >= 1, timeout=60, show=b.servo_status
        )
        wait_for(
            lambda: (
                (d := b.servo_status())
                and d["guard"] == "stopped"
                and "--target 0.050 J only" in (d["stop_reason"] or "")
                and d["usable_uj"] >= 50_000  # a loaded host stops it late: topped up to it
            ),
            timeout=60,
        )
        servo = b.servo_status()
        assert servo is not None
        final = b.stop()
    assert servo["stop_reason"].startswith("held: "), servo["stop_reason"]
    assert 50_000 <= servo["usable_uj"] <= servo["stop_at_uj"], servo
    assert final["conservation"]["holds"]
    err = capsys.readouterr().err
    assert "moteus axis 1: --target 0.050 J is not above where its guard stops it" in err, err
    assert "moteus axis 1: parked (held: " in err, err


def test_an_application_raising_its_own_limits_is_charged_for_them(tmp_path: Path) -> None:
    """Behind the guard, every 5 ms, the application sets servo.max_current_A 20 and
    servo.max_power_W 450 and servo.max_velocity 100 on the diagnostic channel and commands
    position mode with ±2 N·m feed-forward, reversing, in bursts of three frames. Each conf set
    is charged at its envelope from when it was seen until the guard's own limits, written after
    it, read back; what the controller drew stays inside granted + bound."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.position(1.0)
        wait_for(lambda: (d := b.servo_status()) and d["guard"] == "running", timeout=60)
        done = threading.Event()

        def attack() -> None:
            sign = 1.0
            while not done.wait(0.005):
                b.conf("conf set servo.max_current_A 20")
                b.conf("conf set servo.max_power_W 450")
                b.conf("conf set servo.max_velocity 100")
                for _ in range(3):  # a burst between the guard's queries
                    b.send(write_mode(Mode.STOPPED))  # leaves a timeout, as an application does
                    b.position(2.0 * sign)
                sign = -sign

        before = wait_for(b.servo_status)["stops"]
        attacker = threading.Thread(target=attack, daemon=True)
        attacker.start()
        try:
            wait_for(lambda: (d := b.servo_status()) and d["writes_seen"], timeout=60)
            wait_for(
                lambda: (d := b.servo_status()) and (d["stops"] > before or d["refused"]),
                timeout=60,
            )
        finally:
            done.set()
            attacker.join()
        wait_for(lambda: (d := b.servo_status()) and d["drive_state"] == "STOPPED")
        final = b.stop()
    granted, servo = granted_and_servo(final)
    print(
        f"drawn {b.drawn()} µJ, granted {granted} µJ, bound {servo['bound_uj']} µJ, metered "
        f"{servo['metered_uj']} µJ, writes seen {servo['writes_seen']}, {servo['stop_reason']}"
    )
    assert servo["writes_seen"] > 0
    assert b.drawn() <= granted + servo["bound_uj"], (b.drawn(), granted, servo["bound_uj"])
    assert servo["metered_uj"] >= b.drawn()


def test_a_supervisor_held_off_as_a_write_behind_it_arrives_stays_inside_the_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The attack above on a supervisor held off (tests/test_odrive_live.py's stall): the
    Notifier's thread waits 0.5 s at the first ``conf set servo.max_current_A 20`` before the
    link takes it in, the controller running at the application's limits meanwhile. The link
    stamps the frame at its arrival and ``DeviceGuard`` takes the wait as its intake, in the
    bound (the ODrive guard's code: 108 J drawn on 10.2 J granted, bound 371 J, intake 0.52 s).
    The intake is the check that bites here: with the frames stamped when taken in it read
    0.16 s; with the intake left out of the bound, 112-118 J drawn on 9.8-9.9 J granted still
    kept inside 123-135 J, the wait having lengthened the reaction measured as well (0.27-0.28
    s: the stop queued behind ``conf get`` answers that came through the held thread)."""
    from canergy.live.devices.moteus_link import MoteusLink

    stalls: list[float] = []
    take = MoteusLink.on_message_received

    def held_off(link: MoteusLink, frame: can.Message) -> None:
        if b"max_current_A 20" in bytes(frame.data) and not stalls:  # theirs
            stalls.append(0.5)
            time.sleep(0.5)  # the link's Notifier held off: the write waits to be taken in
        take(link, frame)

    monkeypatch.setattr(MoteusLink, "on_message_received", held_off)
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.position(1.0)
        wait_for(lambda: (d := b.servo_status()) and d["guard"] == "running", timeout=60)
        done = threading.Event()
        sent = [0]

        def attack() -> None:
            sign = 1.0
            while not done.wait(0.005):
                b.conf("conf set servo.max_current_A 20")
                b.conf("conf set servo.max_power_W 450")
                b.conf("conf set servo.max_velocity 100")
                sent[0] += 3
                for _ in range(3):
                    b.send(write_mode(Mode.STOPPED))
                    b.position(2.0 * sign)
                sign = -sign

        attacker = threading.Thread(target=attack, daemon=True)
        attacker.start()
        try:
            wait_for(lambda: (d := b.servo_status()) and d["writes_seen"], timeout=60)
            wait_for(lambda: (d := b.servo_status()) and (d["stops"] or d["refused"]), timeout=60)
        finally:
            done.set()
            attacker.join()
        # every write taken in, then the controller stopped
        wait_for(lambda: (d := b.servo_status()) and d["writes_seen"] >= sent[0], timeout=30)
        wait_for(lambda: (d := b.servo_status()) and d["drive_state"] == "STOPPED", timeout=30)
        final = b.stop()
    granted, servo = granted_and_servo(final)
    print(
        f"drawn {b.drawn()} µJ, granted {granted} µJ, bound {servo['bound_uj']} µJ, metered "
        f"{servo['metered_uj']} µJ, writes seen {servo['writes_seen']} of {sent[0]}, timings "
        f"{servo['bound_timings_us']}, {servo['stop_reason']}"
    )
    assert stalls and servo["bound_timings_us"]["intake"] >= 500_000
    assert b.drawn() <= granted + servo["bound_uj"], (b.drawn(), granted, servo["bound_uj"])
    assert servo["metered_uj"] >= b.drawn()


def test_an_applications_limit_that_never_reads_back_stops_the_controller_for_good(
    tmp_path: Path,
) -> None:
    """The application sets servo.max_current_A 20 behind the guard, and from then the
    controller answers no ``conf get``: the guard's own limits, written over it at once, never
    read back. The application's value is charged at its envelope all along, and past the
    feedback timeout the controller is stopped for good, the write named. Before that deadline
    the guard wrote its limits again every 100 ms and the controller ran on."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.position(1.0)
        wait_for(lambda: (d := b.servo_status()) and d["guard"] == "running", timeout=60)
        with b.face.lock:
            b.model.answers_reads = False
        # asked with a reply: the controller answers the application, not the guard's poll
        line = Stream(False, DIAGNOSTIC_CHANNEL, b"conf set servo.max_current_A 20\n")
        b.send(encode(line), reply=True)
        b.position(1.0)
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        wait_for(lambda: (d := b.servo_status()) and d["drive_state"] == "STOPPED")
        final = b.stop()
    granted, servo = granted_and_servo(final)
    assert d["refused"] == (
        "a write behind the guard (limits power_w 100, current_a 20, velocity_rev_s 2, "
        "timeout_s 0.1) not verified in time"
    )
    assert d["latched"] and servo["guard"] != "running" and servo["alive"] is False
    assert b.drawn() <= granted + servo["bound_uj"], (b.drawn(), granted, servo["bound_uj"])
    assert servo["metered_uj"] >= b.drawn()


def test_limits_changed_off_the_bus_are_found_by_the_periodic_read_back(tmp_path: Path) -> None:
    """servo.max_current_A changes where the guard cannot see it (over the controller's USB,
    say: set in the emulator directly) while it runs: the guard's read-back every second finds
    it and stops the controller for good, naming the value."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.position(1.0)
        wait_for(lambda: (d := b.servo_status()) and d["guard"] == "running", timeout=60)
        with b.face.lock:
            b.model.config["servo.max_current_A"] = 20.0
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        wait_for(lambda: (d := b.servo_status()) and d["drive_state"] == "STOPPED")
        b.stop()
    assert d["refused"] == (
        "limits changed behind the guard (a periodic read-back): servo.max_current_A reads 20, "
        "written 2"
    )
    assert d["latched"] and d["writes_seen"] == 0


def test_a_voltage_mode_behind_the_guard_stops_the_controller_for_good(tmp_path: Path) -> None:
    """Voltage modes bypass the current and power limits: the guard cannot bound them."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.send(encode(Write(Kind.INT8, Reg.MODE, (float(Mode.VOLTAGE_FOC),))))
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        b.stop()
    assert d["refused"] == "a write behind the guard: mode 7 (VOLTAGE_FOC)"
    assert d["latched"] and d["alive"] is False


def test_a_limit_that_does_not_read_back_is_refused_at_set_up(tmp_path: Path) -> None:
    with guarded_servo(tmp_path, *LIMITS, *BUDGET, current_cap=1.0) as b:
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        final = b.stop()
    assert d["refused"] == "limits not taken: servo.max_current_A reads 1, written 2"
    granted, servo = granted_and_servo(final)
    assert granted == 0 and servo["alive"] is False


def test_a_controller_that_ignores_the_stop_is_stuck(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_servo(tmp_path, *LIMITS, *BUDGET, ignores_stop=True) as b:
        wait_for(lambda: ready(b), timeout=60)
        done = threading.Event()
        app = threading.Thread(target=keep_commanding, args=(b, done), daemon=True)
        app.start()
        try:
            d = wait_for(
                lambda: (d := b.servo_status()) and d["guard"] == "stuck" and d, timeout=60
            )
        finally:
            done.set()
            app.join()
        final = b.stop()
    assert d["stuck"] == "still powered 2000 ms after the stop"
    assert d["alive"] is False
    _, servo = granted_and_servo(final)
    # it ignores mode 0 but took the closed limits (0 W, 0 A): nothing is left to draw, so
    # nothing is booked uncontained (the guard's books would say so at the envelope in force)
    assert servo["limits"] == {**servo["limits"], "power_w": 0.0, "current_a": 0.0}
    assert servo["uncontained_uj"] == 0
    assert "moteus axis 1: STUCK (still powered 2000 ms after the stop" in capsys.readouterr().err


def test_malformed_frames_from_the_controller_are_counted_and_dropped(tmp_path: Path) -> None:
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        for junk in (b"\x77", b"\x2c\x05\x00", b"\x41\x01\x30ab", b"\x20\xff\xff\xff\xff\xff"):
            b.send_as_servo(junk)
        d = wait_for(lambda: (d := b.servo_status()) and d["bad_frames"] >= 4 and d, timeout=30)
        final = b.stop()
    assert d["refused"] is None and final["conservation"]["holds"]


@pytest.mark.parametrize(
    ("data", "why", "to"),
    [
        (
            b"\x01\x00\x0a\x77",
            "a frame the guard cannot read (unknown subframe 0x77 at byte 4)",
            SERVO,
        ),
        (encode(Write(Kind.FLOAT, Reg.MODE, (7.5,))), "mode 7.5 (mode 7.5)", SERVO),
        (encode(Write(Kind.INT8, Reg.MODE, (99.0,))), "mode 99 (mode 99)", SERVO),
        (encode(Write(Kind.INT16, 0x110, (5.0,))), "multiplex id (0x110)", SERVO),
        (encode(Write(Kind.INT8, Reg.MODE, (7.0,))), "mode 7 (VOLTAGE_FOC)", 0x7F),
        (encode(Stream(False, 1, b"conf  load\n")), "'conf  load'", SERVO),
        (
            encode(Stream(False, 1, b"conf set servo.max_current_A 9x\n")),
            "'conf set servo.max_current_A 9x'",
            SERVO,
        ),
    ],
)
def test_a_frame_to_the_controller_the_guard_cannot_bound_stops_it_for_good(
    tmp_path: Path, data: bytes, why: str, to: int
) -> None:
    """The controller acts on what the guard cannot read: a subframe after an unknown one, a
    mode that is no mode the limits hold in, a change of its id."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.send(data, destination=to)
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        b.stop()
    assert d["refused"] == f"a write behind the guard: {why}"


def test_an_application_using_the_guards_source_id_is_still_seen(tmp_path: Path) -> None:
    """The guard's source id says nothing of who sent a frame: a limit set from it is charged."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.conf("conf set servo.max_current_A 20", source=0x7E)
        d = wait_for(lambda: (d := b.servo_status()) and d["writes_seen"] and d, timeout=30)
        b.stop()
    assert d["writes_seen"] >= 1


def test_a_frame_to_the_controller_in_its_own_name_is_still_seen(tmp_path: Path) -> None:
    """The controller acts on what is addressed to it, whatever the source id: a frame from
    the controller's own id to itself is a command, not a reply."""
    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        b.send(encode(Write(Kind.INT8, Reg.MODE, (7.0,))), source=SERVO)
        d = wait_for(lambda: (d := b.servo_status()) and d["refused"] and d, timeout=30)
        b.stop()
    assert d["refused"] == "a write behind the guard: mode 7 (VOLTAGE_FOC)"


def test_moteus_needs_can_fd_and_its_own_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["supervisor", "-i", "virtual", "-c", "x", "--moteus", "1", *LIMITS]
    argv += ["--moteus-torque-constant", "0.1", "--state", str(tmp_path / "s")]
    assert main(argv) == 2
    assert "moteus speaks CAN FD: give --fd" in capsys.readouterr().err
    assert main([*argv, "--fd", "--odrive", "3"]) == 2
    assert "--moteus and --odrive on one bus" in capsys.readouterr().err
    assert main([*argv, "--fd", "--moteus-source", "127"]) == 2
    assert "--moteus-source 127 is the broadcast id" in capsys.readouterr().err


def test_the_moteus_librarys_own_commands_as_the_application(tmp_path: Path) -> None:
    """The application is the ``moteus`` package's (PyPI) message encoding, a client nobody here
    wrote: position commands with 2 N·m feed-forward and queries every 5 ms, the limits raised
    with its diagnostic writes and its stop, sent as its transport sends them (source 0, NOP
    padding, extended above 0x7FF). Nothing of it opens a transport."""
    import moteus

    controller = moteus.Controller(id=SERVO)

    def send(command: Any) -> None:
        arbitration_id = can_id(command.source, command.destination, command.reply_required)
        b.app.send(
            can.Message(
                arbitration_id=arbitration_id,
                data=padded(command.data),
                is_extended_id=extended(arbitration_id),
                is_fd=True,
            )
        )

    with guarded_servo(tmp_path, *LIMITS, *BUDGET) as b:
        wait_for(lambda: ready(b), timeout=60)
        done = threading.Event()

        def app() -> None:
            sign = 1.0
            while not done.wait(0.005):
                if b.drawn() > 0:  # once it ran (before, a stop could come before any motion)
                    send(controller.make_diagnostic_write(b"conf set servo.max_current_A 20\n"))
                send(controller.make_stop())
                send(
                    controller.make_position(
                        position=math.nan, velocity=0.0, feedforward_torque=2 * sign, query=True
                    )
                )
                sign = -sign

        before = wait_for(b.servo_status)["stops"]
        runner = threading.Thread(target=app, daemon=True)
        runner.start()
        try:
            wait_for(
                lambda: (d := b.servo_status()) and d["writes_seen"] and d["stops"] > before,
                timeout=60,
            )
        finally:
            done.set()
            runner.join()
        final = b.stop()
    granted, servo = granted_and_servo(final)
    assert b.drawn() > 0 and servo["bad_frames"] == 0  # its frames all parse
    assert b.drawn() <= granted + servo["bound_uj"], (b.drawn(), granted, servo["bound_uj"])
    assert servo["metered_uj"] >= b.drawn()


def test_sampled_metering_integrates_the_power_register_and_claims_no_bound(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--moteus-meter sampled: no limits written, register 0x007 integrated between queries,
    guarantee none (the controller keeps its own limits: 450 W here)."""
    with guarded_servo(tmp_path, "--moteus-meter", "sampled", *BUDGET) as b:
        wait_for(lambda: (d := b.servo_status()) and d["ready"], timeout=60)
        done = threading.Event()
        app = threading.Thread(target=keep_commanding, args=(b, done, 0.5), daemon=True)
        app.start()
        try:
            d = wait_for(lambda: (d := b.servo_status()) and d["metered_uj"] > 0 and d, timeout=60)
        finally:
            done.set()
            app.join()
        b.stop()
    assert d["meter"] == "sampled" and d["guarantee"] == "none" and d["bound_uj"] is None
    assert d["limits"] is None and d["envelope_w"] is None
    assert b.model.config["servo.max_power_W"] == 450.0  # nothing written
    assert "warning: --moteus-meter sampled" in capsys.readouterr().err
