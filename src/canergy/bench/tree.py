"""Scale by composition: a root, gateways and their nodes in virtual time (``demo.tree``).

Each node draws power and is topped up by its gateway, each gateway by the root, through the
codec and a mildly lossy channel per bus. Measured per tree: transactions completed (all
levels), per second of virtual time and per CPU second of this process, CPU µs per transaction,
and memory per node. The CPU is the simulator's: every core (root, gateways, nodes), the
workload, the codec and the channels in one process. Memory per node: what ``tracemalloc`` sees
held by the large tree's run minus the small one's, over the nodes it adds (a shorter run). The
bus's bandwidth is not modelled: the virtual-time rate is the load the cores carried, not what
one CAN bus would carry.
"""

from __future__ import annotations

import tracemalloc
from typing import Any

from canergy.demo.tree import TreeConfig, TreeRun
from canergy.faults import FaultProfile
from canergy.units import US_PER_S

NODE_POWER_UW = (50_000, 150_000)


def config(gateways: int, nodes: int, seconds: float) -> TreeConfig:
    """Every node's budget flows for the whole run; no power losses (the demo and tests have)."""
    duration = int(seconds * US_PER_S)
    per_node = NODE_POWER_UW[1] * duration // US_PER_S
    return TreeConfig(
        gateways=gateways,
        nodes=nodes,
        initial=gateways * nodes * per_node * 2,
        duration_us=duration,
        faults=FaultProfile(loss=0.01, duplicate=0.01),
        gateway_resets=0,
        node_resets=0,
        root_resets=0,
        gateway_target=nodes * 600_000,
        gateway_return_above=nodes * 1_200_000,
        node_target=500_000,
        node_power_uw=NODE_POWER_UW,
        observe_every=0,
    )


def measure(gateways: int, nodes: int, seconds: float) -> dict[str, Any]:
    result = TreeRun(config(gateways, nodes, seconds)).run()
    tracemalloc.start()
    run = TreeRun(config(gateways, nodes, min(seconds, 1.0)))
    run.run()
    held = tracemalloc.get_traced_memory()[0]  # ``run`` and all it holds are still alive
    tracemalloc.stop()
    del run
    total = gateways * nodes
    virtual_s = result.virtual_us / US_PER_S
    return {
        "gateways": gateways,
        "nodes_per_gateway": nodes,
        "nodes": total,
        "passive": result.passive,
        "transactions": result.transactions,
        "virtual_s": round(virtual_s, 3),
        "tx_per_virtual_s": round(result.transactions / virtual_s) if virtual_s else None,
        "cpu_s": round(result.cpu_s, 3),
        "tx_per_cpu_s": round(result.transactions / result.cpu_s) if result.cpu_s else None,
        "cpu_us_per_tx": round(result.cpu_s * 1e6 / result.transactions, 1)
        if result.transactions
        else None,
        "cpu_ms_per_node_per_virtual_s": round(result.cpu_s * 1e3 / virtual_s / total, 3)
        if virtual_s
        else None,
        "frames_sent": result.frames_sent,
        "bytes_held": held,
    }


def scale(quick: bool = False) -> dict[str, Any]:
    """A small tree (the baseline) and 8 gateways x 127 nodes, measured in the same process."""
    seconds = 0.5 if quick else 5.0
    small = measure(1, 8, seconds)
    large = measure(2, 16, seconds) if quick else measure(8, 127, seconds)

    def ratio(key: str) -> float | None:
        a, b = large[key], small[key]
        return round(a / b, 2) if a and b else None

    added = large["nodes"] - small["nodes"]
    return {
        "baseline": small,
        "tree": large,
        "cpu_per_tx_ratio": ratio("cpu_us_per_tx"),
        "bytes_per_added_node": round((large["bytes_held"] - small["bytes_held"]) / added),
    }
