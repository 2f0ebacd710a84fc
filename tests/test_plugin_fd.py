"""CAN FD end to end through the pytest plugin, on python-can's virtual bus: the test's bus opened
for FD (``@pytest.mark.canergy(fd=True)``), a supervisor started on it with ``--fd`` in
authenticated mode (each message and its 64-bit MAC in one FD frame), the bridge carrying FD
frames both ways to a node of the test's process that speaks FD, and the books closed at
teardown."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import can
import pytest

from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import load_key
from canergy.bridge.link import Bridge
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from canergy.testing.bus import TestBus
from canergy.testing.plugin import Books
from canergy.testing.run import Loop
from canergy.testing.supervisor import SupervisorRun
from firmware_model.__main__ import bind_starts, status
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

FLAGS = ["--nodes", "1", "--initial", "10J", "--target", "1J", "--max-grant", "0.4J"]
FLAGS += ["--response-timeout", "100ms"]


def _fd_node(books: Books, bus: TestBus, key: Path, tmp: Path) -> None:
    """Node 1, the emulator in this process, on ``bus`` with its key, in the FD layout; its
    status in the books, stopped at teardown."""
    host = NodeHost(
        [FirmwareNode(1, NvStore(tmp / "1.nv", 1, fsync=False), NodeConfig(), monotonic_us())]
    )
    codec = Codec()
    node_key = load_key(key).node_key(1)
    keys = {1: node_key}.__getitem__
    auth = FrameAuth(codec, Layout.FD, keys, Direction.TO_CLIENT, host.freshness)
    bind_starts(auth, host)
    runtime = BusRuntime(bus.open(), host, codec=codec, receives=Direction.TO_CLIENT, auth=auth)
    loop = Loop(runtime)
    books.add_client(lambda: status(host, runtime), stop=loop.halt)


@pytest.mark.canergy(fd=True)
def test_an_fd_node_is_granted_through_the_bridge_and_the_books_close(
    canergy_bus: TestBus,
    canergy_books: Books,
    canergy_supervisor: Callable[..., SupervisorRun],
    canergy_bridge: Callable[..., Bridge],
    tmp_path: Path,
) -> None:
    below = canergy_bus.sibling()
    assert below.fd and "--fd" in canergy_bus.flags
    up_frames: list[can.Message] = []
    down_frames: list[can.Message] = []
    seen = {"supervisor's bus": up_frames, "node's bus": down_frames}
    with canergy_bus.open() as up, below.open() as down:  # each side of the bridge
        notifiers = [can.Notifier(up, [up_frames.append]), can.Notifier(down, [down_frames.append])]
        bridge = canergy_bridge(canergy_bus, below, loss=0.05, duplicate=0.05, seed=6)
        sup = canergy_supervisor(*FLAGS, auth=True)
        _fd_node(canergy_books, below, sup.node_key(1), tmp_path)
        final = sup.wait_for(lambda s: s["nodes"]["1"]["committed"] >= 3, "three grants in FD")
        for notifier in notifiers:
            notifier.stop()
    assert final.get("auth_failures", {}) == {}  # one frame each: nothing parted by a loss
    for where, got in seen.items():
        frames = [f for f in got if f.is_extended_id]  # canergy's, both ways
        assert frames and all(f.is_fd and f.bitrate_switch for f in frames), where
        assert max(len(f.data) for f in frames) > 8, where  # message + MAC: beyond classic CAN
    directions = bridge.status()["directions"].values()
    assert all(c["forwarded"] > 0 for c in directions)
