"""Real SocketCAN for the vcan suite (``pytest -m vcan``): the interface and the shared flags.

``vcan_up`` is an autouse module fixture: a test module that imports it fails (never skips) when
the interface is missing. ``client`` starts a node (``python -m firmware_model``, or the C node
through ``c_client``, made by ``support.firmware_build``'s ``c_node`` fixture) and
``supervisor`` a supervisor, both with the flags the vcan tests share, as processes of a
``support.procs.Procs``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from support.procs import Procs, python

ROOT = Path(__file__).resolve().parents[2]
IFACE = os.environ.get("CANERGY_VCAN", "vcan0")
BUS = ["-i", "socketcan", "-c", IFACE]
# syscalls inside user-mode Linux are slow: timeouts and waits are generous
TIMEOUT = ["--response-timeout", "0.3"]
BUDGET = "100J"
"""The supervisor's budget: three 0.2 W nodes spend 10 J in about 17 s, which a slow run (a
busy CI machine, user-mode Linux) could pass before its last step, and then nothing is granted."""
POWER_UW = 200_000
"""Each node's constant power, µW (``client``'s ``--power 0.2W``)."""
TARGET_UJ = 1_000_000
"""The level the supervisor tops each node up to, µJ (``supervisor``'s ``--target 1J``)."""


@pytest.fixture(scope="module", autouse=True)
def vcan_up() -> None:
    state = Path(f"/sys/class/net/{IFACE}/operstate")
    assert state.exists(), (
        f"{IFACE} missing: ip link add dev {IFACE} type vcan; ip link set up {IFACE}"
    )


def client(
    procs: Procs, node: int, *extra: str, program: list[str] | None = None
) -> subprocess.Popen[bytes]:
    """A node with the same flags, as ``python -m firmware_model`` or ``program`` (the C node)."""
    tmp = procs.tmp
    argv = [
        *(program or python("-m", "firmware_model")),
        "--node",
        str(node),
        *BUS,
        "--nv",
        str(tmp / f"n{node}.nv"),
        "--power",
        "0.2W",
        "--status-file",
        str(tmp / f"n{node}.json"),
        "--telemetry-period",
        "0.5",
        *TIMEOUT,
        *extra,
    ]
    return procs.start(f"client{node}", argv)


def keys(tmp: Path, node: int = 1) -> tuple[Path, Path]:
    """``canergy keys``: a master key and node ``node``'s key derived from it, in ``tmp``."""
    canergy = [sys.executable, "-m", "canergy", "keys"]
    master, node_key = tmp / "master.key", tmp / f"n{node}.key"
    subprocess.run([*canergy, "-o", str(master)], check=True, timeout=60, cwd=tmp)
    subprocess.run(
        [*canergy, "--master", str(master), "--nodes", str(node), "-o", str(node_key)],
        check=True,
        timeout=60,
    )
    return master, node_key


def supervisor(procs: Procs, nodes: str, *extra: str) -> subprocess.Popen[bytes]:
    tmp = procs.tmp
    argv = python(
        "-m",
        "canergy",
        "supervisor",
        *BUS,
        "--nodes",
        nodes,
        "--initial",
        BUDGET,
        "--target",
        "1J",
        "--max-grant",
        "0.5J",
        "--state",
        str(tmp / "state.json"),
        "--status-file",
        str(tmp / "sup.json"),
        *TIMEOUT,
        *extra,
    )
    return procs.start("supervisor", argv)


# The C node (firmware/ports/linux): the same process model, flags, NV file and status file as
# firmware_model --node, so the tests carry over with the binary (support.firmware_build's
# c_node fixture) in its place.
def c_client(procs: Procs, binary: Path, node: int, *extra: str) -> subprocess.Popen[bytes]:
    return client(procs, node, *extra, program=[str(binary)])
