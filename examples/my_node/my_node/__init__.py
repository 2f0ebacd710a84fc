"""Our node as its tests start it.

On python-can's virtual bus (which connects only the buses of one process) the node runs in the
test's process: ``InProcess`` puts a node host on the bus. Our stand-in host is canergy's emulator
of a client node (``firmware_model``, shipped in canergy's wheel). On SocketCAN the node is a
process of its own: the C node our firmware links (``c_node_argv``), or the emulator's command
line (``emulator_argv``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from canergy.testing.bus import TestBus
from canergy.testing.run import Loop
from firmware_model.__main__ import status
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

Host = NodeHost
"""The stand-in for our node's Python host."""

POWER_W = 0.2
"""What the actuator draws while it runs."""


class InProcess:
    """Nodes ``nodes`` served by ``host`` on ``bus`` in a thread of this process, their NV files
    in ``tmp``; ``status()`` is theirs as the emulator writes it, ``stop()`` ends them."""

    def __init__(
        self, bus: TestBus, nodes: list[int], tmp: Path, host: type[NodeHost] = Host
    ) -> None:
        config = NodeConfig(power=PowerProfile.constant(POWER_W))
        now = monotonic_us()
        self.host = host(
            [FirmwareNode(n, NvStore(tmp / f"n{n}.nv", n, fsync=False), config, now) for n in nodes]
        )
        self.runtime = BusRuntime(
            bus.open(), self.host, codec=Codec(), receives=Direction.TO_CLIENT
        )
        self._loop = Loop(self.runtime)  # in a thread of its own until stop()

    def status(self) -> dict[str, Any]:
        return status(self.host, self.runtime)

    def stop(self) -> None:
        self._loop.halt()


def _node_flags(node: int, timeout: str) -> list[str]:
    """The flags canergy_spawn fills in: the bus, NV file and status file of node ``node``."""
    return [
        *("--node", str(node), "-i", "{interface}", "-c", "{channel}"),
        *("--nv", f"{{tmp}}/n{node}.nv", "--status-file", "{status}"),
        *("--power", f"{POWER_W}W", "--response-timeout", timeout),
    ]


def c_node_argv(program: Path, node: int, timeout: str = "0.3") -> list[str]:
    """Our C node (``program``) as node ``node``."""
    return [str(program), *_node_flags(node, timeout)]


def emulator_argv(node: int, timeout: str = "0.3") -> list[str]:
    """The emulator as node ``node``, run by the test's Python."""
    return ["{python}", "-m", "firmware_model", *_node_flags(node, timeout)]
