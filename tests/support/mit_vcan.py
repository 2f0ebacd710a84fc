"""What the vcan tests of an MIT motor in line share (``test_vcan_mit_inline``,
``test_vcan_mit_hosted``): the emulated DM4310 on the motors' bus, the application's burst until
the gate's status shows the budget gone, and the checks of what reached the motor."""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import can

from canergy.devices.mit import ENTER, worst_torque
from canergy.live.runtime import monotonic_us
from firmware_model.drive.motor import LoadTorque
from firmware_model.mit.live_bench import DM, GREEDY, MOTOR, PUSH, burst
from firmware_model.mit.motor import MitFace, MitMotorModel
from support.procs import wait

CAP = 0.5
"""N·m: 0.5·30 + 3/2·0.85·(0.5/0.945)² = 15.36 W, charged by the clock from the grant on: the
20 J granted last 1.3 s, commanded or not (a held-off application must still get commands in)."""
SLOW = ("--mit-feedback-timeout", "2s", "--mit-stop-timeout", "2s")
"""Inside user-mode Linux a process can be held off for hundreds of milliseconds."""

Status = Callable[[], "dict[str, Any] | None"]


def interfaces_up(*names: str) -> None:
    """Fail (never skip) when an interface the test needs is missing."""
    for iface in names:
        assert Path(f"/sys/class/net/{iface}/operstate").exists(), (
            f"{iface} missing: ip link add dev {iface} type vcan; ip link set up {iface}"
        )


def motor_on(channel: str) -> tuple[MitMotorModel, MitFace]:
    """The emulated DM4310 answering on ``channel``, started."""
    motor = MitMotorModel(
        MOTOR, DM, monotonic_us(), master_id=MOTOR + 0x10, load=LoadTorque.constant(0.02, True)
    )
    face = MitFace(motor, can.Bus(interface="socketcan", channel=channel))
    face.start()
    return motor, face


def burst_until_spent(app: can.BusABC, gate: Status, motor: MitMotorModel, show: Any) -> int:
    """Enter motor mode, the largest feed-forward torque and, every tenth frame, the largest
    gains until ``gate()`` (the motor's part of a status file) shows the budget gone; then the
    motor out of motor mode, and one more command refused and counted. The rounds sent."""

    def exhausted() -> bool:
        s = gate()
        return bool(s and s["stop_reason"] == "budget exhausted" and s["guard"] == "stopped")

    rounds = burst(app, exhausted, [ENTER, *[PUSH] * 8, GREEDY], timeout_s=300)
    assert exhausted(), show()
    wait(lambda: not motor.enabled, "the motor out of motor mode", show=show)
    after = (gate() or {})["commands"]["refused_why"]
    last = "no budget (budget exhausted)"
    app.send(can.Message(arbitration_id=MOTOR, data=GREEDY, is_extended_id=False))

    def counted() -> bool:
        s = gate()
        return bool(s and s["commands"]["refused_why"].get(last, 0) > after.get(last, 0))

    wait(counted, "the command after the budget refused and counted", show=show)
    return rounds


def received_within_the_cap(motor: MitMotorModel, face: MitFace) -> tuple[int, int]:
    """The motor only ever applied torque under the cap, and every command it received asks at
    most the cap through its velocity and feed-forward terms (kd·(|v| + Ω) + |t_ff|). Its
    stiffness term is clamped from the position in the newest reply, so the gate lets one kp
    step through near the set point (kp·25 rad, the worst position, is not what it bounds: a
    series run met 100/819 · 25 = 3.05 N·m that way, with the torque applied under the cap).
    What the motor drew (µJ) and how many commands it received."""
    with face.lock:
        drawn = motor.drawn_uj
        received = list(motor.commands)
    assert received and 0 < motor.torque_max_seen <= CAP + 1e-9
    for command in received:
        assert worst_torque(DM, command, command.p, 0, 0) <= Fraction(CAP)
    return drawn, len(received)
