"""An MIT motor in line on python-can's virtual bus, black-box, on the wall clock: the emulated
DM4310 (``firmware_model.mit``, the CiA 402 drive's motor physics), ``canergy supervisor`` (its
real ``main``, in a thread) granting to an ordinary node id, and an application of our own that
opens ``MitBus`` over its bus instead of the bus itself and sends a burst of the largest gains.
What the motor drew stays within what was granted plus the bound the proxy's guard showed; the
motor saw only clamped commands; what was refused is counted."""

from __future__ import annotations

import contextlib
import json
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import can

from canergy.cli import main as canergy_main
from canergy.devices.mit import ENTER, MODELS, encode, worst_torque
from canergy.live.control import request
from canergy.live.mit_bus import MitBus, MitMotor
from canergy.live.runtime import monotonic_us
from firmware_model.drive.live_bench import wait_for
from firmware_model.drive.motor import LoadTorque
from firmware_model.mit.motor import MitFace, MitMotorModel

DM = MODELS["DM4310"]
MOTOR, NODE = 1, 11
CAP = 0.5
"""N·m: 0.5·30 + 3/2·0.85·(0.5/0.945)² = 15.36 W while the budget lasts."""
GREEDY = encode(DM, 12.5, 30.0, 500.0, 5.0, 10.0).pack()
"""The largest gains, the largest feed-forward torque, the farthest set point."""
REVERSED = encode(DM, -12.5, -30.0, 500.0, 5.0, -10.0).pack()
PUSH = encode(DM, 0.0, 0.0, 0.0, 0.0, 10.0).pack()
"""The largest feed-forward torque alone (clamped to the cap, it runs the motor up to speed)."""


@dataclass
class Rig:
    tmp: Path
    model: MitMotorModel
    face: MitFace
    channel: str
    control: Path
    result: list[int]
    thread: threading.Thread

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj

    def books(self) -> dict[str, Any] | None:
        with contextlib.suppress(FileNotFoundError, json.JSONDecodeError):
            return dict(json.loads((self.tmp / "status.json").read_text()))
        return None

    def stop(self) -> dict[str, Any]:
        request(self.control, {"stop": True}, 30)
        self.thread.join(timeout=60)
        final = self.books()
        assert final is not None and self.result == [0], self.result
        return final


@contextlib.contextmanager
def rig(tmp: Path, initial: str) -> Iterator[Rig]:
    channel = f"mit-{uuid.uuid4().hex}"
    model = MitMotorModel(
        MOTOR, DM, monotonic_us(), master_id=MOTOR + 0x10, load=LoadTorque.constant(0.02, True)
    )
    face = MitFace(model, can.Bus(interface="virtual", channel=channel))
    face.start()
    control = tmp / "ctl.sock"
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, "--nodes", str(NODE)),
        *("--state", str(tmp / "s.json"), "--no-fsync", "--initial", initial),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(control), "--target", "1J", "--max-grant", "500mJ"),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(canergy_main(argv)), daemon=True)
    thread.start()
    r = Rig(tmp, model, face, channel, control, result, thread)
    try:
        yield r
    finally:
        if thread.is_alive() and control.exists():
            request(control, {"stop": True}, 30)
        thread.join(timeout=60)
        face.close()


def burst(bus: can.BusABC, until: Any, frames: list[bytes], period_s: float = 0.002) -> int:
    """ENTER, then ``frames`` in turn every ``period_s`` until ``until()``; frames sent."""
    sent = 0
    bus.send(can.Message(arbitration_id=MOTOR, data=ENTER, is_extended_id=False))
    deadline = time.monotonic() + 60
    while not until() and time.monotonic() < deadline:
        data = frames[sent % len(frames)]
        bus.send(can.Message(arbitration_id=MOTOR, data=data, is_extended_id=False))
        sent += 1
        time.sleep(period_s)
    return sent


def test_a_burst_of_the_largest_gains_draws_at_most_granted_plus_the_bound(
    tmp_path: Path,
) -> None:
    with rig(tmp_path, "3J") as r:
        bus = MitBus(
            can.Bus(interface="virtual", channel=r.channel),
            [MitMotor(MOTOR, node=NODE, model="DM4310", max_torque=CAP)],
        )
        try:
            wait_for(lambda: bus.status(MOTOR)["guard"] == "running", timeout=60)

            def exhausted() -> bool:
                s = bus.status(MOTOR)
                return bool(s["stop_reason"] == "budget exhausted" and s["guard"] == "stopped")

            sent = burst(bus, exhausted, [PUSH] * 9 + [GREEDY])
            assert exhausted(), bus.status(MOTOR)
            refused_before = bus.counts(MOTOR).refused
            bus.send(can.Message(arbitration_id=MOTOR, data=GREEDY, is_extended_id=False))
            status = bus.status(MOTOR)
            counts = bus.counts(MOTOR)
        finally:
            bus.shutdown()
        final = r.stop()
    node = final["nodes"][str(NODE)]
    granted = node["delivered_uj"] - node["returns_credited_uj"]
    drawn = r.drawn()
    print(
        f"sent {sent}, clamped {counts.clamped}, refused {counts.refused}, resent "
        f"{counts.resent}; drawn {drawn} µJ, granted {granted} µJ, bound {status['bound_uj']} µJ"
    )
    assert drawn > 0 and sent > 10
    assert drawn <= granted + status["bound_uj"], (drawn, granted, status["bound_uj"])
    assert counts.clamped >= 1 and counts.refused == refused_before + 1
    assert 0 < r.model.torque_max_seen <= CAP + 1e-9
    assert len(r.model.commands) >= counts.clamped  # every command the motor got ...
    for c in r.model.commands:  # ... asks for at most the cap at any position within 25 rad
        assert worst_torque(DM, c, c.p, 0, 0) + c.kp * 25 <= Fraction(CAP)
    assert not r.model.enabled  # exit motor mode when the budget was gone


def test_the_same_burst_straight_to_the_motor_draws_far_more(tmp_path: Path) -> None:
    """The attack is real: without the gate, 0.3 s of it (reversing every 2 ms) draws more than
    the whole 3 J and its bound."""
    with rig(tmp_path, "3J") as r:
        bus = can.Bus(interface="virtual", channel=r.channel)
        try:
            end = time.monotonic() + 0.3
            burst(bus, lambda: time.monotonic() > end, [GREEDY, REVERSED])
        finally:
            bus.shutdown()
        r.stop()
    assert r.drawn() > 4_000_000, r.drawn()
