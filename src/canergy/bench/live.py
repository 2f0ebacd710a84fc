"""The live stack on python-can's virtual bus, and python-canopen SDO writes on the same bus kind.

canergy: a supervisor service and a firmware node host, each with its own bus end and loop thread
(as two processes would be), one-shot grants kept in flight for every node; per-transaction
latency from request to resolution. Baseline: a ``canopen.LocalNode`` serving expedited SDO
downloads of 4 bytes to a ``RemoteNode`` client, one at a time, in the same process.

The nodes come from a client emulator registered under the ``canergy.emulators`` entry-point
group (the way python-can finds its interfaces): canergy names none and depends on none, and a
host-only install without one skips this part (see ``load_emulator``).
"""

from __future__ import annotations

import statistics
import threading
import time
import uuid
from collections.abc import Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Protocol

import can
import canopen

from canergy.codec import Codec
from canergy.core import Supervisor, Timing
from canergy.live.runtime import BusRuntime, Handler, monotonic_us
from canergy.live.service import ServiceConfig, SupervisorService
from canergy.messages import Direction

TIMING = Timing(response_timeout_us=500_000, retries=3, command_timeout_us=1_000_000)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


EMULATORS = "canergy.emulators"


class Emulator(Protocol):
    """What a client emulator offers the benchmark: a host of nodes and its NV record size."""

    nv_record_bytes: int
    nv_file_bytes: int

    def node_host(self, nodes: Sequence[int], nv_dir: Path, timing: Timing, now: int) -> Handler:
        """Nodes with NV files under ``nv_dir``, behind one bus handler."""
        ...

    def telemetry_sent(self, host: Handler) -> int:
        """TELEMETRY frames the host's nodes sent (information, not protocol frames)."""
        ...


class EmulatorMissing(Exception):
    """No registered client emulator loads here; the message says why."""


def load_emulator() -> Emulator:
    """The first client emulator of the ``canergy.emulators`` group that loads."""
    reasons = []
    for point in entry_points(group=EMULATORS):
        try:
            emulator: Emulator = point.load()
        except ImportError as exc:
            reasons.append(f"{point.value}: {exc}")
            continue
        return emulator
    why = "; ".join(reasons) or f"none registered under the {EMULATORS} entry points"
    raise EmulatorMissing(
        f"skipped the live stack and the client NV figures: they need a client emulator ({why})"
    )


def canergy_grants(
    emulator: Emulator, nodes: int, duration_s: float, nv_dir: Path
) -> dict[str, Any]:
    channel = f"bench-{uuid.uuid4().hex}"
    codec = Codec()
    ids = list(range(1, nodes + 1))
    now = monotonic_us()
    core = Supervisor(ids, 10**15, timing=TIMING)
    service = SupervisorService(core, ServiceConfig(status_period_us=10**12, fsync=False), now)
    host = emulator.node_host(ids, nv_dir, TIMING, now)
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
    telemetry = emulator.telemetry_sent(host)  # not protocol frames
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
