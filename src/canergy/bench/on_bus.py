"""``canergy bench`` on a bus the user names: their interface, their host, their figures.

The supervisor runs in this process on the bus the flags open (as ``canergy supervisor`` would);
the nodes run in another process: the command of the client emulator registered under
``canergy.emulators`` or, on SocketCAN, the C node (``--c-node PATH``: one process per node). Then
python-canopen's SDO client in this process writes to an SDO server in a process of its own
(``python -m canergy.bench.sdo_server``), on the same interface. Reported: throughput, latency
p50/p99, the CPU of the supervisor's loop thread per frame on the bus, the nodes' processes'
CPU, and the latency ratio against the SDO write.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import can
import canopen

from canergy.bench import code, live
from canergy.codec import Codec

SDO_NODE = 5
"""The SDO server's node id (its frames are 11-bit, outside canergy's 29-bit block)."""


@dataclass(frozen=True)
class BusTarget:
    """The bus the user named (from ``canergy bench``'s flags): how other programs are told to
    open it, and how this process opens it."""

    flags: tuple[str, ...]
    """The bus flags for another program taking python-can's flags (without ``--id-base``)."""
    interface: str | None
    channel: str | None
    id_base: int
    open: Callable[[list[dict[str, Any]]], can.BusABC]
    """Open it here with these acceptance filters."""

    def argv(self) -> list[str]:
        """The flags with ``--id-base``."""
        return [*self.flags, "--id-base", f"0x{self.id_base:08X}"]


def _wait_ready(proc: subprocess.Popen[str], what: str, timeout_s: float) -> None:
    """Wait for the line ``ready`` on ``proc``'s stdout; a clear error if it exits first."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        readable, _, _ = select.select([proc.stdout], [], [], 0.2)
        if readable and proc.stdout.readline().strip() == "ready":
            return
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr is not None else ""
            raise RuntimeError(f"{what} exited with status {proc.returncode}: {err.strip()}")
    raise RuntimeError(f"{what} not ready after {timeout_s:g} s")


def _stop(procs: Sequence[subprocess.Popen[Any]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process (Linux ``/proc``; None elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def node_commands(bus: BusTarget, nodes: int, nv_dir: Path, c_node: Path | None) -> list[list[str]]:
    """The processes that put ``nodes`` nodes (ids 1..nodes) on the bus."""
    if c_node is None:
        return [live.load_emulator().command(f"1-{nodes}", nv_dir, bus.argv())]
    if bus.interface != "socketcan":
        raise ValueError("--c-node: the C node runs on SocketCAN only (-i socketcan)")
    base = [str(c_node), "-i", "socketcan", "-c", str(bus.channel)]
    base += ["--id-base", f"0x{bus.id_base:08X}"]
    return [[*base, "--node", str(n), "--nv", str(nv_dir / f"{n}.nv")] for n in range(1, nodes + 1)]


@contextmanager
def _processes(commands: list[list[str]], logs: Path) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``commands`` running, their stderr in files under ``logs``; stopped on the way out."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for i, cmd in enumerate(commands):
            with (logs / f"{i}.err").open("w") as err:
                procs.append(
                    subprocess.Popen(
                        cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err
                    )
                )
        yield procs
    finally:
        _stop(procs)


def grants_on_bus(
    bus_target: BusTarget,
    nodes: int,
    duration_s: float,
    c_node: Path | None,
    state_file: bool = False,
    core: str = "python",
) -> dict[str, Any]:
    """``live.drive_grants`` on the flags' bus against node processes; ``state_file``: the
    supervisor keeps its books in a file; ``core``: its core ("python", "c")."""
    codec = Codec(bus_target.id_base)
    with tempfile.TemporaryDirectory() as tmp:
        logs = Path(tmp)
        with _processes(node_commands(bus_target, nodes, logs, c_node), logs) as procs:
            bus = bus_target.open(codec.supervisor_filters())
            clocks = [partial(_process_cpu_s, p.pid) for p in procs]
            try:
                row = live.drive_grants(
                    bus,
                    range(1, nodes + 1),
                    duration_s,
                    warm_up_s=30.0,
                    node_clocks=clocks,
                    state_path=logs / "supervisor.json" if state_file else None,
                    core=core,
                    codec=codec,
                )
            except live.NoAnswer as exc:
                dead = [i for i, p in enumerate(procs) if p.poll() is not None]
                if dead:
                    why = (logs / f"{dead[0]}.err").read_text().strip()
                    raise RuntimeError(f"{exc}; a node process exited: {why}") from exc
                raise
            finally:
                bus.shutdown()
    row["node_processes"] = len(procs)
    return row


def sdo_on_bus(bus: BusTarget, count: int) -> dict[str, Any]:
    """SDO expedited writes from this process to an SDO server process on the same bus."""
    cmd = [sys.executable, "-m", "canergy.bench.sdo_server", *bus.flags]
    server = subprocess.Popen(
        [*cmd, "--node", str(SDO_NODE)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_ready(server, "the SDO server process", 30.0)
        answers = [{"can_id": 0x580 + SDO_NODE, "can_mask": 0x7FF, "extended": False}]
        network = canopen.Network(bus.open(answers))
        network.connect()
        try:
            od = live.sdo_dictionary()
            return live.sdo_latencies(network.add_node(canopen.RemoteNode(SDO_NODE, od)), count)
        finally:
            network.disconnect()
    finally:
        _stop([server])


def run_on_bus(
    bus: BusTarget,
    node_counts: Sequence[int],
    seconds: float,
    writes: int,
    c_node: Path | None,
    cores: Sequence[str] = ("python",),
) -> dict[str, Any]:
    """Every row of ``node_counts`` for each of ``cores`` in turn (the supervisor's core; the
    first one's figures at the top, the C core's under ``c_core`` with its ratios to the Python
    core's under ``c_vs_python``), then the SDO baseline, on the flags' bus."""
    from canergy.bench.run import (
        LATENCY_RATIO_TARGET,
        compare_cores,
        latency_ratio,
        supervisor_headroom,
    )

    stacks: dict[str, dict[str, Any]] = {}
    for core in cores:
        rows = [
            grants_on_bus(bus, n, seconds, c_node, state_file, core)
            for state_file in (False, True)
            for n in node_counts
        ]
        stacks[core] = {"live": rows, "headroom": supervisor_headroom(rows)}
    sdo = sdo_on_bus(bus, writes)
    for stack in stacks.values():
        stack["latency_ratio_vs_sdo"] = latency_ratio(stack["live"], sdo)
    first = stacks[cores[0]]
    return {
        "bus": bus.argv(),
        "code": code.code(),
        "nodes_by": "C node processes" if c_node else live.load_emulator().label,
        **first,
        "sdo": sdo,
        "latency_ratio_target": LATENCY_RATIO_TARGET,
        "c_core": stacks["c"] if "c" in stacks and cores[0] != "c" else None,
        "c_vs_python": compare_cores(stacks),
    }
