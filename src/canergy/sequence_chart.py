"""Message-sequence charts in the style of the paper's Fig. 6, shared by the simulator's figures
and ``canergy plot``: the supervisor's lane on top, one lane per client below, a line per frame
from its sender's lane to its receiver's, one colour per message type."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from canergy.extras import MissingExtra

try:
    from matplotlib.axes import Axes
    from matplotlib.collections import LineCollection
except ImportError as exc:  # canergy[plot]
    raise MissingExtra("plot", exc) from exc

COLOURS = {
    "INTENTION": "black",
    "ACK": "tab:blue",
    "COMMIT": "tab:green",
    "COMMITTED": "tab:green",
    "ABORT": "tab:red",
    "ABORTED": "tab:red",
    "STATUS_REQUEST": "gold",
    "FINAL_ACK": "deepskyblue",
    "RETURN": "tab:purple",
    "RETURN_ACK": "plum",
    "TELEMETRY": "tab:olive",
    "JOIN": "tab:orange",
    "ADMIT": "tab:orange",
}
LOST_STUB_S = 0.5
"""Length in time of the dashed stub drawn for a frame that never arrived."""


@dataclass(frozen=True, slots=True)
class Arrow:
    """One frame: its type name, when and from which lane it left, where it went and when it
    arrived there (several times if duplicated; none: lost)."""

    kind: str
    start: float
    start_lane: float
    end_lane: float
    arrivals: tuple[float, ...]


def draw_arrows(ax: Axes, arrows: Iterable[Arrow], *, lw: float = 1.2) -> None:
    """A solid line per arrival, a dashed stub ending in a cross for a lost frame; one line
    collection per type (a capture may hold many thousand frames), each named once in the
    legend, in order of first appearance."""
    solid: dict[str, list[list[tuple[float, float]]]] = {}
    stubs: dict[str, list[list[tuple[float, float]]]] = {}
    for a in arrows:
        solid.setdefault(a.kind, [])
        if a.arrivals:
            solid[a.kind] += [[(a.start, a.start_lane), (t, a.end_lane)] for t in a.arrivals]
        else:
            mid = (a.start_lane + a.end_lane) / 2
            stubs.setdefault(a.kind, []).append(
                [(a.start, a.start_lane), (a.start + LOST_STUB_S, mid)]
            )
    for kind, segments in solid.items():
        colour = COLOURS.get(kind, "grey")
        named = False
        if segments:
            ax.add_collection(LineCollection(segments, colors=colour, linewidths=lw, label=kind))
            named = True
        lost = stubs.get(kind, [])
        if lost:
            ax.add_collection(LineCollection(lost, colors=colour, linewidths=1, linestyles="--"))
            ends = [segment[1] for segment in lost]
            ax.plot(
                [x for x, _ in ends],
                [y for _, y in ends],
                "x",
                color=colour,
                label=None if named else kind,
            )
    ax.autoscale_view()


def label_lanes(ax: Axes, names: Sequence[str], title: str) -> None:
    """Lanes top to bottom (``names[0]`` at y = len - 1 ... the last at 0), time axis, legend."""
    top = len(names) - 1
    ax.set_yticks([float(top - i) for i in range(len(names))])
    ax.set_yticklabels(list(names))
    ax.set_xlabel("time (s)")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
