"""Human-readable report of a demo run: settings, per-node table, ledger, verdict."""

from __future__ import annotations

from canergy.demo.result import DemoResult
from canergy.units import format_energy


def format_report(r: DemoResult) -> str:
    cfg, led, c = r.config, r.ledger, r.injector.counters
    f = cfg.faults
    lines = [
        f"canergy demo: variant {cfg.variant}, {len(cfg.nodes)} nodes, seed {cfg.seed}, "
        f"loss {f.loss:.0%}, duplicate {f.duplicate:.0%}, reorder {f.reorder:.0%}, "
        f"corrupt {f.corrupt:.0%}",
        f"virtual time {r.virtual_us / 1e6:.2f} s"
        + ("" if r.finished else " (stopped at the duration limit before settling)")
        + f"; transactions started {r.transactions_started}; "
        + ", ".join(f"{k} {v}" for k, v in r.outcomes.items() if k != "settled"),
        f"frames sent {r.frames_sent}: lost {c.lost}, duplicated {c.duplicated}, "
        f"reordered {c.reordered}, corrupted {c.corrupted}; decode errors {r.decode_errors}; "
        f"supervisor resets {r.supervisor_resets}",
        "",
        f"{'node':>4} {'usable':>14} {'spent':>14} {'commits':>7} {'timeout':>7} "
        f"{'aborts':>6} {'returns':>7} {'resets':>6}",
    ]
    for n, s in r.nodes.items():
        lines.append(
            f"{n:>4} {format_energy(r.client_usable[n]):>14} {format_energy(r.client_spent[n]):>14}"
            f" {s.committed:>7} {s.timeout_committed:>7} {s.aborted:>6} {s.returns:>7}"
            f" {s.resets:>6}"
        )
    terms = [
        ("supervisor usable", led.supervisor_usable),
        ("supervisor reserved", led.supervisor_reserved),
        ("clients usable", led.clients_usable),
        ("spent by actuators", led.spent),
        ("returns in flight", led.returns_in_flight),
        ("- overlap (counted once)", -led.overlap),
        ("dissipated", led.dissipated),
    ]
    lines += [
        "",
        f"ledger: initial {format_energy(led.initial)} + injected {format_energy(led.injected)} =",
    ]
    lines += [f"  {name:<26} {format_energy(v):>15}" for name, v in terms]
    if r.passive:
        verdict = (
            "PASSIVE: energy was never created "
            f"(lowest dissipation seen {format_energy(r.min_dissipated)})"
        )
    else:
        at = r.first_violation_us / 1e6 if r.first_violation_us is not None else float("nan")
        verdict = (
            f"NOT PASSIVE: energy was generated (first at {at:.3f} s, "
            f"worst {format_energy(-r.min_dissipated)} created)"
        )
    return "\n".join([*lines, "", f"verdict: {verdict}"])
