"""A supervisor (``canergy supervisor`` in a thread: the pytest plugin's ``SupervisorRun``) and a
node on python-can's virtual bus, with a rogue bus object beside them that sends frames in
either side's name.

``bench`` yields a ``Bench`` once the supervisor answers on its control socket, and stops
everything after; ``Bench.forge`` sends a frame as a rogue would, ``Bench.status`` is the
supervisor's status (its last, once it ended). Extra arguments go to the supervisor
(``--on-intrusion``, ``--return-hold``, ...).
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from canergy.testing.bus import TestBus
from canergy.testing.run import Loop, until
from canergy.testing.supervisor import SupervisorRun
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

CODEC = Codec()


@dataclass
class Bench:
    tmp: Path
    rogue: can.BusABC
    host: NodeHost
    sup: SupervisorRun

    def status(self) -> dict[str, Any]:
        return self.sup.status()

    def forge(self, msg: Any) -> int:
        """Send ``msg`` as a rogue would; when it left (monotonic µs)."""
        arbitration_id, data = CODEC.encode(msg)
        sent = monotonic_us()
        self.rogue.send(can.Message(arbitration_id=arbitration_id, data=data))
        return sent

    def wait(self, condition: Any, timeout: float = 30) -> None:
        until(condition, timeout_s=timeout)


def bench(tmp: Path, *extra: str) -> Iterator[Bench]:
    bus = TestBus("virtual", f"intrusion-{uuid.uuid4().hex}")
    now = monotonic_us()
    node = FirmwareNode(1, NvStore(tmp / "1.nv", 1, fsync=False), NodeConfig(), now)
    host = NodeHost([node])
    node_bus = bus.open(can_filters=CODEC.client_watch_filters(1))
    loop = Loop(BusRuntime(node_bus, host, codec=CODEC, receives=Direction.TO_CLIENT))
    rogue = bus.open()
    try:
        flags = ["--nodes", "1", "--initial", "10J", "--status-period", "50ms", *extra]
        sup = SupervisorRun(bus, tmp, flags)
        try:
            yield Bench(tmp, rogue, host, sup)
        finally:
            sup.stop()
    finally:
        loop.halt()
        rogue.shutdown()
