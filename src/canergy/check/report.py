"""Human-readable summary and counterexample trace of a model-checking run."""

from __future__ import annotations

from canergy.check.explore import CheckResult
from canergy.units import format_energy


def format_summary(r: CheckResult) -> str:
    b = r.bounds
    bounds = (
        f"clients {b.clients}, transactions {b.transactions}, losses {b.losses}, "
        f"duplicates {b.duplicates}, power losses {b.power_losses}, in flight {b.in_flight}, "
        f"units {b.units}, retries {b.retries}"
        + ("" if b.timeouts is None else f", timeouts {b.timeouts}")
        + (f", NV losses {b.nv_losses}" if b.nv_losses else "")
        + (f", old copies {b.old_copies}" if b.old_copies else "")
        + (" (backups taken at any moment)" if b.backups and b.old_copies else "")
        + (f", supervisor old copies {b.supervisor_old_copies}" if b.supervisor_old_copies else "")
        + (
            " (supervisor backups taken at any moment)"
            if b.supervisor_backups and b.supervisor_old_copies
            else ""
        )
        + (f", forgeries {b.forgeries}" if b.forgeries else "")
        + (f", replays {b.replays}" if b.replays else "")
        + (f", re-syncs {b.resyncs}" if b.resyncs else "")
    )
    lines = [
        f"canergy check: variant {r.variant}; {bounds}",
        f"states {r.states:,}  transitions {r.transitions:,}  depth {r.depth}  "
        f"time {r.seconds:.2f} s  ({r.states_per_second:,.0f} states/s, {r.engine} engine"
        + (f", {r.workers} processes)" if r.workers > 1 else ")")
        + ("" if r.complete else "  INCOMPLETE: " + "; ".join(r.notes)),
        f"reductions: symmetry {'on' if r.symmetry else 'off'}, "
        f"{r.subsumed:,} states subsumed by cheaper ones",
        f"worst dissipation in a quiescent state: {format_energy(r.worst_quiescent_dissipation)} "
        f"over {r.quiescent_states:,} quiescent states",
        f"violations: {r.violations:,} state(s) with energy generated",
    ]
    if r.counterexample is not None:
        lines.append(f"shortest counterexample: {len(r.counterexample)} steps (--trace shows it)")
    return "\n".join(lines)


def format_trace(r: CheckResult) -> str:
    if r.counterexample is None:
        return "no counterexample"
    lines = ["shortest counterexample:"]
    for n, (step, world) in enumerate(r.counterexample, 1):
        led = world.ledger()
        lines.append(
            f"{n:>3}. {step.describe():<70} Us {led.supervisor_usable // 1000:>3} "
            f"Ts {led.supervisor_reserved // 1000:>3} Uc {led.clients_usable // 1000:>3} "
            f"spent {led.spent // 1000:>3} overlap {led.overlap // 1000:>3} "
            f"dissipated {led.dissipated // 1000:>4} (units)"
        )
    return "\n".join(lines)
