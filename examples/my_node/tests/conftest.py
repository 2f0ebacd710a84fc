"""Our node under test, on whichever bus canergy's plugin gives the test (``canergy_bus``).

- python-can's virtual bus (the default): nodes 1 and 2 served in this process by our Python
  host (``--node-host``, default ``my_node:Host``).
- SocketCAN (``--canergy-interface socketcan --canergy-channel vcan0``): the supervisor on vcan0,
  our nodes on ``--below`` (default vcan1) as processes: node 1 our C node (``--c-node``), node 2
  the emulator.

Either way a bridge of the test's puts its faults between the supervisor's bus and the nodes'.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from pathlib import Path

import my_node
import pytest

NODES = [1, 2]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--c-node", type=Path, help="our C node's program (SocketCAN runs)")
    parser.addoption(
        "--node-host",
        default="my_node:Host",
        help="MODULE:CLASS, the Python host of our node on the virtual bus",
    )
    parser.addoption("--below", default="vcan1", help="the nodes' SocketCAN bus (not virtual)")


@pytest.fixture(scope="session")
def node_host(pytestconfig):
    """The class of our node's Python host (``--node-host``)."""
    module, _, name = pytestconfig.getoption("--node-host").partition(":")
    return getattr(importlib.import_module(module), name)


@pytest.fixture
def timeout(canergy_bus):
    """The response timeout of the supervisor and the nodes: processes on SocketCAN (in
    user-mode Linux too) are held off longer than threads of one process."""
    return "50ms" if canergy_bus.interface == "virtual" else "0.3"


@pytest.fixture
def nodes(
    request, canergy_bus, canergy_books, canergy_spawn, tmp_path, timeout, node_host
) -> Iterator:
    """The nodes' bus, with nodes 1 and 2 running on it and their statuses in the books."""
    if canergy_bus.interface == "virtual":
        below = canergy_bus.sibling()
        running = my_node.InProcess(below, NODES, tmp_path, node_host)
        canergy_books.add_client(running.status, stop=running.stop)
        yield below
        running.stop()
        return
    program = request.config.getoption("--c-node")
    if program is None:
        raise pytest.UsageError("give --c-node=PATH: our C node's program")
    below = canergy_bus.sibling(request.config.getoption("--below"))
    canergy_spawn(my_node.c_node_argv(program.resolve(), 1, timeout), "node1", bus=below)
    canergy_spawn(my_node.emulator_argv(2, timeout), "node2", bus=below)
    yield below
