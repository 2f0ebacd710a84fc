"""The live stack on python-can's virtual bus, and python-canopen SDO writes on the same bus kind.

canergy: a supervisor service and a firmware node host, each with its own bus end and loop thread
(as two processes would be), one-shot grants kept in flight for every node; per-transaction
latency from request to resolution. Baseline: a ``canopen.LocalNode`` serving expedited SDO
downloads of 4 bytes to a ``RemoteNode`` client, one at a time, in the same process.

The nodes are ``firmware_model``'s, imported only when measured: canergy never depends on the
emulator, which a host-only install lacks (see ``emulator_missing``).
"""

from __future__ import annotations

import statistics
import threading
import time
import uuid
from typing import Any

import can
import canopen

from canergy.codec import Codec
from canergy.core import Supervisor, Timing
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.service import ServiceConfig, SupervisorService
from canergy.messages import Direction

TIMING = Timing(response_timeout_us=500_000, retries=3, command_timeout_us=1_000_000)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def emulator_missing() -> str | None:
    """Why the emulated nodes cannot run here, or None when ``firmware_model`` imports."""
    try:
        import firmware_model  # noqa: F401
    except ImportError:
        return (
            "skipped the live stack and the client NV figures: they run the firmware_model "
            "emulator (canergy's source tree has it), which is not importable here"
        )
    return None


def canergy_grants(nodes: int, duration_s: float, nv_dir: Any) -> dict[str, Any]:
    from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
    from firmware_model.nvstore import NvStore

    channel = f"bench-{uuid.uuid4().hex}"
    codec = Codec()
    ids = list(range(1, nodes + 1))
    now = monotonic_us()
    core = Supervisor(ids, 10**15, timing=TIMING)
    service = SupervisorService(core, ServiceConfig(status_period_us=10**12, fsync=False), now)
    host = NodeHost(
        [
            FirmwareNode(
                n, NvStore(nv_dir / f"{n}.nv", n, fsync=False), NodeConfig(timing=TIMING), now
            )
            for n in ids
        ]
    )
    sup_bus = can.Bus(interface="virtual", channel=channel, can_filters=codec.supervisor_filters())
    node_bus = can.Bus(interface="virtual", channel=channel)
    runtimes = [
        BusRuntime(sup_bus, service, codec=codec, receives=Direction.TO_SUPERVISOR),
        BusRuntime(node_bus, host, codec=codec, receives=Direction.TO_CLIENT),
    ]
    stop = threading.Event()
    threads = [
        threading.Thread(target=r.run, args=(stop.is_set, 0.01), daemon=True) for r in runtimes
    ]
    latencies: list[float] = []

    def ask(node: int) -> None:
        started = time.perf_counter()

        def reply(result: dict[str, Any]) -> None:  # runs in the service's thread
            if result.get("outcome") == "COMMITTED":
                latencies.append(time.perf_counter() - started)
            if not stop.is_set():
                ask(node)  # keep one grant in flight per node

        service.request_grant(node, 1_000, reply)

    for n in ids:  # queued before the loops start
        ask(n)
    start, cpu_start = time.perf_counter(), time.process_time()
    for t in threads:
        t.start()
    time.sleep(duration_s)
    stop.set()
    for t in threads:
        t.join(timeout=10)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    frames = sum(r.counters.frames_sent for r in runtimes)
    telemetry = sum(n.telemetry_sent for n in host.nodes.values())  # not protocol frames
    for r in runtimes:
        r.bus.shutdown()
    done = len(latencies)
    return {
        "nodes": nodes,
        "transactions": done,
        "tx_per_s": done / elapsed,
        "latency_p50_ms": 1e3 * _percentile(latencies, 0.5) if done else None,
        "latency_p99_ms": 1e3 * _percentile(latencies, 0.99) if done else None,
        "frames_per_tx": (frames - telemetry) / done if done else None,
        "telemetry_per_tx": telemetry / done if done else None,
        "cpu_us_per_frame": 1e6 * cpu / frames if frames else None,
    }


def sdo_writes(count: int) -> dict[str, Any]:
    channel = f"sdo-{uuid.uuid4().hex}"
    od = canopen.ObjectDictionary()
    var = canopen.objectdictionary.ODVariable("Value", 0x2000, 0)
    var.data_type = canopen.objectdictionary.UNSIGNED32
    var.access_type = "rw"
    od.add_object(var)
    server_net, client_net = canopen.Network(), canopen.Network()
    server_net.connect(interface="virtual", channel=channel)
    client_net.connect(interface="virtual", channel=channel)
    try:
        server_net.add_node(canopen.LocalNode(5, od))
        remote = client_net.add_node(canopen.RemoteNode(5, od))
        remote.sdo.RESPONSE_TIMEOUT = 5.0
        latencies = []
        start = time.perf_counter()
        for i in range(count):
            t = time.perf_counter()
            remote.sdo.download(0x2000, 0, i.to_bytes(4, "little"))
            latencies.append(time.perf_counter() - t)
        elapsed = time.perf_counter() - start
    finally:
        server_net.disconnect()
        client_net.disconnect()
    return {
        "writes": count,
        "writes_per_s": count / elapsed,
        "latency_p50_ms": 1e3 * statistics.median(latencies),
        "latency_p99_ms": 1e3 * _percentile(latencies, 0.99),
        "frames_per_write": 2,
    }
