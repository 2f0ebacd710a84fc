"""CANopen beside canergy on one virtual bus: EDS objects, NMT gating, heartbeat watchdog, audit."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from support.live_rig import TIMING, Loop

from canergy.codec import ID_MASK, Codec
from canergy.core import Supervisor
from canergy.live.canopen.manager import CanopenManager
from canergy.live.canopen.shared_bus import EDS, STANDARD_FRAMES, shared_network
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.ledger import Ledger
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.messages import MAX_NODE, MIN_NODE, Direction, MsgType
from canergy.units import UJ_PER_J
from firmware_model.actuator import PowerProfile
from firmware_model.canopen_node import CanopenFace
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

NODES = (1, 2)


@dataclass
class Bench:
    channel: str
    host: NodeHost
    faces: dict[int, CanopenFace]
    service: SupervisorService
    manager: CanopenManager

    def wait(self, condition: object, timeout_s: float = 30) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():  # type: ignore[operator]
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.02)


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    channel = f"co-{uuid.uuid4().hex}"
    codec = Codec()
    now = monotonic_us()
    config = NodeConfig(
        power=PowerProfile.constant(0.5), timing=TIMING, telemetry_period_us=200_000
    )
    nodes = [
        FirmwareNode(n, NvStore(tmp_path / f"{n}.nv", n, fsync=False), config, now) for n in NODES
    ]
    host = NodeHost(nodes)
    node_bus = can.Bus(interface="virtual", channel=channel)
    node_net, node_reader = shared_network(node_bus)
    faces = {n.node: CanopenFace(n, node_net) for n in nodes}
    for face in faces.values():
        face.boot()
        face.local.nmt.start_heartbeat(100)
    sup_bus = can.Bus(
        interface="virtual",
        channel=channel,
        can_filters=[*codec.supervisor_filters(), STANDARD_FRAMES],
    )
    sup_net, sup_reader = shared_network(sup_bus)
    manager = CanopenManager(sup_net, NODES, EDS, 500_000, monotonic_us)
    service = build_service(
        Supervisor(NODES, 100 * UJ_PER_J, timing=TIMING),
        ServiceConfig(policy=TopUp(UJ_PER_J), limits=Limits(max_grant=UJ_PER_J), fsync=False),
        now,
        liveness=manager.alive,
    )
    loops = [
        Loop(
            BusRuntime(
                node_bus, host, codec=codec, receives=Direction.TO_CLIENT, source=node_reader
            )
        ),
        Loop(
            BusRuntime(
                sup_bus, service, codec=codec, receives=Direction.TO_SUPERVISOR, source=sup_reader
            )
        ),
    ]
    try:
        yield Bench(channel, host, faces, service, manager)
    finally:
        for loop in loops:
            loop.runtime.bus.stop_all_periodic_tasks()
            loop.stop.set()
        for net in (node_net, sup_net):
            net.notifier.stop()
        for loop in loops:
            loop.halt()


def test_nodes_get_grants_only_once_started(bench: Bench) -> None:
    time.sleep(0.5)
    assert all(n.client.state.credited == 0 for n in bench.host.nodes.values())  # PRE-OPERATIONAL
    bench.manager.start_all()
    bench.wait(lambda: all(n.client.state.credited >= UJ_PER_J for n in bench.host.nodes.values()))
    assert all(f.local.nmt.state == "OPERATIONAL" for f in bench.faces.values())


def test_an_eds_only_master_reads_every_energy_object(bench: Bench) -> None:
    bench.manager.start_all()
    bench.wait(lambda: bench.host.nodes[1].client.state.credited > 0)
    master = canopen.Network()
    master.connect(interface="virtual", channel=bench.channel)
    try:
        remote = master.add_node(canopen.RemoteNode(1, str(EDS)))
        names = [o.name for o in remote.object_dictionary.values() if 0x2000 <= o.index < 0x6000]
        values = {name: remote.sdo[name].raw for name in names}
        assert len(values) == 11
        state = bench.host.nodes[1].client.state
        assert values["Credited uJ"] == state.credited
        # the actuator spends while the objects are read one SDO transfer at a time: read
        # Spent before Usable, so that what moved from one to the other in between is not
        # counted twice (a run under load read Usable, then a Spent 53 mJ further on)
        spent = remote.sdo["Spent uJ"].raw
        usable = remote.sdo["Usable budget uJ"].raw
        credited = bench.host.nodes[1].client.state.credited  # read after both
        assert spent >= values["Spent uJ"] and usable + spent <= credited
        assert values["Response timeout ms"] == TIMING.response_timeout_us // 1000
        remote.sdo["Power mW"].raw = 250
        assert bench.host.nodes[1].actuator.profile.power_uw(0) == 250_000
        assert remote.sdo["Identity object"]["Product code"].raw == 1
    finally:
        master.disconnect()


def test_heartbeat_loss_stops_grants_and_a_restart_resumes(bench: Bench) -> None:
    bench.manager.start_all()
    node2 = bench.host.nodes[2]
    bench.wait(lambda: node2.client.state.credited >= UJ_PER_J)
    bench.faces[2].local.nmt.stop_heartbeat()
    bench.wait(lambda: bench.service.status()["nodes"]["2"]["lost"], timeout_s=10)
    granted = node2.client.state.credited
    time.sleep(2.5)  # node 2 spends 0.5 W and reports a low level: no grant may follow
    assert node2.client.state.credited == granted
    assert bench.service.status()["nodes"]["1"]["lost"] is False
    bench.faces[2].local.nmt.start_heartbeat(100)
    bench.wait(lambda: node2.client.state.credited > granted, timeout_s=10)


def test_nmt_stop_halts_the_actuator_and_refuses_grants(bench: Bench) -> None:
    bench.manager.start_all()
    node1 = bench.host.nodes[1]
    bench.wait(lambda: node1.client.state.credited >= UJ_PER_J)
    bench.manager.remotes[1].nmt.state = "STOPPED"
    bench.wait(lambda: bench.faces[1].local.nmt.state == "STOPPED")
    time.sleep(0.5)
    spent = node1.client.state.spent
    time.sleep(0.5)
    assert node1.client.state.spent == spent and node1.actuator.halted


def test_the_sdo_audit_matches_the_books(bench: Bench) -> None:
    bench.manager.start_all()
    bench.wait(lambda: all(n.client.state.credited >= UJ_PER_J for n in bench.host.nodes.values()))
    report = bench.manager.audit(bench.service.ledger.books)
    assert report["consistent"], report
    assert all(report["nodes"][str(n)]["credited_uj"] > 0 for n in NODES)


def test_the_control_sockets_sdo_audit_reads_the_books_on_the_loop_thread(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``{"audit": true}``: the SDO reads block, so they run on a thread of their own; the
    comparison with the books is handed back to the loop thread, the only one that touches
    them (a C core's sessions are then never read while a frame is handled)."""
    import queue
    import threading

    from canergy.live.serve import answer_control

    bench.manager.start_all()
    bench.wait(lambda: all(n.client.state.credited >= UJ_PER_J for n in bench.host.nodes.values()))
    posted: queue.SimpleQueue[Any] = queue.SimpleQueue()
    readers: list[threading.Thread] = []
    replies: list[dict[str, Any]] = []
    books = Ledger.books

    def watched_books(ledger: Ledger) -> dict[int, dict[str, int]]:
        readers.append(threading.current_thread())
        return books(ledger)

    monkeypatch.setattr(Ledger, "books", watched_books)  # the class's: nothing of the service
    answer_control(bench.service, {"audit": True}, replies.append, bench.manager, posted.put)
    compare = posted.get(timeout=30)  # the reads done, off this thread
    assert replies == [] and readers == []
    compare()
    assert readers == [threading.current_thread()]
    (report,) = replies
    assert report["consistent"], report
    assert all(report["nodes"][str(n)]["credited_uj"] > 0 for n in NODES)


def test_canergy_ids_never_collide_with_the_cia_301_predefined_set() -> None:
    """CiA 301 predefined connection set: 11-bit ids only. canergy uses only 29-bit ids, so the
    two cannot meet on the wire; the numbers do not overlap either."""
    predefined = {0x000, 0x080, 0x100}  # NMT, SYNC, TIME
    for node in range(MIN_NODE, MAX_NODE + 1):
        predefined |= {0x080 + node, 0x580 + node, 0x600 + node, 0x700 + node}  # EMCY, SDO, HB
        predefined |= {
            base + node for base in (0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480, 0x500)
        }
    codec = Codec()
    ours = {codec.arbitration_id(t, n) for t in MsgType for n in range(MIN_NODE, MAX_NODE + 1)}
    assert max(predefined) <= 0x7FF and not ours & predefined
    assert all(i & ID_MASK == codec.id_base and i > 0x7FF for i in ours)
    assert all(not codec.is_canergy_id(i, extended=False) for i in predefined)


def test_a_rebooted_node_is_started_again_and_resumes(bench: Bench) -> None:
    bench.manager.start_all()
    node2 = bench.host.nodes[2]
    bench.wait(lambda: node2.client.state.credited >= UJ_PER_J)
    bench.faces[2].boot()  # boot-up message, PRE-OPERATIONAL: no grants
    bench.faces[2].local.nmt.start_heartbeat(100)
    bench.wait(lambda: bench.manager.state_name(2) == "PRE-OPERATIONAL")
    assert bench.manager.rebooted() == [2]  # and NMT start went out to node 2
    bench.wait(lambda: bench.faces[2].local.nmt.state == "OPERATIONAL")
    bench.service.node_rebooted(2, monotonic_us())
    granted = node2.client.state.credited
    bench.wait(lambda: node2.client.state.credited > granted, timeout_s=15)
