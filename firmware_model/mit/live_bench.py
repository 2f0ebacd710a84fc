"""An MIT-mode motor on python-can's virtual bus, on the wall clock: the emulated motor
(``MitFace``) and ``canergy supervisor`` (its real ``main``, in a thread) granting to an ordinary
node id, which the application's ``MitBus`` (or ``canergy inline``) holds the proxy of; frames
an application of our own sends (``burst``).
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import can

from canergy.cli import main as canergy_main
from canergy.devices.mit import ENTER, MODELS, encode, worst_torque
from canergy.live.runtime import monotonic_us
from canergy.live.supervisor.control import request
from firmware_model.drive.motor import LoadTorque
from firmware_model.mit.motor import MitFace, MitMotorModel

BUDGET = "20J"
"""What the runs grant a motor: at the 0.5 N·m cap's 15.36 W it covers a host that stalls 1.2 s.
The guard keeps the worst reaction and latency it has seen, and holds a motor whose budget cannot
stop it within them: with 3 J, one 0.3 s stall as the gate started held the motor for good
("held: 2.923 J in hand, 4.401 J needed"), and a run waiting for ``running`` timed out (a
fresh-clone CI run of 30fdafd)."""
SLOW_HOST = {"feedback_timeout_us": 2_000_000, "stop_timeout_us": 2_000_000}
"""Threads on a loaded machine stall for 300 ms: a feedback gap is not what these runs test."""

__all__ = [
    "BUDGET",
    "DM",
    "GREEDY",
    "MOTOR",
    "NODE",
    "PUSH",
    "REVERSED",
    "SLOW_HOST",
    "STEADY",
    "Rig",
    "asked_at_most",
    "burst",
    "rig",
    "send_latency",
]

DM = MODELS["DM4310"]
MOTOR, NODE = 1, 11
GREEDY = encode(DM, 12.5, 30.0, 500.0, 5.0, 10.0).pack()
"""The largest gains, the largest feed-forward torque, the farthest set point."""
REVERSED = encode(DM, -12.5, -30.0, 500.0, 5.0, -10.0).pack()
PUSH = encode(DM, 0.0, 0.0, 0.0, 0.0, 10.0).pack()
"""The largest feed-forward torque alone (clamped to the cap, it runs the motor up to speed)."""
STEADY = encode(DM, 0.0, 0.0, 0.0, 0.05, 0.5).pack()
"""Clamped under 0.5 N·m (kd and t_ff by one factor), it settles near 6 rad/s with some torque
left: a motor that ignores exit then shows torque in every reply. (At its top speed, 30 rad/s,
the emulated motor shows none in some replies, which reads as stopped; docs/guide/drives.md.)"""


@dataclass
class Rig:
    tmp: Path
    model: MitMotorModel
    face: MitFace
    channel: str
    control: Path
    result: list[int]
    thread: threading.Thread
    others: list[MitFace] = field(default_factory=list)
    """The other motors' faces (``rig(others=...)``), in order."""

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj

    def drawn_by(self, face: MitFace) -> int:
        with face.lock:
            return face.model.drawn_uj

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
def rig(
    tmp: Path,
    initial: str,
    others: Sequence[tuple[MitMotorModel, int]] = (),
    per_node: str | None = None,
    hosted: Sequence[str] = (),
    **motor: Any,
) -> Iterator[Rig]:
    """The DM4310 ``MOTOR`` (proxy ``NODE``) and ``others`` (each a motor and its proxy's node
    id) on one virtual channel, the supervisor granting ``initial`` in all, topping each node up
    to ``per_node`` (default: ``initial``). ``hosted``: the supervisor hosts the gates itself,
    these flags (``--mit ...``) instead of ``--nodes``; ``motor``: ``MitMotorModel``'s fields."""
    channel = f"mit-{uuid.uuid4().hex}"
    model = MitMotorModel(
        MOTOR,
        DM,
        monotonic_us(),
        master_id=MOTOR + 0x10,
        load=LoadTorque.constant(0.02, True),
        **motor,
    )
    faces = [
        MitFace(m, can.Bus(interface="virtual", channel=channel))
        for m in (model, *[o for o, _ in others])
    ]
    for face in faces:
        face.start()
    control = tmp / "ctl.sock"
    nodes = ",".join(str(n) for n in (NODE, *(n for _, n in others)))
    target = per_node or initial
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel),
        *(hosted or ("--nodes", nodes)),
        *("--state", str(tmp / "s.json"), "--no-fsync", "--initial", initial),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(control), "--target", target, "--max-grant", target),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(canergy_main(argv)), daemon=True)
    thread.start()
    r = Rig(tmp, model, faces[0], channel, control, result, thread, faces[1:])
    try:
        yield r
    finally:
        if thread.is_alive() and control.exists():
            request(control, {"stop": True}, 30)
        thread.join(timeout=60)
        for face in faces:
            face.close()


def burst(
    bus: can.BusABC,
    until: Any,
    frames: list[bytes],
    period_s: float = 0.002,
    motors: Sequence[int] = (MOTOR,),
    timeout_s: float = 60,
) -> int:
    """ENTER, then ``frames`` in turn every ``period_s`` (each to every one of ``motors``) until
    ``until()``; rounds sent. AssertionError if ``until()`` is still false after
    ``timeout_s``: a condition never met is a failure, not a shorter run."""
    sent = 0
    for motor in motors:
        bus.send(can.Message(arbitration_id=motor, data=ENTER, is_extended_id=False))
    deadline = time.monotonic() + timeout_s
    while not until() and time.monotonic() < deadline:
        data = frames[sent % len(frames)]
        for motor in motors:
            bus.send(can.Message(arbitration_id=motor, data=data, is_extended_id=False))
        sent += 1
        time.sleep(period_s)
    if not until():
        raise AssertionError(f"burst: not done after {timeout_s:g} s ({sent} rounds sent)")
    return sent


def asked_at_most(model: MitMotorModel, cap: float) -> int:
    """Check that every command ``model`` received asked, where the motor was as it came, for
    at most ``cap`` N·m (its kp term from that position, its kd term at any speed); how many.
    (The gate bounds kp's term from the newest reply plus the drift since: a command is not
    bounded at every position, and with a longer budget the motor does get ones with kp.)"""
    assert model.commands and len(model.positions) == len(model.commands)
    for c, at in zip(model.commands, model.positions, strict=True):
        assert worst_torque(model.model, c, Fraction(at), 0, 0) <= Fraction(cap), (c, at)
    return len(model.commands)


def send_latency(tmp: Path, n: int = 2000, rounds: int = 3) -> dict[str, Any]:
    """µs per ``send`` of an MIT command: straight to the bus (to an id nobody guards) and
    through ``MitBus`` (clamped under 0.05 N·m), ``rounds`` alternating rounds of ``n`` each,
    with the supervisor granting and the motor answering; and the gate's counts."""
    from canergy.live.devices.mit_bus import MitBus, MitMotor
    from firmware_model.drive.live_bench import wait_for

    with rig(tmp, "60J") as r:
        direct = can.Bus(interface="virtual", channel=r.channel)
        motors = [MitMotor(MOTOR, node=NODE, model="DM4310", max_torque=0.05)]
        inline = MitBus(
            can.Bus(interface="virtual", channel=r.channel), motors, guard_config=SLOW_HOST
        )
        times: dict[str, list[float]] = {"direct": [], "inline": []}
        try:
            wait_for(lambda: inline.status(MOTOR)["guard"] == "running", timeout=60)
            inline.send(can.Message(arbitration_id=MOTOR, data=ENTER, is_extended_id=False))
            for _ in range(rounds):
                for name, bus, target in (("direct", direct, MOTOR + 1), ("inline", inline, MOTOR)):
                    frame = can.Message(arbitration_id=target, data=GREEDY, is_extended_id=False)
                    start = time.perf_counter_ns()
                    for _ in range(n):
                        bus.send(frame)
                    times[name].append((time.perf_counter_ns() - start) / n / 1000)
            counts = inline.counts(MOTOR)
            stop_reason = inline.status(MOTOR)["stop_reason"]
        finally:
            inline.shutdown()
            direct.shutdown()
        r.stop()
    return {"us": times, "counts": counts, "stop_reason": stop_reason}
