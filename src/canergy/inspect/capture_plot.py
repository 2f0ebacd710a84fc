"""``canergy plot``: a capture's budgets per node over time and its message sequence, drawn like
the simulator's figures (step lines, the same colours per message type, 110 dpi)."""

from __future__ import annotations

import math
from pathlib import Path

from canergy.extras import MissingExtra

try:
    import matplotlib

    matplotlib.use("Agg")  # files only, no display needed
    import matplotlib.pyplot as plt
except ImportError as exc:  # canergy[plot]
    raise MissingExtra("plot", exc) from exc

from canergy.inspect.timeline import Timeline
from canergy.sequence_chart import COLOURS, Arrow, draw_arrows, label_lanes


def _joules(values: list[int | None]) -> list[float]:
    return [math.nan if v is None else v / 1e6 for v in values]


def draw(
    tl: Timeline,
    nodes: list[str],
    path: Path,
    title: str,
    window: tuple[float, float] | None = None,
) -> None:
    """One panel per node in ``nodes`` (granted, returned, the most it can hold, audit alarms),
    the message-sequence chart of those nodes below, on one time axis (``window``: from, to)."""
    lanes = len(nodes) + 1
    chart = max(1.4, 0.35 * lanes)
    fig, axes = plt.subplots(
        len(nodes) + 1,
        1,
        sharex=True,
        figsize=(12, 1.2 + 1.8 * len(nodes) + chart),
        gridspec_kw={"height_ratios": [1.8] * len(nodes) + [chart]},
        squeeze=False,
    )
    panels = [row[0] for row in axes]
    for ax, name in zip(panels, nodes, strict=False):
        s = tl.nodes[name]
        ax.step(
            s.times,
            _joules(list(s.granted_uj)),
            where="post",
            color="tab:green",
            label="granted (committed)",
        )
        ax.step(
            s.times,
            _joules(list(s.returned_uj)),
            where="post",
            color="tab:purple",
            label="returned",
        )
        ax.step(
            s.times,
            _joules(s.holdable_uj),
            where="post",
            color="black",
            ls="--",
            lw=1,
            label="holdable at most",
        )
        if s.alarms:
            ax.plot(s.alarms, [0.0] * len(s.alarms), "r^", ms=6, label="audit alarm")
        if not s.times:
            ax.text(
                0.5,
                0.5,
                "no transaction in the capture",
                transform=ax.transAxes,
                ha="center",
                va="center",
                color="grey",
            )
        ax.set_ylabel(f"node {name}\n(J)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    seq = panels[-1]
    lane = {name: float(len(nodes) - 1 - i) for i, name in enumerate(nodes)}
    top = float(len(nodes))
    arrows, damaged = [], []
    for m in tl.marks:
        if m.node not in lane:
            continue
        start, end = (top, lane[m.node]) if m.to_client else (lane[m.node], top)
        if m.damaged:
            damaged.append((m.t, start))
        else:
            arrows.append(Arrow(m.kind, m.t, start, end, (m.t,)))
    draw_arrows(seq, arrows, lw=0.8)
    for kind in dict.fromkeys(a.kind for a in arrows):  # a dot where each frame arrived
        ends = [(a.start, a.end_lane) for a in arrows if a.kind == kind]
        seq.scatter(*zip(*ends, strict=True), s=6, color=COLOURS.get(kind, "grey"), zorder=3)
    if damaged:
        seq.plot(*zip(*damaged, strict=True), "x", color="grey", label="CRC failed")
    label_lanes(
        seq, ["supervisor", *(f"node {n}" for n in nodes)], "message sequence (dot: receiver)"
    )
    seq.set_xlabel("time since the first frame (s)" if tl.timed else "frame number")
    if window is not None:
        seq.set_xlim(*window)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
