"""Figures like the paper's: a message-sequence chart (Fig. 6) and budget plots (Figs. 7-9)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from canergy.extras import MissingExtra

try:
    import matplotlib

    matplotlib.use("Agg")  # files only, no display needed
    import matplotlib.pyplot as plt
except ImportError as exc:  # canergy[plot]
    raise MissingExtra("plot", exc) from exc

from canergy.sequence_chart import Arrow, draw_arrows, label_lanes
from canergy.sim.engine import SimResult


def message_sequence(result: SimResult, path: Path, until_s: float | None = 30.0) -> None:
    """Supervisor on top, clients below; a line per frame from sending to arrival (solid),
    lost ones as a dashed stub ending in a cross; grey ticks where a timeout re-sent."""
    k = result.config.clients
    fig, ax = plt.subplots(figsize=(12, 2.2 + 0.6 * k))
    arrows = []
    for f in result.frames:
        if until_s is not None and f["t"] > until_s:
            continue
        top, node = float(k), float(k - f["node"])
        start, end = (top, node) if f["to_client"] else (node, top)
        arrows.append(Arrow(f["type"], f["t"], start, end, tuple(f["arrivals"])))
    draw_arrows(ax, arrows)
    for t, where, _ in result.timeouts:
        if until_s is None or t <= until_s:
            y = float(k) if where == 0 else float(k - where)
            ax.plot([t, t], [y - 0.15, y + 0.15], color="grey", lw=2)
    label_lanes(
        ax,
        ["supervisor", *(f"client {n}" for n in range(1, k + 1))],
        f"message sequence: {result.config.strategy} (grey ticks: timeouts, x: lost)",
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def budgets(result: SimResult, path: Path) -> None:
    """Usable supervisor budget, usable client budgets, their sum and the initial energy."""
    times, sup, cli, dissipated = _columns(result)
    total = [a + b for a, b in zip(sup, cli, strict=True)]
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.step(times, sup, where="post", label="supervisor usable")
    ax.step(
        times, cli, where="post", label="client usable" + ("s" if result.config.clients > 1 else "")
    )
    ax.step(times, total, where="post", label="sum", color="black", lw=1.5)
    ax.axhline(result.config.initial / 1e6, color="grey", ls="--", label="initial energy")
    generated = [(t, s) for t, s, d in zip(times, total, dissipated, strict=True) if d < 0]
    if generated:
        ax.plot(*zip(*generated, strict=True), "r^", ms=5, label="energy generated (ledger)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("energy (J)")
    ax.set_title(f"energy budgets: {result.config.strategy}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def overlay(results: Sequence[SimResult], path: Path) -> None:
    """The sum of usable budgets for every strategy over the same channel realisation."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for r in results:
        times, sup, cli, _ = _columns(r)
        ax.step(
            times,
            [a + b for a, b in zip(sup, cli, strict=True)],
            where="post",
            label=r.config.strategy,
        )
    ax.axhline(results[0].config.initial / 1e6, color="grey", ls="--", label="initial energy")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("usable supervisor + clients (J)")
    ax.set_title("sum of usable budgets per strategy (energy in flight not included)")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _columns(r: SimResult) -> tuple[list[float], list[float], list[float], list[float]]:
    points = [(0.0, r.config.initial, 0, 0), *r.budgets]
    end = r.config.duration_s
    points.append((end, *points[-1][1:]))
    return (
        [p[0] for p in points],
        [p[1] / 1e6 for p in points],
        [p[2] / 1e6 for p in points],
        [p[3] / 1e6 for p in points],
    )
