"""``MitBus`` on python-can's virtual bus without a supervisor: frames that would reach a guarded
motor outside MIT mode (Damiao's other modes and parameter frame) are refused and counted, never
sent; seen from someone else on the bus, they refuse the motor for good; frames to other ids
pass untouched; ``on_refused="raise"`` raises."""

from __future__ import annotations

import time
import uuid

import can
import pytest

from canergy.devices.mit import EXIT, MODELS, pack_reply
from canergy.live.devices.mit_bus import MitBus, MitMotor, MitRefused
from firmware_model.drive.live_bench import wait_for


def frame(arbitration_id: int, data: bytes = b"\x00" * 8) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)


def test_other_modes_of_the_motor_are_refused_and_other_ids_pass() -> None:
    channel = f"mitbus-{uuid.uuid4().hex}"
    watch = can.Bus(interface="virtual", channel=channel)
    bus = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(1, node=11)])
    try:
        bus.send(frame(0x201))  # Damiao velocity mode, motor 1
        bus.send(frame(0x7FF, bytes([1, 0, 0x55, 10, 3, 0, 0, 0])))  # a parameter write
        bus.send(can.Message(arbitration_id=1, is_remote_frame=True, is_extended_id=False))
        bus.send(frame(0x123))  # someone else's id
        seen = []
        while (got := watch.recv(timeout=0.2)) is not None and len(seen) < 50:
            seen.append(got)
        ids = {f.arbitration_id for f in seen if not f.is_extended_id}
        assert 0x123 in ids and 0x201 not in ids and 0x7FF not in ids
        assert all(bytes(f.data) == EXIT for f in seen if f.arbitration_id == 1)
        why = bus.counts(1).refused_why
        assert why == {
            "Damiao mode frame 0x201 (not MIT)": 1,
            "Damiao parameter frame 0x7FF": 1,
            "remote frame": 1,
        }
        assert not [f for f in seen if f.is_remote_frame]
    finally:
        bus.shutdown()
        watch.shutdown()


def test_another_sender_reaching_the_motor_refuses_it_for_good() -> None:
    channel = f"mitbus-{uuid.uuid4().hex}"
    other = can.Bus(interface="virtual", channel=channel)
    bus = MitBus(
        can.Bus(interface="virtual", channel=channel), [MitMotor(1, node=11)], on_refused="raise"
    )
    try:
        other.send(frame(0x101))  # position-velocity mode, behind the gate
        wait_for(lambda: bus.status(1)["refused"], timeout=10)
        assert "another sender" in bus.status(1)["refused"]
        with pytest.raises(MitRefused, match="no budget"):
            bus.send(frame(1))
    finally:
        bus.shutdown()
        other.shutdown()


def test_a_forged_reply_on_the_bus_refuses_the_motor() -> None:
    channel = f"mitbus-{uuid.uuid4().hex}"
    forger = can.Bus(interface="virtual", channel=channel)
    bus = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(1, node=11)])
    try:
        reply = pack_reply(MODELS["DM4310"], 1, 0x8000, 2048, 2048)
        sent = 0  # the gate's frames unanswered (no motor here) take as many as it sent
        while not bus.status(1)["refused"] and sent < 2000:
            forger.send(frame(0x11, reply))
            sent += 1
            time.sleep(0.001)
        wait_for(lambda: bus.status(1)["refused"], timeout=10)
        assert bus.counts(1).late < sent
        assert "asked for" in bus.status(1)["refused"]
    finally:
        bus.shutdown()
        forger.shutdown()


def test_an_application_that_never_reads_keeps_only_the_newest_frames(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import canergy.live.devices.mit_bus as mit_bus

    monkeypatch.setattr(mit_bus, "INCOMING_MAX", 5)
    channel = f"mitbus-{uuid.uuid4().hex}"
    other = can.Bus(interface="virtual", channel=channel)
    bus = MitBus(can.Bus(interface="virtual", channel=channel), [MitMotor(1, node=11)])
    try:
        for n in range(20):
            other.send(frame(0x123, bytes([n])))
        wait_for(lambda: bus.dropped == 15, timeout=10)
        kept = [bytes(f.data)[0] for f in iter(lambda: bus.recv(timeout=0.2), None)]
        assert kept == list(range(15, 20))
    finally:
        bus.shutdown()
        other.shutdown()
