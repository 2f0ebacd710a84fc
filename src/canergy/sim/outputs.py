"""``canergy simulate`` output files: summary.json, trace.csv and the PNG figures."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from canergy.sim.engine import SimResult

TRACE_FIELDS = [
    "time_s",
    "strategy",
    "event",
    "at",
    "message",
    "fields",
    "detail",
    "supervisor_usable_uj",
    "clients_usable_uj",
    "sum_uj",
    "dissipated_uj",
]


def write_outputs(results: Sequence[SimResult], out: Path) -> dict[str, Any]:
    """Write everything for ``results`` (one per strategy, same channel) into ``out``."""
    from canergy.sim import figures  # matplotlib is imported only when figures are drawn

    out.mkdir(parents=True, exist_ok=True)
    summary = {r.config.strategy: r.summary() for r in results}
    config = asdict(results[0].config)
    config.pop("strategy")
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "config.json").write_text(json.dumps(config, indent=2, default=str) + "\n")
    with open(out / "trace.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, TRACE_FIELDS)
        writer.writeheader()
        for r in results:
            writer.writerows(r.trace)
    for r in results:
        figures.message_sequence(r, out / f"sequence-{r.config.strategy}.png")
        figures.budgets(r, out / f"budgets-{r.config.strategy}.png")
    figures.overlay(results, out / "budgets-overlay.png")
    return summary
