"""The emulator as canergy's benchmark sees it (entry point ``canergy.emulators``)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from canergy.core import Timing
from canergy.live.runtime import Handler
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import RECORD_SIZE, SLOT_SIZE, NvStore


class BenchNodes:
    """Firmware nodes with NV files (no fsync), one host behind one bus handler."""

    nv_record_bytes = RECORD_SIZE
    nv_file_bytes = 2 * SLOT_SIZE
    label = "python -m firmware_model"

    def node_host(self, nodes: Sequence[int], nv_dir: Path, timing: Timing, now: int) -> Handler:
        return NodeHost(
            [
                FirmwareNode(
                    n, NvStore(nv_dir / f"{n}.nv", n, fsync=False), NodeConfig(timing=timing), now
                )
                for n in nodes
            ]
        )

    def command(self, nodes: str, nv_dir: Path, bus_flags: Sequence[str]) -> list[str]:
        program = [sys.executable, "-m", "firmware_model"]
        return [*program, "--nodes", nodes, "--nv", str(nv_dir), "--no-fsync", *bus_flags]


EMULATOR = BenchNodes()
