"""Detection without a key: a second supervisor and a spoofer are reported within a second.

A side never receives its own frames back (SocketCAN and python-can's virtual bus alike), so a
frame in its own direction for a node it handles was sent by someone else.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.cli import main
from canergy.codec import Codec
from canergy.live.control import request
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Ack, Direction, Intention
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

CODEC = Codec()


def test_watch_filters_pass_the_own_direction_too() -> None:
    intention, _ = CODEC.encode(Intention(5, 1, 1, 0))
    ack, _ = CODEC.encode(Ack(5, 1))
    other_ack, _ = CODEC.encode(Ack(6, 1))
    assert not CODEC.accepts(CODEC.supervisor_filters(), intention, True)
    assert CODEC.accepts(CODEC.supervisor_watch_filters(), intention, True)
    assert not CODEC.accepts(CODEC.client_filters(5), ack, True)
    assert CODEC.accepts(CODEC.client_watch_filters(5), ack, True)
    assert not CODEC.accepts(CODEC.client_watch_filters(5), other_ack, True)


@dataclass
class Bench:
    tmp: Path
    rogue: can.BusABC
    host: NodeHost
    result: list[int]
    thread: threading.Thread

    def status(self) -> dict[str, Any]:
        try:
            return dict(json.loads((self.tmp / "status.json").read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def forge(self, msg: Any) -> int:
        """Send ``msg`` as a rogue would; when it left (monotonic µs)."""
        arbitration_id, data = CODEC.encode(msg)
        sent = monotonic_us()
        self.rogue.send(can.Message(arbitration_id=arbitration_id, data=data))
        return sent

    def wait(self, condition: Any, timeout: float = 30) -> None:
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, "timed out"
            time.sleep(0.02)


def bench(tmp: Path, *extra: str) -> Iterator[Bench]:
    channel = f"intrusion-{uuid.uuid4().hex}"
    now = monotonic_us()
    node = FirmwareNode(1, NvStore(tmp / "1.nv", 1, fsync=False), NodeConfig(), now)
    host = NodeHost([node])
    node_bus = can.Bus(
        interface="virtual", channel=channel, can_filters=CODEC.client_watch_filters(1)
    )
    loop = Loop(BusRuntime(node_bus, host, codec=CODEC, receives=Direction.TO_CLIENT))
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, "--nodes", "1", "--initial", "10J"),
        *("--state", str(tmp / "s.json"), "--no-fsync"),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(tmp / "ctl.sock"), *extra),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    rogue = can.Bus(interface="virtual", channel=channel)
    b = Bench(tmp, rogue, host, result, thread)
    try:
        b.wait(lambda: b.status().get("nodes"))
        yield b
    finally:
        if thread.is_alive():
            request(tmp / "ctl.sock", {"stop": True}, 30)
        thread.join(timeout=60)
        loop.halt()
        rogue.shutdown()


@pytest.fixture
def warned(tmp_path: Path) -> Iterator[Bench]:
    yield from bench(tmp_path)


def test_a_second_supervisor_is_reported_within_a_second(warned: Bench) -> None:
    b = warned
    sent = b.forge(Intention(1, 500, 100, 0))
    b.wait(lambda: b.status().get("intrusions", 0) >= 1)
    report = b.status()["intrusion_report"]
    assert report["first_at_us"] - sent < 1_000_000
    (event,) = report["recent"]
    assert event["node"] == 1 and event["frame"].startswith("0CE00101#")
    assert b.status()["nodes"]["1"]["intrusions"] == 1
    assert not b.status()["stopping"]  # warn: counted and reported, nothing else
    b.forge(Intention(7, 1, 100, 0))  # a node this supervisor does not manage: not its business
    time.sleep(0.3)
    assert b.status()["intrusions"] == 1


def test_a_frame_in_a_nodes_name_is_reported_by_the_node(warned: Bench) -> None:
    b = warned
    node = b.host.nodes[1]
    sent = b.forge(Ack(1, 321))
    b.wait(lambda: node.intrusions.total >= 1)
    assert node.intrusions.first_at is not None and node.intrusions.first_at - sent < 1_000_000
    assert node.status()["intrusions"] == 1
    assert node.status()["intrusion_report"]["recent"][0]["frame"].startswith("0CE00901#")


def test_stop_on_intrusion_ends_the_supervisor_with_status_3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for b in bench(tmp_path, "--on-intrusion", "stop"):
        b.forge(Intention(1, 500, 100, 0))
        b.thread.join(timeout=60)
        assert b.result == [3]
        final = b.status()
        assert final["stopped_by_intrusion"] and final["intrusions"] >= 1
    assert "stopped on intrusion" in capsys.readouterr().err
