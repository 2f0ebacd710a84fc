"""A supervisor (``canergy supervisor``, in a thread) and a node on python-can's virtual bus,
with a rogue bus object beside them that sends frames in either side's name.

``bench`` yields a ``Bench`` once the supervisor reports its node, and stops everything after;
``Bench.forge`` sends a frame as a rogue would, ``Bench.status`` reads the supervisor's status
file. Extra arguments go to the supervisor (``--on-intrusion``, ``--return-hold``, ...).
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

from canergy.cli import main
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import Direction
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore
from support.live_rig import Loop

CODEC = Codec()


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
