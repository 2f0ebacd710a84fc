"""The emulated DC bus power meter: its counter without CAN, then on python-can's ``virtual`` bus
(generous timeouts, no assertion on tight timing) and beside the drive in
``python -m firmware_model.drive --power-meter``."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.drive_model import MS, enabled
from support.virtual_bus import Frames, wait_for

import firmware_model.drive.__main__ as drive_main
from canergy.live.runtime import monotonic_us
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import EDS, DriveAbort
from firmware_model.drive.power_meter import METER_EDS, PowerMeterFace, PowerMeterModel

METER = 20
TPDO1 = 0x180 + METER


def counter(uj: int) -> int:
    return uj // 1000 % 2**16


# -- the model --------------------------------------------------------------------------------


@given(st.integers(0, 2**45))
def test_the_counter_is_whole_mj_modulo_2_16(uj: int) -> None:
    meter = PowerMeterModel(METER, lambda: uj)
    assert meter.read(0x2100) == counter(uj)


def test_the_counter_follows_the_drive_and_wraps_at_65_535_j() -> None:
    drive = enabled({0x60FF: 50_000})
    meter = PowerMeterModel(METER, lambda: drive.drawn_uj, voltage_mv=lambda: drive.read(0x6079))
    last, total_mj = meter.read(0x2100), 0
    for t in range(10 * MS, 500 * MS, 10 * MS):
        drive.advance(t)
        now = meter.read(0x2100)
        total_mj += (now - last) % 2**16  # how a reader undoes the wrap
        last = now
        assert now == counter(drive.drawn_uj)
    assert total_mj == drive.drawn_uj // 1000 > 0
    assert meter.read(0x2101) == 24_000
    drive.motor.energy.drawn.uj = 65_535_999
    assert meter.read(0x2100) == 65_535
    drive.motor.energy.drawn.uj = 65_536_000 + 1_999
    assert meter.read(0x2100) == 1
    status = meter.status()
    assert (status["node"], status["energy_mj"], status["voltage_mv"]) == (METER, 1, 24_000)


def test_tpdo1_goes_every_event_timer_period_in_operational_only() -> None:
    energy = [0]
    meter = PowerMeterModel(METER, lambda: energy[0], defaults={(0x1800, 5): 20})
    assert meter.due_tpdos(MS) == []  # PRE-OPERATIONAL
    meter.set_nmt("OPERATIONAL", MS)
    sent = []
    for t in range(MS, 201 * MS, MS):
        energy[0] = t * 10  # 10 mW
        sent += [(t, frame) for frame in meter.due_tpdos(t)]
    assert [t for t, _ in sent] == list(range(MS, 201 * MS, 20 * MS))
    assert all(
        cob == TPDO1 and data == counter(t * 10).to_bytes(2, "little") for t, (cob, data) in sent
    )
    meter.set_nmt("STOPPED", 202 * MS)
    assert meter.due_tpdos(300 * MS) == []


def test_the_energy_is_read_only_and_the_mapping_can_take_the_voltage() -> None:
    meter = PowerMeterModel(METER, lambda: 5_000, voltage_mv=lambda: 48_000)
    with pytest.raises(DriveAbort):
        meter.write(0x2100, 0, 0)
    meter.write(0x1800, 1, 0x8000_0000 | TPDO1)
    meter.write(0x1A00, 0, 0)
    meter.write(0x1A00, 2, 0x21010020)
    meter.write(0x1A00, 0, 2)
    meter.write(0x1800, 1, TPDO1)
    meter.set_nmt("OPERATIONAL", MS)
    assert meter.due_tpdos(MS) == [
        (TPDO1, (5).to_bytes(2, "little") + (48_000).to_bytes(4, "little"))
    ]
    meter.reset(application=False, now_us=2 * MS)  # reset communication: the default mapping
    assert meter.values[0x1A00, 0] == 1 and meter.nmt == "PRE-OPERATIONAL"
    assert meter.bad_writes == 1


# -- on the virtual bus -----------------------------------------------------------------------


@dataclass
class MeterRig:
    face: PowerMeterFace
    network: canopen.Network
    node: canopen.RemoteNode
    frames: Frames
    energy: list[int]


def _close(network: canopen.Network) -> None:
    if network.notifier is not None:
        network.notifier.stop()
    if network.bus is not None:
        network.bus.shutdown()


@pytest.fixture
def meter_rig() -> Iterator[MeterRig]:
    channel = f"meter-{uuid.uuid4().hex}"
    energy = [1_234_567]
    meter_net = drive_network(can.Bus(interface="virtual", channel=channel))
    model = PowerMeterModel(METER, lambda: energy[0], monotonic_us())
    face = PowerMeterFace(model, meter_net)
    network = drive_network(can.Bus(interface="virtual", channel=channel))
    frames = Frames()
    assert network.notifier is not None
    network.notifier.add_listener(frames)
    node = canopen.RemoteNode(METER, str(METER_EDS))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    network.add_node(node)
    face.boot()
    face.start()
    try:
        yield MeterRig(face, network, node, frames, energy)
    finally:
        face.close()
        _close(network)
        _close(meter_net)


def test_a_master_reads_the_counter_by_sdo_and_its_tpdo_mapping(meter_rig: MeterRig) -> None:
    node = meter_rig.node
    node.nmt.wait_for_heartbeat(5)
    assert node.nmt.state == "PRE-OPERATIONAL"
    assert node.sdo[0x2100].raw == 1234
    meter_rig.energy[0] = 70_000_000  # past 65.535 J
    assert node.sdo[0x2100].raw == 70_000 - 65_536
    assert node.sdo[0x1018][2].raw == 0x403
    node.tpdo.read()
    tpdo = node.tpdo[1]
    assert tpdo.enabled and tpdo.cob_id == TPDO1 and tpdo.trans_type == 254
    assert tpdo.event_timer == 10
    assert [(var.index, var.length) for var in tpdo] == [(0x2100, 16)]


def test_tpdo1_goes_on_the_bus_every_period_after_nmt_start(meter_rig: MeterRig) -> None:
    node, frames = meter_rig.node, meter_rig.frames
    node.nmt.wait_for_heartbeat(5)
    node.sdo[0x1800][5].raw = 20
    time.sleep(0.2)
    assert frames.of(TPDO1) == []  # PRE-OPERATIONAL
    node.nmt.state = "OPERATIONAL"
    wait_for(lambda: len(frames.of(TPDO1)) >= 30)
    gaps = [b - a for (a, _), (b, _) in zip(frames.of(TPDO1), frames.of(TPDO1)[1:], strict=False)]
    assert 0.010 <= statistics.median(gaps) <= 0.040  # the 20 ms event timer
    meter_rig.energy[0] = 65_537_000
    wait_for(lambda: frames.of(TPDO1)[-1][1] == (1).to_bytes(2, "little"))
    node.nmt.state = "STOPPED"
    time.sleep(0.1)
    count = len(frames.of(TPDO1))
    time.sleep(0.3)
    assert len(frames.of(TPDO1)) == count
    assert meter_rig.face.status()["bad_writes"] == 0


# -- beside the drive: python -m firmware_model.drive --power-meter ----------------------------


def _run_for(seconds: float) -> Callable[..., None]:
    """``DriveFace.run`` that stops by itself after ``seconds``."""
    real = DriveFace.run

    def run(self: DriveFace, stop: Callable[[], bool], every: Callable[[int], None]) -> None:
        end = time.monotonic() + seconds
        real(self, lambda: stop() or time.monotonic() > end, every)

    return run


def test_the_drive_runs_a_meter_of_its_energy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    channel = f"meter-main-{uuid.uuid4().hex}"
    network = drive_network(can.Bus(interface="virtual", channel=channel))
    frames = Frames()
    assert network.notifier is not None
    network.notifier.add_listener(frames)
    drive = canopen.RemoteNode(10, str(EDS))
    drive.sdo.RESPONSE_TIMEOUT = 2.0
    network.add_node(drive)
    monkeypatch.setattr(DriveFace, "run", _run_for(3.0))
    status_file = tmp_path / "status.json"
    argv = ["--node", "10", "-i", "virtual", "-c", channel, "--power-meter", str(METER)]
    argv += ["--pdo-period", "20ms", "--status-file", str(status_file)]
    result: list[int] = []

    def application() -> None:
        """Once both nodes booted: NMT start all, run the drive in PV by SDO."""
        wait_for(lambda: bool(frames.of(0x700 + METER) and frames.of(0x70A)))
        network.nmt.state = "OPERATIONAL"
        for index, value in ((0x6060, 3), (0x60FF, 40_000), *((0x6040, cw) for cw in (6, 7, 15))):
            drive.sdo[index].raw = value

    app = threading.Thread(target=application, daemon=True)
    app.start()
    try:
        result.append(drive_main.main(argv))
    finally:
        app.join(10)
        _close(network)
    assert result == [0]
    status = json.loads(status_file.read_text())
    meter = status["power_meter"]
    assert meter["node"] == METER and meter["nmt"] == "OPERATIONAL"
    # the drive's figures are of the instant the meter read it (it advances the drive to then)
    assert meter["energy_mj"] == counter(status["drawn_uj"])
    assert meter["energy_mj"] > 0
    sent = [int.from_bytes(data, "little") for _, data in frames.of(TPDO1)]
    assert len(sent) >= 20 and sent == sorted(sent) and 0 < sent[-1] <= meter["energy_mj"]


_LOCKS_SCRIPT = """
import os, signal, sys, threading, time
import can, canopen
import firmware_model.drive.__main__ as drive_main
from firmware_model.drive.canopen_face import drive_network
from firmware_model.drive.power_meter import METER_EDS

sys.setswitchinterval(1e-6)  # threads switch as often as they can: any lock order shows
channel, status, meter_id = sys.argv[1], sys.argv[2], int(sys.argv[3])
network = drive_network(can.Bus(interface="virtual", channel=channel))
meter = canopen.RemoteNode(meter_id, str(METER_EDS))
meter.sdo.RESPONSE_TIMEOUT = 5.0
network.add_node(meter)
seen = {0x700 + meter_id: 0, 0x70A: 0, 0x180 + meter_id: 0}
for cob_id in seen:
    network.subscribe(cob_id, lambda cob_id, data, ts: seen.__setitem__(cob_id, seen[cob_id] + 1))

def application():
    try:
        while not (seen[0x700 + meter_id] and seen[0x70A]):
            time.sleep(0.01)
        network.nmt.state = "OPERATIONAL"
        reads, end = 0, time.monotonic() + 2.5
        while time.monotonic() < end:
            meter.sdo[0x2100].raw
            reads += 1
        print("reads", reads, "tpdos", seen[0x180 + meter_id], flush=True)
    except Exception as exc:
        print("failed:", repr(exc), flush=True)
    os.kill(os.getpid(), signal.SIGINT)

threading.Thread(target=application, daemon=True).start()
argv = ["--node", "10", "-i", "virtual", "-c", channel, "--power-meter", str(meter_id)]
argv += ["--pdo-period", "1ms", "--status-file", status, "--status-period", "1ms"]
sys.exit(drive_main.main(argv))
"""


def test_the_status_and_the_meters_own_reads_never_wait_on_each_other(tmp_path: Path) -> None:
    """The status (written every tick here) reads the meter and the drive at one instant while
    the meter's TPDO (every 1 ms) and its SDO server read the drive from their own threads:
    locks taken in opposite orders deadlock the process (the vcan suite caught one). A process
    of its own: a deadlocked one is ended by the timeout."""
    status = tmp_path / "status.json"
    channel = f"locks-{uuid.uuid4().hex}"
    argv = [sys.executable, "-c", _LOCKS_SCRIPT, channel, str(status), str(METER)]
    try:
        run = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    except subprocess.TimeoutExpired as exc:
        hang = "the drive's process hangs (its threads wait on each other)"
        raise AssertionError(f"{hang}: {exc}") from None
    assert run.returncode == 0, run.stdout + run.stderr
    words = run.stdout.split()
    assert words[:1] == ["reads"], run.stdout + run.stderr
    assert int(words[1]) > 20 and int(words[3]) > 100, run.stdout
    assert json.loads(status.read_text())["power_meter"]["node"] == METER
