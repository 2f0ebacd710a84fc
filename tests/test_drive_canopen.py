"""The emulated drive on python-can's ``virtual`` bus, driven by python-canopen masters.

Timeouts are generous and no assertion depends on tight timing (a loaded 2-core machine).
"""

from __future__ import annotations

import itertools
import statistics
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import can
import canopen
import pytest
from canopen.profiles.p402 import State402
from support.virtual_bus import Frames, wait_for

from canergy.live.runtime import monotonic_us
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque

NODE, MASTER = 10, 1
CIA402_EDS = "src/canergy/live/canopen/cia402.eds"


@dataclass
class Rig:
    face: DriveFace
    network: canopen.Network
    node: canopen.BaseNode402
    frames: Frames
    channel: str

    @property
    def model(self) -> DriveModel:
        return self.face.model

    def master(self) -> tuple[canopen.Network, can.BusABC]:
        """Another master on its own bus object (closed by the rig)."""
        bus = can.Bus(interface="virtual", channel=self.channel)
        net = drive_network(bus)
        self._extra.append((net, bus))
        return net, bus

    _extra: list[tuple[canopen.Network, can.BusABC]]


def _close(net: canopen.Network, bus: can.BusABC) -> None:
    if net.notifier is not None:
        net.notifier.stop()
    bus.shutdown()


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = f"drive-{uuid.uuid4().hex}"
    drive_bus = can.Bus(interface="virtual", channel=channel)
    drive_net = drive_network(drive_bus)
    model = DriveModel(NODE, monotonic_us(), load=LoadTorque.constant(0.01, opposing=True))
    face = DriveFace(model, drive_net)
    master_bus = can.Bus(interface="virtual", channel=channel)
    network = drive_network(master_bus)
    frames = Frames()
    assert network.notifier is not None
    network.notifier.add_listener(frames)
    node = canopen.BaseNode402(NODE, CIA402_EDS)
    for name in ("TIMEOUT_SWITCH_STATE_FINAL", "TIMEOUT_SWITCH_STATE_SINGLE"):
        setattr(node, name, 5.0)
    node.TIMEOUT_CHECK_TPDO = 2.0
    node.TIMEOUT_SWITCH_OP_MODE = 5.0
    network.add_node(node)
    face.boot()
    face.start()
    r = Rig(face, network, node, frames, channel, [])
    try:
        yield r
    finally:
        face.close()
        for net, bus in [(network, master_bus), *r._extra, (drive_net, drive_bus)]:
            _close(net, bus)


def start(rig: Rig) -> None:
    """Heard in PRE-OPERATIONAL, PDOs read by SDO, then NMT start and TPDO1 seen periodic (the
    master then waits for statuswords instead of reading them by SDO)."""
    node = rig.node
    node.nmt.wait_for_heartbeat(5)
    assert node.nmt.state == "PRE-OPERATIONAL"
    node.setup_402_state_machine()
    node.nmt.state = "OPERATIONAL"
    assert node.tpdo[1].wait_for_reception(5) is not None
    wait_for(lambda: node.tpdo[1].is_periodic)
    wait_for(lambda: node.state == "SWITCH ON DISABLED")


def test_base_node_402_master_runs_profiled_velocity_and_quick_stops(rig: Rig) -> None:
    node = rig.node
    node.nmt.wait_for_heartbeat(5)
    node.sdo[0x1800][5].raw = 20  # event timer by SDO in PRE-OPERATIONAL
    node.sdo[0x1801][5].raw = 20
    start(rig)
    assert 0x6040 in node.rpdo_pointers  # controlword by RPDO1
    node.op_mode = "PROFILED VELOCITY"
    assert node.op_mode == "PROFILED VELOCITY"
    node.sdo[0x60FF].raw = 40_000  # 40 rad/s
    node.state = "OPERATION ENABLED"
    assert rig.model.state == "OPERATION ENABLED"
    wait_for(lambda: abs(node.tpdo_values[0x606C] - 40_000) < 100)
    wait_for(lambda: node.statusword & 0x0400 != 0)  # target reached
    t0 = time.monotonic()
    time.sleep(1.0)
    times = [t for t, _ in rig.frames.of(0x18A) if t >= t0]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert len(gaps) >= 10
    assert 0.010 <= statistics.median(gaps) <= 0.040  # the 20 ms event timer
    velocity = rig.frames.of(0x28A)[-1][1][0:4]
    assert abs(int.from_bytes(velocity, "little", signed=True) - 40_000) < 100
    drawn = rig.face.status()["drawn_uj"]
    assert drawn > 0.5 * 1e-4 * 40**2 * 1e6  # at least the kinetic energy
    node.controlword = State402.CW_QUICK_STOP  # option 2: stop, then SWITCH ON DISABLED
    wait_for(lambda: node.state == "SWITCH ON DISABLED")
    assert abs(node.tpdo_values[0x606C]) < 20
    status = rig.face.status()
    assert status["quick_stop_count"] == 1
    states = [h["state"] for h in status["history"]]
    assert states[-2:] == ["QUICK STOP ACTIVE", "SWITCH ON DISABLED"]
    node.state = "OPERATION ENABLED"
    node.state = "SWITCH ON DISABLED"  # disable voltage: 9
    assert rig.model.state == "SWITCH ON DISABLED"
    assert status["bad_writes"] == 0 and status["decode_errors"] == 0


def test_master_heartbeat_loss_faults_the_drive(rig: Rig) -> None:
    node = rig.node
    node.nmt.wait_for_heartbeat(5)
    node.sdo[0x1016][1].raw = MASTER << 16 | 300  # 300 ms
    heartbeat = rig.network.send_periodic(0x700 + MASTER, [5], 0.05)
    try:
        wait_for(lambda: rig.model.heartbeat_active)
        node.sdo[0x6060].raw = 3
        node.sdo[0x60FF].raw = 20_000
        for cw in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = cw
        time.sleep(0.5)
        assert rig.model.state == "OPERATION ENABLED"  # the heartbeat keeps it running
    finally:
        heartbeat.stop()
    stopped = monotonic_us()
    emcy = node.emcy.wait(0x8130, timeout=10)
    assert emcy is not None
    wait_for(lambda: node.sdo[0x6041].raw & 0x4F == 0x08)  # FAULT
    assert node.sdo[0x603F].raw == 0x8130
    assert node.sdo[0x1001].raw & 1
    reaction = next(t for t, s in rig.model.psm.history if s == "FAULT REACTION ACTIVE")
    assert 300_000 - 60_000 <= reaction - stopped <= 300_000 + 2_000_000
    status = rig.face.status()
    assert status["fault_reason"] == "heartbeat consumer timeout"
    assert status["heartbeat_timeouts"] == 1
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80  # fault reset
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    assert node.sdo[0x603F].raw == 0


def test_sync_triggers_tpdos_of_transmission_type_1(rig: Rig) -> None:
    node = rig.node
    node.nmt.wait_for_heartbeat(5)
    node.sdo[0x1800][2].raw = 1
    for comm in (0x1801, 0x1802):
        node.sdo[comm][1].raw = node.sdo[comm][1].raw | 0x8000_0000  # invalid
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.2)
    assert rig.frames.of(0x18A) == [] and rig.frames.of(0x28A) == []
    for _ in range(5):
        rig.network.sync.transmit()
        time.sleep(0.02)
    wait_for(lambda: len(rig.frames.of(0x18A)) == 5)
    time.sleep(0.2)
    assert len(rig.frames.of(0x18A)) == 5 and rig.frames.of(0x38A) == []
    sw = int.from_bytes(rig.frames.of(0x18A)[-1][1][0:2], "little")
    assert sw & 0x4F == 0x40


def test_a_second_master_reads_by_sdo_while_the_first_runs_the_drive(rig: Rig) -> None:
    start(rig)
    node = rig.node
    node.op_mode = "PROFILED VELOCITY"
    node.sdo[0x60FF].raw = 30_000
    net, _ = rig.master()
    other = canopen.RemoteNode(NODE, CIA402_EDS)
    net.add_node(other)
    other.sdo.RESPONSE_TIMEOUT = 5.0  # a loaded host answers late
    seen: list[tuple[int, int]] = []
    garbled: list[Exception] = []
    done = threading.Event()

    def poll() -> None:
        while not done.is_set():
            try:
                seen.append((other.sdo[0x6041].raw, other.sdo[0x606C].raw))
            except canopen.SdoCommunicationError as e:  # an answer to the other master's
                garbled.append(e)  # request (both share the drive's SDO server): read again

    reader = threading.Thread(target=poll)
    reader.start()
    try:
        node.state = "OPERATION ENABLED"  # RPDO controlwords, TPDO statuswords
        wait_for(lambda: abs(node.tpdo_values[0x606C] - 30_000) < 100)
        wait_for(
            lambda: len(seen) > 20 and abs(seen[-1][1] - 30_000) < 200,
            show=lambda: (seen[-3:], garbled[-3:]),
        )
    finally:
        done.set()
        reader.join(10)
    assert any(sw & 0x6F == 0x27 for sw, _ in seen)  # OPERATION ENABLED, read by SDO
    assert rig.model.state == "OPERATION ENABLED"


def test_bad_sdo_writes_are_aborted_and_counted(rig: Rig) -> None:
    node = rig.node
    node.nmt.wait_for_heartbeat(5)
    bad = [(0x6060, 1), (0x6085, 0), (0x6041, 0x27)]
    for index, value in bad:
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo[index].raw = value
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo.download(0x6040, 0, b"\x01\x02\x03\x04")  # wrong length
    assert rig.face.status()["bad_writes"] == 4
    assert node.sdo[0x6060].raw == 0 and node.sdo[0x6041].raw & 0x4F == 0x40


def test_a_guard_writes_the_limits_reads_them_back_and_reads_the_energy(rig: Rig) -> None:
    """0x6072, 0x6073 and 0x6080 by SDO (raw, whatever the master's EDS has), 0 refused for
    0x6080 only; 0x2011 is the drive's energy drawn."""
    sdo = rig.node.sdo
    rig.node.nmt.wait_for_heartbeat(5)
    for index, value in ((0x6072, 0), (0x6073, 0), (0x6080, 5_000), (0x6072, 800)):
        sdo.download(index, 0, value.to_bytes(4 if index == 0x6080 else 2, "little"))
        assert int.from_bytes(sdo.upload(index, 0), "little") == value
    with pytest.raises(canopen.SdoAbortedError):
        sdo.download(0x6080, 0, bytes(4))
    with rig.face.lock:
        rig.model.motor.energy.drawn.uj = 2**32 + 1_234
    assert sdo.upload(0x2011, 0) == (1_234).to_bytes(4, "little")
    assert rig.model.read(0x6080) == 5_000 and rig.model.bad_writes == 1
