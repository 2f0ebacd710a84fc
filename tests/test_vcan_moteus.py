"""A guarded moteus on real SocketCAN, CAN FD (``pytest -m vcan``): ``canergy supervisor --fd
--moteus`` as a separate process on vcan0, the emulated controller (``firmware_model.moteus``)
and an application of our own in the test's process on their own sockets, as in
tests/test_moteus_live.py on the virtual bus. The check is the guarantee: what the controller
drew stays within what it was granted plus the bound the guard showed, and it was stopped.

Inside user-mode Linux a process can be held off for hundreds of milliseconds: the guard's
feedback and stop timeouts are 3 s, its reaction and latency allowances are raised to what it
measures (and so is the bound)."""

from __future__ import annotations

import threading
from typing import Any

import can
import pytest
from support.procs import Procs, procs, python, status, wait
from support.vcan import BUS, IFACE, vcan_up

from canergy.devices.moteus import Mode, can_id, extended
from canergy.ledger import ledger_from_status
from canergy.live.runtime import monotonic_us
from firmware_model.drive.motor import LoadTorque
from firmware_model.moteus.live_bench import LIMITS, MOTOR, SERVO
from firmware_model.moteus.servo import ServoFace, ServoModel

pytestmark = pytest.mark.vcan
__all__ = ["procs", "vcan_up"]  # the fixtures of support, used here


def _fd_bus() -> can.BusABC:
    return can.Bus(interface="socketcan", channel=IFACE, fd=True)


def _guarded(procs: Procs) -> dict[str, Any]:
    path = procs.tmp / "sup.json"
    if not path.exists():
        return {}
    return dict(status(path)["cia402"]["devices"]["moteus"][str(SERVO)])


@pytest.mark.parametrize("attack", [False, True], ids=["plain", "limits-behind-the-guard"])
def test_a_guarded_moteus_on_vcan0_stays_inside_its_grant_plus_the_bound(
    procs: Procs, attack: bool
) -> None:
    """``attack``: every cycle the application also sets servo.max_current_A 20,
    servo.max_power_W 450 and servo.max_velocity 100 behind the guard and sends its command in
    a burst of three between the guard's queries, as tests/test_moteus_live.py's attacker does
    on the virtual bus. Each write is charged at its envelope until the guard's own limits read
    back (or the controller is stopped for good): the guarantee is the same."""
    servo = ServoModel(SERVO, monotonic_us(), load=LoadTorque.constant(0.01, opposing=True))
    face = ServoFace(servo, _fd_bus())
    face.start()
    app = _fd_bus()
    done = threading.Event()

    def application() -> None:  # position mode, 1 N·m feed-forward, every 20 ms
        from canergy.devices.moteus import DIAGNOSTIC_CHANNEL, Kind, Reg, Stream, Write, encode

        data = encode(
            Write(Kind.INT8, Reg.MODE, (float(Mode.POSITION),)),
            Write(Kind.FLOAT, Reg.COMMAND_POSITION, (float("nan"), 0.0, 1.0)),
        )
        stop = encode(Write(Kind.INT8, Reg.MODE, (float(Mode.STOPPED),)))
        ident = can_id(0, SERVO)
        lines = [
            encode(Stream(False, DIAGNOSTIC_CHANNEL, f"conf set servo.{x}\n".encode()))
            for x in ("max_current_A 20", "max_power_W 450", "max_velocity 100")
        ]
        while not done.wait(0.02):
            # held off past the watchdog, the controller latches TIMEOUT: as an application
            # reading mode 15 in its replies would, leave it with a stop (a run in user-mode
            # Linux with two kernels on two cores once drew nothing for it)
            payloads = [stop, data] if servo.mode is Mode.TIMEOUT else [data]
            if attack:
                payloads = [*lines, *payloads, data, data]
            for payload in payloads:
                frame = can.Message(
                    arbitration_id=ident, data=payload, is_extended_id=extended(ident), is_fd=True
                )
                app.send(frame)

    runner = threading.Thread(target=application, daemon=True)
    try:
        procs.start(
            "supervisor",
            python(
                "-m",
                "canergy",
                "supervisor",
                *BUS,
                "--fd",
                *("--moteus", str(SERVO), *LIMITS, *MOTOR),
                *("--moteus-feedback-timeout", "3s", "--moteus-stop-timeout", "3s"),
                # the envelope is charged by the clock from the first grant: 30 J at its
                # 8 W keep the controller's budget for about 4 s, so an application held off
                # for a second (a run in user-mode Linux under load 8 drew nothing) still runs.
                # The target stays above the bound, which grows with the reaction measured: at
                # a 5 J target a loaded run's 0.55 s reaction made it 5.8 J, and the guard
                # held the controller with 5 J in hand that the supervisor, its node at the
                # target, never topped up (the budget never ran out)
                *("--initial", "30J", "--target", "10J", "--max-grant", "0.5J"),
                *("--response-timeout", "0.3"),
                *("--state", str(procs.tmp / "state.json"), "--no-fsync"),
                *("--status-file", str(procs.tmp / "sup.json"), "--status-period", "0.2"),
            ),
        )
        show = lambda: (_guarded(procs), procs.stderr("supervisor")[-2000:])  # noqa: E731
        wait(lambda: bool(_guarded(procs).get("limits_confirmed")), "the limits set", show=show)
        runner.start()

        def drew() -> bool:
            with face.lock:
                return servo.drawn_uj > 0

        wait(drew, "the controller running", show=show)

        def spent() -> bool:  # all 30 J granted: a stop while a top-up was late is not the end
            sup = status(procs.tmp / "sup.json")
            guarded = _guarded(procs)
            exhausted = guarded.get("stop_reason") == "budget exhausted"
            return (sup["usable_uj"] == 0 and exhausted) or (attack and bool(guarded["refused"]))

        if attack:
            wait(lambda: _guarded(procs)["writes_seen"] > 0, "the writes seen", show=show)
        wait(spent, "the budget running out (or the controller stopped for good)", show=show)
        done.set()
        runner.join(timeout=30)
        # stopped by the guard, or timed out since (the power stage off either way)
        wait(lambda: servo.mode in (Mode.STOPPED, Mode.TIMEOUT), "the stop", show=show)
        assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    finally:
        done.set()
        face.close()
        app.shutdown()
    sup = status(procs.tmp / "sup.json")
    guarded = sup["cia402"]["devices"]["moteus"][str(SERVO)]
    books = sup["nodes"][str(SERVO)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    with face.lock:
        drawn = servo.drawn_uj
    print(
        f"drawn {drawn} µJ, granted {granted} µJ, bound {guarded['bound_uj']} µJ, writes seen "
        f"{guarded['writes_seen']}, {guarded['stop_reason']}, refused {guarded['refused']}"
    )
    assert "POSITION" in [s for _, s in servo.history]  # it ran
    assert guarded["stuck"] is None, guarded
    assert guarded["writes_seen"] > 0 if attack else guarded["limits_verified"] is True, guarded
    assert 0 < drawn <= granted + guarded["bound_uj"], (drawn, granted, guarded)
    assert sup["conservation"]["holds"]
    debt = ledger_from_status(sup, []).drive_debt
    # under attack the guard may refuse the controller for good (its read-back met the answer
    # to the application's own conf set) and charge the application's limits while it holds it
    # stopped: the books then show more debt than the bound, booked, never drawn
    assert attack or debt <= guarded["bound_uj"], (debt, guarded)
