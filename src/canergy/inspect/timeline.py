"""A capture over time, for ``canergy plot``: every node's books as the audit rebuilds them after
each of its frames (granted, returned, the most it can hold) and the frames for a sequence chart.

Granted is what the node booked (its COMMITTED transactions), returned its acknowledged returns,
and the bound is ``NodeBooks.holdable_bound`` (None until the capture shows an intention).
Energies stay integer µJ; times are seconds since the capture's first frame, or frame numbers
when the capture has no timestamps (candump's default format).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from canergy.inspect.audit import Auditor, NodeBooks, node_label
from canergy.inspect.frames import Described
from canergy.messages import Direction, Telemetry

SAMPLES = 4000
"""Samples per node at most over the capture's span (more changes are merged into the next)."""


@dataclass(slots=True)
class NodeSeries:
    label: str
    times: list[float] = field(default_factory=list)
    granted_uj: list[int] = field(default_factory=list)
    returned_uj: list[int] = field(default_factory=list)
    holdable_uj: list[int | None] = field(default_factory=list)
    alarms: list[float] = field(default_factory=list)
    """Times of the frames the audit flagged for this node."""

    def sample(self, t: float, b: NodeBooks) -> None:
        values = (b.booked(), b.acked_returns(), b.holdable_bound())
        if self.times and values == self.last():
            return
        self.times.append(t)
        self.granted_uj.append(values[0])
        self.returned_uj.append(values[1])
        self.holdable_uj.append(values[2])

    def last(self) -> tuple[int, int, int | None]:
        return self.granted_uj[-1], self.returned_uj[-1], self.holdable_uj[-1]


@dataclass(frozen=True, slots=True)
class Mark:
    """One canergy frame in the sequence chart."""

    t: float
    node: str
    kind: str
    to_client: bool
    damaged: bool


@dataclass(slots=True)
class Timeline:
    timed: bool
    """False: the capture has no timestamps and times are frame numbers."""
    start: float
    end: float
    frames: int
    foreign: int
    nodes: dict[str, NodeSeries]
    marks: list[Mark]
    violations: list[str]


def timeline(
    described: Sequence[Described], *, reordered: bool = False, samples: int = SAMPLES
) -> Timeline:
    """Feed the audit frame by frame and sample each node's books after its frames."""
    timed = bool(described) and all(d.timestamp is not None for d in described)
    times = [d.timestamp or 0.0 for d in described] if timed else list(range(len(described)))
    start = min(times, default=0.0)
    span = max(times, default=0.0) - start
    gap = span / samples if samples else 0.0
    auditor = Auditor(reordered=reordered)
    many = len({d.channel for d in described if d.message is not None}) > 1
    series: dict[tuple[str, int], NodeSeries] = {}
    sampled: dict[tuple[str, int], float] = {}
    marks: list[Mark] = []
    for d, stamp in zip(described, times, strict=True):
        t = float(stamp) - start
        before = len(auditor.violations)
        auditor.feed(d)
        for v in auditor.violations[before:]:
            if v.node is not None:
                _series(series, (v.channel, v.node), many).alarms.append(t)
        m = d.message
        if m is None:
            continue
        key = (d.channel, m.node)
        s = _series(series, key, many)
        marks.append(
            Mark(t, s.label, m.TYPE.name, m.TYPE.direction is Direction.TO_CLIENT, not d.crc_ok)
        )
        b = auditor.nodes.get(key)
        if b is None or isinstance(m, Telemetry):
            continue
        if key not in sampled or t - sampled[key] >= gap:
            s.sample(t, b)
            sampled[key] = t
    auditor.finish()
    end = span
    for key, s in series.items():
        b = auditor.nodes.get(key)
        if b is not None:
            s.sample(end, b)
            if s.times and s.times[-1] != end:  # the last value holds to the end of the capture
                s.times.append(end)
                s.granted_uj.append(s.granted_uj[-1])
                s.returned_uj.append(s.returned_uj[-1])
                s.holdable_uj.append(s.holdable_uj[-1])
    nodes = {s.label: s for _, s in sorted(series.items())}
    return Timeline(
        timed=timed,
        start=start,
        end=end,
        frames=auditor.frames,
        foreign=auditor.foreign,
        nodes=nodes,
        marks=marks,
        violations=[v.what for v in auditor.violations],
    )


def _series(
    series: dict[tuple[str, int], NodeSeries], key: tuple[str, int], many: bool
) -> NodeSeries:
    s = series.get(key)
    if s is None:
        s = series[key] = NodeSeries(str(node_label(key[0], key[1], many)))
    return s
