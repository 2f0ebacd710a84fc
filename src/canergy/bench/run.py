"""``canergy bench``: every comparison in one run, a table on stdout and JSON for the record.

The parts that run emulated client nodes are skipped, and named under ``skipped``, where no
client emulator is registered and importable (a host-only install; see ``live.load_emulator``)."""

from __future__ import annotations

import platform
import tempfile
import tracemalloc
from pathlib import Path
from typing import Any

from canergy.bench import auth, codec, core, live, tree, wire


def memory_per_node(nodes: int = 127, emulator: live.Emulator | None = None) -> dict[str, Any]:
    from canergy.core import Supervisor
    from canergy.live.service import ServiceConfig, SupervisorService

    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    service = SupervisorService(Supervisor(range(1, nodes + 1), 10**9), ServiceConfig(), 0)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    used = sum(s.size_diff for s in after.compare_to(before, "filename"))
    assert service.core.nodes  # keep it alive until measured
    result: dict[str, Any] = {"nodes": nodes, "supervisor_bytes_per_node": used / nodes}
    if emulator is not None:
        result |= {
            "client_nv_record_bytes": emulator.nv_record_bytes,
            "client_nv_file_bytes": emulator.nv_file_bytes,
        }
    return result


def run(quick: bool = False) -> dict[str, Any]:
    seconds = 0.3 if quick else 3.0
    emulator: live.Emulator | None = None
    skipped: list[str] = []
    try:
        emulator = live.load_emulator()
    except live.EmulatorMissing as exc:
        skipped.append(str(exc))
    live_rows = []
    if emulator is not None:
        with tempfile.TemporaryDirectory() as tmp:
            nv = Path(tmp)
            live_rows = [live.canergy_grants(emulator, n, seconds, nv) for n in (1, 16, 127)]
    sdo = live.sdo_writes(50 if quick else 2000)
    one = live_rows[0] if live_rows else {"latency_p50_ms": None, "cpu_us_per_frame": None}
    return {
        "machine": f"{platform.node()} {platform.machine()} {platform.python_implementation()} "
        f"{platform.python_version()}, {__import__('os').cpu_count()} cores",
        "quick": quick,
        "codec": codec.compare(loops=100 if quick else 2000, repeats=3 if quick else 9),
        "core": [
            core.transactions_per_second(n, loss, 0.2 if quick else 3.0)
            for n in (1, 127)
            for loss in (0.0, 0.3)
        ],
        "live": live_rows,
        "sdo": sdo,
        "latency_ratio_vs_sdo": (
            one["latency_p50_ms"] / sdo["latency_p50_ms"] if one["latency_p50_ms"] else None
        ),
        "wire": wire.model(),
        "headroom": wire.headroom(one["cpu_us_per_frame"]) if one["cpu_us_per_frame"] else None,
        "memory": memory_per_node(emulator=emulator),
        "auth": auth.overhead(loops=20 if quick else 500, repeats=3 if quick else 7),
        "tree": tree.scale(quick),
        "skipped": skipped,
    }


def _n(value: float | None, spec: str) -> str:
    """A figure, or n/a when the run measured nothing (a quick run on a busy machine)."""
    return "n/a" if value is None else format(value, spec)


def table(r: dict[str, Any]) -> str:
    c = r["codec"]
    lines = [
        f"machine: {r['machine']}"
        + ("  (quick smoke run: figures meaningless)" if r["quick"] else ""),
        "",
        "codec, encode+decode per frame (median per type)       target  measured",
        f"  canergy {c['canergy_us_per_frame']:.2f} us; speed-up vs cantools (median/min)"
        f"   >= 30x  {c['median_speedup']:.1f}x / {c['min_speedup']:.1f}x",
        "",
        "core, transactions/s in memory (no bus)",
    ]
    for row in r["core"]:
        target = ">= 50,000" if row["nodes"] == 1 and row["loss"] == 0 else ""
        lines.append(
            f"  {row['nodes']:>3} nodes, loss {row['loss']:.0%}: {row['tx_per_s']:>9,.0f} tx/s "
            f"({row['frames_per_tx']:.2f} frames/tx) {target}"
        )
    lines += ["", "live stack on python-can virtual (supervisor + emulator threads)"]
    lines += [f"  {reason}" for reason in r["skipped"]]
    for row in r["live"]:
        lines.append(
            f"  {row['nodes']:>3} nodes: {row['tx_per_s']:>7,.0f} tx/s, latency p50 "
            f"{_n(row['latency_p50_ms'], '.2f')} ms p99 {_n(row['latency_p99_ms'], '.2f')} ms, "
            f"{_n(row['frames_per_tx'], '.2f')} protocol frames/tx "
            f"(+{_n(row['telemetry_per_tx'], '.2f')} telemetry)"
        )
    s = r["sdo"]
    lines += [
        f"  python-canopen SDO expedited 4-byte write: {s['writes_per_s']:,.0f}/s, p50 "
        f"{s['latency_p50_ms']:.3f} ms p99 {s['latency_p99_ms']:.3f} ms",
        f"  transaction latency / SDO write latency (1 node, p50): target <= 2: "
        f"{_n(r['latency_ratio_vs_sdo'], '.2f')}",
        "",
        "wire model, nominal transaction (frames of "
        + "+".join(map(str, r["wire"]["frame_bytes"]))
        + " bytes)",
    ]
    for row in r["wire"]["rows"]:
        rates = ", ".join(f"{int(b) // 1000}k: {v}" for b, v in row["max_tx_per_s"].items())
        lines.append(
            f"  {row['ids']} {row['stuffing']:>5} stuffing: {row['bits_per_tx']} bits/tx; "
            f"max tx/s {rates}"
        )
    h = r["headroom"] or {
        "cpu_us_per_frame": None,
        "wire_us_per_frame_1mbit": None,
        "headroom": None,
    }
    m = r["memory"]
    nv = (
        f"; client NV record {m['client_nv_record_bytes']} bytes "
        f"({m['client_nv_file_bytes']} with A/B slots)"
        if "client_nv_record_bytes" in m
        else ""
    )
    lines += ["", "authenticated mode, per message (MAC built and checked) and per transaction"]
    for row in r["auth"]["rows"]:
        ratio = f" ({row['vs_plain']:.1f}x plain)" if "vs_plain" in row else ""
        lines.append(
            f"  {row['layout']:>7}: {row['us_per_frame']:.1f} us/message{ratio}, "
            f"{row['frames_per_tx']} frames and {row['bytes_per_tx']} data bytes per transaction"
        )
    lines += [
        f"  CPU per frame {_n(h['cpu_us_per_frame'], '.1f')} us vs wire "
        f"{_n(h['wire_us_per_frame_1mbit'], '.0f')} us at 1 Mbit/s: headroom "
        f"{_n(h['headroom'], '.2f')} "
        "(target >= 1)",
        "",
        f"memory: supervisor {m['supervisor_bytes_per_node']:.0f} bytes/node at {m['nodes']} "
        f"nodes{nv}",
        "",
        "scale by composition, virtual time (root -> gateways -> nodes, 1% loss and duplicates)",
    ]
    t = r["tree"]
    for row in (t["baseline"], t["tree"]):
        lines.append(
            f"  {row['gateways']} x {row['nodes_per_gateway']:>3} = {row['nodes']:>4} nodes: "
            f"{row['transactions']:>7,} tx in {row['virtual_s']:.1f} s virtual "
            f"({_n(row['tx_per_virtual_s'], ',')} tx/s), {_n(row['cpu_us_per_tx'], '.0f')} us "
            f"CPU/tx, {_n(row['cpu_ms_per_node_per_virtual_s'], '.2f')} ms CPU per node per "
            f"second, {'passive' if row['passive'] else 'NOT PASSIVE'}"
        )
    lines.append(
        f"  CPU per transaction vs the small tree: {_n(t['cpu_per_tx_ratio'], '.2f')}x; memory "
        f"{t['bytes_per_added_node']:,} bytes per added node"
    )
    return "\n".join(lines)
