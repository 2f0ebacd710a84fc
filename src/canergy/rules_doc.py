"""The transition tables as documents: a markdown reference and one state diagram per table.

``canergy rules --docs docs`` writes ``docs/transitions.md`` and ``docs/figures/states-*.png``
from the tables themselves; each figure carries the SHA-256 of the transitions it draws in its
PNG ``Description``, so a test can tell a stale figure without comparing pixels.
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

from canergy.core.state import Phase
from canergy.core.table import RuleTable, event_name, refuse
from canergy.core.variants import VARIANTS
from canergy.extras import require

TABLES: list[RuleTable[Any, Any]] = [
    table for v in VARIANTS.values() for table in (v.supervisor, v.client)
]


def figure_name(table: RuleTable[Any, Any]) -> str:
    return f"states-{table.variant}-{table.role.value}.png"


def edges(table: RuleTable[Any, Any]) -> dict[tuple[Phase, Phase], list[str]]:
    """``(from, to) -> event labels`` for every listed cell; self-loops only for listed cells."""
    out: dict[tuple[Phase, Phase], list[str]] = defaultdict(list)
    for (phase, event), tr in table.listed.items():
        for to in sorted(tr.to):
            out[(phase, to)].append(event_name(event))
    return dict(out)


def diagram_source(table: RuleTable[Any, Any]) -> str:
    """The text a figure is drawn from (and hashed)."""
    lines = [f"{table.variant} {table.role.value}: {', '.join(p.name for p in table.phases)}"]
    for (a, b), labels in sorted(edges(table).items()):
        lines.append(f"{a.name} -> {b.name}: {', '.join(labels)}")
    return "\n".join(lines) + "\n"


def source_hash(table: RuleTable[Any, Any]) -> str:
    return hashlib.sha256(diagram_source(table).encode()).hexdigest()


def markdown(tables: list[RuleTable[Any, Any]] = TABLES) -> str:
    """Every cell of every table: listed cells with their handler, then what is ignored/refused."""
    out = [
        "# Transition tables",
        "",
        "Generated from `canergy.core` by `canergy rules --docs docs`; do not edit by hand "
        "(a test compares). One table per role and variant, `(phase, event) -> handler`. "
        "Guards on transaction ids and energy live inside the handlers; *next* lists the phases "
        "a handler may leave the state in. Cells not listed ignore the event (messages, timers) "
        "or refuse it with `LocalProtocolError` (local requests).",
        "",
    ]
    for table in tables:
        out += [
            f"## {table.variant}: {table.role.value}",
            "",
            f"![{table.variant} {table.role.value} states](figures/{figure_name(table)})",
            "",
            "| phase | event | handler | next | what it does |",
            "| --- | --- | --- | --- | --- |",
        ]
        for phase in table.phases:
            for event in table.events:
                tr = table.listed.get((phase, event))
                if tr is not None:
                    nxt = ", ".join(p.name for p in sorted(tr.to))
                    out.append(
                        f"| {phase.name} | {event_name(event)} | `{tr.name}` | {nxt} | "
                        f"{tr.summary} |"
                    )
        ignored, refused = _defaults(table)
        out += ["", f"Ignored: {ignored or 'none'}.", "", f"Refused: {refused or 'none'}.", ""]
    return "\n".join(out)


def _defaults(table: RuleTable[Any, Any]) -> tuple[str, str]:
    by_kind: dict[bool, list[str]] = {True: [], False: []}
    for event in table.events:
        for kind in (True, False):
            phases = [
                p.name
                for p in table.phases
                if (p, event) not in table.listed
                and (table.cells[(p, event)].handler is refuse) is kind
            ]
            if phases:
                where = "any phase" if len(phases) == len(table.phases) else ", ".join(phases)
                by_kind[kind].append(f"{event_name(event)} in {where}")
    return "; ".join(by_kind[False]), "; ".join(by_kind[True])


def draw(table: RuleTable[Any, Any], path: Path) -> None:
    """Phases on a circle, one arrow per phase change, self-loop events listed under a phase."""
    require("plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(table.phases)
    pos = {
        p: (
            math.cos(math.pi / 2 - 2 * math.pi * i / n),
            math.sin(math.pi / 2 - 2 * math.pi * i / n),
        )
        for i, p in enumerate(table.phases)
    }
    if n == 2:
        pos = {table.phases[0]: (-1.4, 0.0), table.phases[1]: (1.4, 0.0)}
    fig, ax = plt.subplots(figsize=(10, 8))
    ax.set_axis_off()
    ax.set_xlim(-2.4, 2.4)
    ax.set_ylim(-1.9, 1.6)
    ax.set_title(f"{table.variant} {table.role.value}: transitions", fontsize=12)
    loops: dict[Phase, list[str]] = defaultdict(list)
    for (a, b), labels in edges(table).items():
        if a is b:
            loops[a] += labels
            continue
        (x0, y0), (x1, y1) = pos[a], pos[b]
        ax.annotate(
            "",
            xy=(x1, y1),
            xytext=(x0, y0),
            arrowprops={
                "arrowstyle": "-|>",
                "connectionstyle": "arc3,rad=0.18",
                "shrinkA": 22,
                "shrinkB": 22,
                "color": "tab:blue",
            },
        )
        mx, my = (x0 + x1) / 2, (y0 + y1) / 2
        nx, ny = (y1 - y0) * 0.12, (x0 - x1) * 0.12  # toward the arc's bulge
        ax.text(
            mx + nx,
            my + ny,
            "\n".join(labels),
            fontsize=7,
            ha="center",
            va="center",
            color="tab:blue",
            bbox={"fc": "white", "ec": "none", "alpha": 0.8},
        )
    for phase, (x, y) in pos.items():
        ax.text(
            x,
            y,
            phase.name,
            ha="center",
            va="center",
            fontsize=10,
            weight="bold",
            bbox={"boxstyle": "round,pad=0.5", "fc": "#eef", "ec": "black"},
        )
        if loops[phase]:
            rows = [", ".join(loops[phase][i : i + 3]) for i in range(0, len(loops[phase]), 3)]
            ax.text(
                x,
                y - 0.12,
                "stays on:\n" + "\n".join(rows),
                ha="center",
                va="top",
                fontsize=7,
                color="dimgray",
            )
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None, "Description": source_hash(table)})
    plt.close(fig)


def write_docs(docs: Path) -> list[Path]:
    """Write ``transitions.md`` and the figures under ``docs``; the paths written."""
    require("plot")  # before anything is written
    figures = docs / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    written = []
    for table in TABLES:
        draw(table, figures / figure_name(table))
        written.append(figures / figure_name(table))
    (docs / "transitions.md").write_text(markdown())
    return [docs / "transitions.md", *written]
