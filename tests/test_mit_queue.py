"""The application's frames before a gate decides: never an unbounded queue, never a frame
unaccounted for. The supervisor's ``--mit`` (``MitHost``) queues them for its loop, at most
``APP_QUEUE_MAX``: a flood larger than that is refused past the bound, counted, and the counts
add up (forwarded + clamped + refused + overflowed = taken). ``canergy inline``'s forwarder and
``MitBus`` keep no queue (each frame is judged when taken), and their counts add up too."""

from __future__ import annotations

import time
import uuid
from typing import Any

import can
import pytest

import canergy.live.devices.mit_host as mit_host
from canergy.codec import Codec
from canergy.live.devices.mit_bus import MitBus, MitMotor
from canergy.live.devices.mit_forward import POLL_MAX, MitForwarder
from canergy.live.devices.mit_gates import MitGates
from canergy.live.devices.mit_host import MitHost, MitLink
from canergy.live.runtime import monotonic_us
from canergy.messages import Return, Telemetry
from firmware_model.drive.live_bench import wait_for
from firmware_model.mit.live_bench import GREEDY, MOTOR

FLOOD = 5_000


def to_motor(arbitration_id: int = MOTOR) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=GREEDY, is_extended_id=False)


def added(commands: dict[str, Any]) -> int:
    return int(commands["forwarded"] + commands["clamped"] + commands["refused"])


def test_a_flood_on_the_hosted_app_bus_is_held_to_the_bound_and_every_frame_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """5,000 frames wait on the application's bus before the reader starts; the loop takes
    none until the reader has taken them all (a loop held off): 100 wait, the rest are refused
    and counted; a pass then judges the 100 (refused: no budget), and the counts add up."""
    monkeypatch.setattr(mit_host, "APP_QUEUE_MAX", 100)
    channel, app_channel = f"m-{uuid.uuid4().hex}", f"a-{uuid.uuid4().hex}"
    bus = can.Bus(interface="virtual", channel=channel)
    sender = can.Bus(interface="virtual", channel=app_channel)
    route = MitGates([MitMotor(MOTOR, node=MOTOR)], monotonic_us())
    app = can.Bus(interface="virtual", channel=app_channel)
    host = MitHost(bus, app, route, Codec(), lambda: None, monotonic_us)
    link = MitLink(host, route.gates[MOTOR], listens=True)
    try:
        for _ in range(FLOOD - 10):
            sender.send(to_motor())
        for _ in range(10):
            sender.send(to_motor(0x123))  # for no guarded motor
        host.start()
        wait_for(lambda: host.status()["app_taken"] == FLOOD, timeout=60)
        with host.lock:
            waiting = len(host.from_app)
        before = link.status()
        host.pump(monotonic_us())
        after = link.status()
    finally:
        host.close()
        bus.shutdown()
        sender.shutdown()
    assert waiting == 100 and before["app_queue_peak"] == 100 == before["app_queue_max"]
    assert before["app_overflowed"] == FLOOD - 100 == after["app_overflowed"]
    assert after["commands"]["overflowed"] == FLOOD - 100 - 10  # the other 10 were for 0x123
    assert after["commands"]["refused"] == 100  # no budget: judged, refused, counted
    total = added(after["commands"]) + after["app_passed"] + after["app_overflowed"]
    assert total == after["app_taken"] == FLOOD


def test_the_forwarder_takes_a_bounded_batch_per_poll_and_its_counts_add_up() -> None:
    channel, app_channel = f"m-{uuid.uuid4().hex}", f"a-{uuid.uuid4().hex}"
    sender = can.Bus(interface="virtual", channel=app_channel)
    guarded = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(MOTOR, node=11)])
    forwarder = MitForwarder(can.Bus(interface="virtual", channel=app_channel), guarded)
    try:
        for n in range(FLOOD):
            sender.send(to_motor(MOTOR if n % 5 else 0x123))
        forwarder.poll()
        assert forwarder.status()["app_taken"] == POLL_MAX  # then the motors' side
        while forwarder.status()["app_taken"] < FLOOD:
            forwarder.poll(timeout=0)
        status = forwarder.status()
    finally:
        guarded.shutdown()
        forwarder.app.shutdown()
        sender.shutdown()
    commands = status["motors"][str(MOTOR)]["commands"]
    assert status["app_passed"] == FLOOD // 5 and commands["refused"] == FLOOD * 4 // 5
    assert added(commands) + status["app_passed"] + status["app_error_frames"] == FLOOD


def test_the_forwarder_puts_no_canergy_frame_of_the_application_on_the_motors_bus() -> None:
    """A RETURN and a TELEMETRY in the name of the motor's proxy (node 11), sent on the
    application's bus, would reach the supervisor as the proxy's if forwarded: refused and
    counted; another 29-bit frame and a command still cross, and the counts add up."""
    channel, app_channel = f"m-{uuid.uuid4().hex}", f"a-{uuid.uuid4().hex}"
    codec = Codec()
    sender = can.Bus(interface="virtual", channel=app_channel)
    seen = can.Bus(interface="virtual", channel=channel)
    guarded = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(MOTOR, node=11)])
    forwarder = MitForwarder(can.Bus(interface="virtual", channel=app_channel), guarded)
    forged = [codec.encode(Return(node=11, seq=1, amount_mj=5))]
    forged.append(codec.encode(Telemetry(node=11, level_mj=0, witness=9)))
    try:
        for arbitration_id, data in forged:
            sender.send(can.Message(arbitration_id=arbitration_id, data=data))
        sender.send(can.Message(arbitration_id=0x1ABCDE, data=b"\x01"))
        sender.send(to_motor())
        while forwarder.status()["app_taken"] < 4:
            forwarder.poll(timeout=0.1)
        status = forwarder.status()
        crossed = set()  # the gate's keep-alives never end: what crossed within 0.5 s
        end = time.monotonic() + 0.5
        while time.monotonic() < end and (frame := seen.recv(timeout=0.1)) is not None:
            crossed.add((frame.arbitration_id, bytes(frame.data)))
    finally:
        guarded.shutdown()
        forwarder.app.shutdown()
        sender.shutdown()
        seen.shutdown()
    assert status["canergy_frames_refused"] == 2 and status["app_passed"] == 1
    assert (0x1ABCDE, b"\x01") in crossed  # the proxy's own frames cross too, not these:
    assert not any((i, bytes(d)) in crossed for i, d in forged), crossed
    commands = status["motors"][str(MOTOR)]["commands"]
    assert added(commands) + status["app_passed"] + status["canergy_frames_refused"] == 4


def test_mit_bus_judges_every_send_and_its_counts_add_up() -> None:
    channel = f"m-{uuid.uuid4().hex}"
    bus = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(MOTOR, node=11)])
    try:
        for n in range(FLOOD):
            bus.send(to_motor(MOTOR if n % 5 else 0x123))
        commands = bus.status(MOTOR)["commands"]
        taken, passed = bus.route.taken, bus.route.passed
    finally:
        bus.shutdown()
    assert taken == FLOOD and added(commands) + passed == FLOOD


def test_a_flood_on_the_motors_bus_is_held_to_the_bound_and_stops_every_motor_for_good(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The motors' bus brings more frames than the loop takes (a pass held off): past
    ``BUS_QUEUE_MAX`` they are not kept, and since one of them could have been another
    sender's command to a motor, the next pass stops every motor for good, the loss named.
    Before, the queue grew without bound and nothing was said."""
    monkeypatch.setattr(mit_host, "BUS_QUEUE_MAX", 50)
    channel, app_channel = f"m-{uuid.uuid4().hex}", f"a-{uuid.uuid4().hex}"
    bus = can.Bus(interface="virtual", channel=channel)
    route = MitGates([MitMotor(MOTOR, node=MOTOR)], monotonic_us())
    app = can.Bus(interface="virtual", channel=app_channel)
    host = MitHost(bus, app, route, Codec(), lambda: None, monotonic_us)
    link = MitLink(host, route.gates[MOTOR], listens=True)
    try:
        for _ in range(FLOOD):
            host.heard(to_motor(0x123))  # the Notifier's thread, while the loop is held off
        with host.lock:
            waiting = len(host.from_bus)
        guard = route.gates[MOTOR].guard
        before, refused_before = link.status(), guard.refused
        host.pump(monotonic_us())
        after = link.status()
        host.pump(monotonic_us())  # told once: nothing more without a new loss
    finally:
        host.close()
        bus.shutdown()
    assert waiting == 50 and before["bus_overflowed"] == FLOOD - 50 == after["bus_overflowed"]
    assert refused_before is None
    assert guard.latched and "frames of the motors' bus lost" in str(guard.refused)
    assert host.bus_overflowed_told == host.bus_overflowed


class _ShutBus(can.BusABC):
    """An application's bus as SocketCAN's is once shut down: a send raises ValueError (its
    socket's descriptor is -1), not a CanError."""

    def __init__(self) -> None:
        super().__init__(channel="shut")
        self.shut = False
        self.sent: list[can.Message] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.shut:
            raise ValueError("file descriptor cannot be a negative integer (-1)")
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False

    def shutdown(self) -> None:
        self.shut = True
        super().shutdown()


def test_what_the_motors_bus_brings_after_the_host_closed_is_not_forwarded() -> None:
    """The supervisor's exit closes the links (the app's bus shut down) and then takes in what
    they heard: forwarding a motor's reply to the shut bus ended a vcan run with 'error: file
    descriptor cannot be a negative integer (-1)', exit 2, after the budget stop."""
    bus = can.Bus(interface="virtual", channel=f"m-{uuid.uuid4().hex}")
    app = _ShutBus()
    route = MitGates([MitMotor(MOTOR, node=MOTOR)], monotonic_us())
    host = MitHost(bus, app, route, Codec(), lambda: None, monotonic_us)
    try:
        reply = can.Message(arbitration_id=0x0, data=bytes(8), is_extended_id=False)
        host.heard(reply)
        host.pump(monotonic_us())
        assert len(app.sent) == 1  # open: forwarded to the application
        host.close()
        host.heard(reply)
        host.pump(monotonic_us())  # closed: kept from the shut bus
    finally:
        host.close()
        bus.shutdown()
    assert len(app.sent) == 1 and host.status()["to_app"] == 1
