"""canergy frames between hosts over Eclipse Zenoh: the ``zenoh`` python-can interface.

Every session here listens on or connects to ``tcp/127.0.0.1:<free port>`` only; multicast
scouting and gossip are off (the bus never turns them on), so nothing leaves this machine.
"""

from __future__ import annotations

import json
import random
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from support.live_rig import Loop, Rig
from support.zenoh_loopback import endpoint, free_port, site

from canergy.cli import main
from canergy.codec import Codec
from canergy.faults import FaultInjector, FaultProfile
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.live.transports.faulty_bus import FaultyBus
from canergy.live.transports.zenoh_bus import (
    MalformedFrame,
    ZenohBus,
    decode_frame,
    encode_frame,
    frame_key,
    parse_endpoints,
    zenoh_config,
)
from canergy.messages import Direction
from canergy.units import UJ_PER_J
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

TIMEOUT_S = 30.0


def link(a: can.BusABC, b: can.BusABC) -> None:
    """Wait until frames flow both ways (the session connects and subscriptions propagate)."""
    probe = can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"probe")
    for sender, receiver in ((a, b), (b, a)):
        deadline = time.monotonic() + TIMEOUT_S
        while receiver.recv(0.05) is None:
            assert time.monotonic() < deadline, "the zenoh sessions never linked"
            sender.send(probe)
    for bus in (a, b):  # drop the probes still on their way
        time.sleep(0.2)
        while bus.recv(0) is not None:
            pass


@pytest.fixture
def pair() -> Iterator[tuple[ZenohBus, ZenohBus]]:
    """A listening and a connecting bus on one site, linked."""
    port, name = free_port(), site()
    a = ZenohBus(name, listen=endpoint(port), fd=True)
    b = ZenohBus(name, connect=endpoint(port), fd=True)
    try:
        link(a, b)
        yield a, b
    finally:
        a.shutdown()
        b.shutdown()


def zenoh_bus(
    name: str, filters: list[dict[str, int | bool]], listen: str = "", connect: str = ""
) -> can.BusABC:
    """Opened as canergy's commands open it: through python-can's interface registry."""
    return can.Bus(
        interface="zenoh", channel=name, can_filters=filters, listen=listen, connect=connect
    )


def content(msg: can.Message) -> tuple[object, ...]:
    return (
        msg.arbitration_id,
        msg.is_extended_id,
        msg.is_remote_frame,
        msg.is_error_frame,
        msg.is_fd,
        msg.bitrate_switch,
        msg.error_state_indicator,
        msg.dlc,
        bytes(msg.data),
    )


FRAMES = [
    can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02\x03"),
    can.Message(arbitration_id=0x0CE00101, data=bytes(range(8))),
    can.Message(arbitration_id=0x0CE00901, data=b""),
    can.Message(arbitration_id=0x0CE00102, is_fd=True, bitrate_switch=True, data=bytes(64)),
    can.Message(arbitration_id=0x7A, is_extended_id=False, is_fd=True, data=bytes(range(12))),
    can.Message(arbitration_id=0x1FFFFFFF, is_remote_frame=True, dlc=4),
    can.Message(arbitration_id=0x001, is_extended_id=False, is_remote_frame=True, dlc=0),
]


# -- wire format (no network) ---------------------------------------------------------------
@pytest.mark.parametrize("frame", FRAMES)
def test_the_encoding_round_trips(frame: can.Message) -> None:
    key = frame_key("lab", frame.arbitration_id, frame.is_extended_id)
    wire = decode_frame(key, encode_frame(frame, b"8 bytes!", 1234.5), "lab")
    assert content(wire.message) == content(frame)
    assert wire.sender == b"8 bytes!" and wire.sent_at == 1234.5
    assert decode_frame(key, encode_frame(frame, b"8 bytes!"), "lab").sent_at is None


def test_keys_name_site_and_identifier() -> None:
    assert frame_key("lab", 0x0CE00101, True) == "canergy/lab/0CE00101"
    assert frame_key("lab", 0x12, False) == "canergy/lab/012"


@pytest.mark.parametrize(
    ("key", "payload"),
    [
        ("canergy/other/0CE00101", encode_frame(FRAMES[1], bytes(8))),  # another site
        ("canergy/lab/0ce00101", encode_frame(FRAMES[1], bytes(8))),  # lower case
        ("canergy/lab/123", encode_frame(FRAMES[1], bytes(8))),  # extended flag, 3 digits
        ("canergy/lab/0CE00101", encode_frame(FRAMES[1], bytes(8))[:-1]),  # truncated
        ("canergy/lab/0CE00101", b"\x01"),
        ("canergy/lab/0CE00101", b"\x41" + bytes(9)),  # reserved flag
        ("canergy/lab/0CE00101", b"\x01" + bytes(8) + b"\x09" + bytes(9)),  # 9 classic bytes
        ("canergy/lab/3FFFFFFF", b"\x01" + bytes(9)),  # identifier above 29 bits
    ],
)
def test_malformed_samples_are_refused(key: str, payload: bytes) -> None:
    with pytest.raises(MalformedFrame):
        decode_frame(key, payload, "lab")


@pytest.mark.parametrize(
    "bad",
    [
        "udp/224.0.0.224:7446",
        "tcp/239.1.2.3:7447",
        "udp/[ff02::1]:7447",
        "udp/multicast.example:7447",
        "tcp/127.0.0.1:7447#iface=lo",
        "ws/127.0.0.1:7447",
        "tcp/127.0.0.1",
        "tcp/127.0.0.1:99999",
    ],
)
def test_a_non_unicast_endpoint_is_refused(bad: str) -> None:
    with pytest.raises(ValueError, match="zenoh connect endpoint"):
        parse_endpoints(f"tcp/127.0.0.1:7447,{bad}", role="connect")
    with pytest.raises(ValueError, match="zenoh listen endpoint"):
        can.Bus(interface="zenoh", channel="lab", listen=bad)


def test_endpoints_and_config() -> None:
    assert parse_endpoints("tcp/127.0.0.1:1, udp/[::1]:2", role="connect") == [
        "tcp/127.0.0.1:1",
        "udp/[::1]:2",
    ]
    config = zenoh_config("peer", ["tcp/127.0.0.1:7447"], [])
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/gossip/enabled")) is False
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("connect/endpoints")) == []
    with pytest.raises(ValueError, match="client"):
        zenoh_config("client", [], [])
    with pytest.raises(ValueError, match="mode"):
        zenoh_config("router", [], ["tcp/127.0.0.1:1"])
    with pytest.raises(ValueError, match="site"):
        ZenohBus("a/b")


def test_the_cli_refuses_a_multicast_endpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["grant", "--node", "1", "--amount", "1J", "--state", str(tmp_path / "s.json")]
    bus = ["-i", "zenoh", "-c", "lab", "--bus-kwargs", "connect=udp/224.0.0.1:7447"]
    assert main([*argv, *bus]) == 2
    err = capsys.readouterr().err
    assert "cannot open" in err and "multicast" in err


# -- two participants on loopback -----------------------------------------------------------
def test_frames_travel_both_ways_unchanged(pair: tuple[ZenohBus, ZenohBus]) -> None:
    a, b = pair
    for sender, receiver in ((a, b), (b, a)):
        for frame in FRAMES:
            sender.send(frame)
        got = [receiver.recv(TIMEOUT_S) for _ in FRAMES]
        assert [content(m) for m in got if m is not None] == [content(f) for f in FRAMES]
        assert all(m is not None and m.is_rx and m.channel == a.site for m in got)
    assert a.state is can.BusState.ACTIVE and a.malformed == b.malformed == 0


def test_own_frames_are_not_received(pair: tuple[ZenohBus, ZenohBus]) -> None:
    a, b = pair
    a.send(FRAMES[1])
    assert b.recv(TIMEOUT_S) is not None
    b.send(FRAMES[0])
    got = a.recv(TIMEOUT_S)
    assert got is not None and content(got) == content(FRAMES[0])  # not its own FRAMES[1]
    assert a.recv(0.3) is None and b.recv(0.3) is None


def test_own_frames_on_request_and_a_third_participant(pair: tuple[ZenohBus, ZenohBus]) -> None:
    a, _ = pair
    port = free_port()
    c = ZenohBus(a.site, listen=endpoint(port), receive_own_messages=True)
    d = ZenohBus(a.site, connect=endpoint(port))  # two more participants, one process
    try:
        link(c, d)
        c.send(FRAMES[1])
        own = c.recv(TIMEOUT_S)
        assert own is not None and not own.is_rx and content(own) == content(FRAMES[1])
        assert d.recv(TIMEOUT_S) is not None
    finally:
        c.shutdown()
        d.shutdown()


def test_filters_apply(pair: tuple[ZenohBus, ZenohBus]) -> None:
    a, b = pair
    b.set_filters([{"can_id": 0x0CE00100, "can_mask": 0x1FFFFF00, "extended": True}])
    for arbitration_id in (0x0CE00201, 0x0CE00101):
        a.send(can.Message(arbitration_id=arbitration_id, data=b"\x00"))
    a.send(can.Message(arbitration_id=0x101, is_extended_id=False))
    got = b.recv(TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x0CE00101
    assert b.recv(0.5) is None


def test_a_classic_bus_refuses_to_send_fd() -> None:
    bus = ZenohBus(site())
    try:
        with pytest.raises(can.CanOperationError, match="fd=True"):
            bus.send(FRAMES[3])
    finally:
        bus.shutdown()
    with pytest.raises(can.CanOperationError, match="shut down"):
        bus.send(FRAMES[0])
    with pytest.raises(can.CanOperationError, match="shut down"):
        bus.recv(0)


def test_shutdown_leaves_no_thread_behind() -> None:
    before = set(threading.enumerate())
    port, name = free_port(), site()
    a = can.Bus(interface="zenoh", channel=name, listen=endpoint(port))
    b = can.Bus(interface="zenoh", channel=name, connect=endpoint(port))
    link(a, b)
    assert set(threading.enumerate()) > before  # zenoh's callback threads, one per bus
    waiting: list[BaseException] = []

    def blocked_reader() -> None:  # a reader blocked forever is woken by the shutdown
        try:
            a.recv(None)
        except can.CanOperationError as exc:
            waiting.append(exc)

    reader = threading.Thread(target=blocked_reader)
    reader.start()
    time.sleep(0.1)
    a.shutdown()
    b.shutdown()
    b.shutdown()  # twice is harmless
    reader.join(TIMEOUT_S)
    assert len(waiting) == 1
    assert set(threading.enumerate()) == before


# -- the live stack over zenoh ----------------------------------------------------------------
class ZenohRig(Rig):
    """The in-process bench with the supervisor listening and each node host connecting over
    Zenoh; the fault injector sits on the node hosts' leg only."""

    def __init__(self, tmp: Path, nodes: range, node_faults: FaultProfile, seed: int) -> None:
        super().__init__(tmp, nodes, power_w=0.5, seed=seed, initial=50 * UJ_PER_J)
        self.port, self.site = free_port(), site()
        self.node_faults = node_faults
        self.supervisor_opened = False

    def _bus(self, filters: list[dict[str, int | bool]]) -> can.BusABC:
        if not self.supervisor_opened:  # start_supervisor opens the first bus
            self.supervisor_opened = True
            return zenoh_bus(self.site, filters, listen=endpoint(self.port))
        bus = zenoh_bus(self.site, filters, connect=endpoint(self.port))
        return FaultyBus(bus, FaultInjector(self.node_faults, random.Random(self.rng.random())))


def test_supervisor_and_nodes_over_zenoh_with_faults(tmp_path: Path) -> None:
    nodes = range(1, 4)
    faults = FaultProfile(loss=0.2, duplicate=0.1)
    rig = ZenohRig(tmp_path, nodes, faults, seed=5)
    try:
        rig.start_supervisor()
        rig.start_clients()
        rig.wait(lambda: all(rig.committed(n) >= 3 for n in nodes), timeout_s=120)
        rig.settle(timeout_s=120)
        books = rig.ledger()
        assert books.dissipated >= 0, books  # nothing generated
        assert books.spent > 0 and books.clients_usable > 0
        assert rig.service is not None and rig.service.intrusions.total == 0
    finally:
        rig.close()


def test_cli_supervisor_grants_to_a_node_over_zenoh(tmp_path: Path) -> None:
    port, name = free_port(), site()
    control, status = tmp_path / "ctl.sock", tmp_path / "status.json"
    argv = ["supervisor", "-i", "zenoh", "-c", name, "--bus-kwargs", f"listen={endpoint(port)}"]
    argv += ["--nodes", "2", "--initial", "10J", "--max-grant", "3J", "--no-fsync"]
    argv += ["--state", str(tmp_path / "s.json"), "--status-file", str(status)]
    argv += ["--control", str(control)]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)))
    thread.start()
    node = FirmwareNode(2, NvStore(tmp_path / "2.nv", 2, fsync=False), NodeConfig(), monotonic_us())
    host = NodeHost([node])
    codec = Codec()
    bus = zenoh_bus(name, codec.client_filters(2), connect=endpoint(port))
    loop = Loop(BusRuntime(bus, host, codec=codec, receives=Direction.TO_CLIENT))
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not control.exists():
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.02)
        while request(control, {"status": True}, TIMEOUT_S)["frames_received"] == 0:
            assert time.monotonic() < deadline, "no telemetry reached the supervisor"
            time.sleep(0.05)  # the node's telemetry arrived: the sessions are linked
        answer = request(control, {"grant": {"node": 2, "amount_uj": 2_500_000}}, TIMEOUT_S)
        assert answer["outcome"] == "COMMITTED", answer
        assert request(control, {"stop": True}, TIMEOUT_S) == {"stopping": True}
        thread.join(timeout=60)
    finally:
        loop.halt()
        if thread.is_alive():
            request(control, {"stop": True}, TIMEOUT_S)
            thread.join(timeout=60)
    assert result == [0]
    final = json.loads(status.read_text())
    assert final["usable_uj"] == 7_500_000 and final["conservation"]["holds"]
    assert host.nodes[2].client.state.usable == 2_500_000
