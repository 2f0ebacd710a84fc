"""What a bridge does to each frame, decided without I/O: seeded, replayable, counted.

A ``FaultSchedule`` draws each frame's fate from ``canergy.faults.FaultInjector`` (the demo's
loss, duplication, reordering, delay and bit flips), one injector per direction, each seeded from
the schedule's seed and the direction alone. Frames that cross while a ``Partition`` is on are
dropped without a draw; copies whose delay would deliver them during one are dropped too (in
flight when the link was cut). So the n-th frame of a direction meets the same fate in every
run with the same seed and the same partitioned frames before it, whatever its data and whatever
the other direction carries: a run's decisions replay from its seed and its frames. Times are
integer µs since the bridge started, passed in.

A ``PowerCut`` switches a node process off for a time (the bridge kills it and starts it again,
``canergy.bridge.link``): the schedule says when (``power_events``), in the same times.
"""

from __future__ import annotations

import heapq
import itertools
import random
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Generic, TypeVar

from canergy.faults import FaultCounters, FaultInjector, FaultProfile
from canergy.units import format_duration, parse_duration

T = TypeVar("T")

DIRECTIONS = (0, 1)
"""0: from the first bus to the second, 1: back."""


def _shown(text: str, most: int = 40) -> str:
    """``text`` quoted for an error message, cut short when long."""
    return repr(text) if len(text) <= most else f"{text[:most]!r}..."


@dataclass(frozen=True, slots=True)
class Partition:
    """The link is cut (both directions) from ``start_us`` for ``length_us``."""

    start_us: int
    length_us: int

    def __post_init__(self) -> None:
        if self.start_us < 0 or self.length_us <= 0:
            raise ValueError("a partition starts at 0 or later and lasts more than 0")

    @classmethod
    def parse(cls, text: str) -> Partition:
        """``AT+FOR``, two durations: e.g. ``2s+3s`` cuts the link from 2 s after the start
        for 3 s."""
        at, plus, length = text.partition("+")
        try:
            if not plus:
                raise ValueError("give AT+FOR, e.g. 2s+3s")
            return cls(parse_duration(at.strip()), parse_duration(length.strip()))
        except ValueError as exc:
            raise ValueError(f"partition {_shown(text)}: {exc}") from None

    def covers(self, t_us: int) -> bool:
        return self.start_us <= t_us < self.start_us + self.length_us

    def __str__(self) -> str:
        return f"{format_duration(self.start_us)}+{format_duration(self.length_us)}"


NAME = re.compile(r"[A-Za-z0-9_.-]+")
"""A node process's name in a ``PowerCut``."""


@dataclass(frozen=True, slots=True)
class PowerCut:
    """Node process ``node`` (by its name; ``""``: every node process the bridge was given)
    loses its power at ``start_us`` (killed) and gets it back ``length_us`` later (started
    again from what it kept)."""

    start_us: int
    length_us: int
    node: str = ""

    def __post_init__(self) -> None:
        if self.start_us < 0 or self.length_us <= 0:
            raise ValueError("a power cut starts at 0 or later and lasts more than 0")
        if self.node and not NAME.fullmatch(self.node):
            raise ValueError(f"node name {_shown(self.node)}: letters, digits, '_', '.', '-'")

    @classmethod
    def parse(cls, text: str) -> PowerCut:
        """``[NAME@]AT+FOR``: e.g. ``node1@2s+1s`` kills node process ``node1`` 2 s after the
        start and starts it again 1 s later; without ``NAME@``, every node process."""
        name, at, times = text.rpartition("@")
        try:
            if at and not name.strip():
                raise ValueError("give NAME@AT+FOR or AT+FOR, e.g. node1@2s+1s")
            window = Partition.parse(times)
            return cls(window.start_us, window.length_us, name.strip())
        except ValueError as exc:
            raise ValueError(f"power cut {_shown(text)}: {exc}") from None

    def __str__(self) -> str:
        window = f"{format_duration(self.start_us)}+{format_duration(self.length_us)}"
        return f"{self.node}@{window}" if self.node else window


@dataclass(slots=True)
class DirectionCounts:
    """What one direction did so far: ``frames`` seen, of which ``partitioned`` were dropped
    by a partition; the injector's counts of the others; ``forwarded`` copies sent on and
    ``send_errors`` copies the bus refused (counted by whoever sends)."""

    faults: FaultCounters = field(default_factory=FaultCounters)
    partitioned: int = 0
    cut_in_flight: int = 0
    """Copies delayed into a partition: in flight when the link was cut, never arriving."""
    forwarded: int = 0
    send_errors: int = 0

    def as_json(self) -> dict[str, int]:
        counts = asdict(self.faults)
        counts["frames"] += self.partitioned
        counts.update(partitioned=self.partitioned, cut_in_flight=self.cut_in_flight)
        return {**counts, "forwarded": self.forwarded, "send_errors": self.send_errors}


class FaultSchedule:
    """The fate of every frame crossing a bridge, per direction."""

    def __init__(
        self,
        profile: FaultProfile,
        seed: int,
        partitions: Sequence[Partition] = (),
        power_cuts: Sequence[PowerCut] = (),
    ) -> None:
        self.profile, self.seed, self.partitions = profile, seed, tuple(partitions)
        self.power_cuts = tuple(power_cuts)
        edges = [(c.start_us, False, c.node) for c in self.power_cuts]
        edges += [(c.start_us + c.length_us, True, c.node) for c in self.power_cuts]
        self._edges = sorted(edges, key=lambda e: e[0])  # stable: a cut before its end
        self._next_edge = 0
        self.counts = tuple(DirectionCounts() for _ in DIRECTIONS)
        self._injectors = tuple(
            FaultInjector(profile, random.Random(f"canergy-bridge:{seed}:{d}"), c.faults)
            for d, c in zip(DIRECTIONS, self.counts, strict=True)
        )

    def __repr__(self) -> str:
        """What built it (hypothesis prints it for a failing example): the same decisions when
        evaluated with ``FaultSchedule``, ``FaultProfile`` and ``Partition`` in scope."""
        return (
            f"FaultSchedule({self.profile!r}, {self.seed!r}, {self.partitions!r}, "
            f"{self.power_cuts!r})"
        )

    def next_power_event(self) -> int | None:
        """When the next power cut starts or ends (None: no more)."""
        return self._edges[self._next_edge][0] if self._next_edge < len(self._edges) else None

    def power_events(self, t_us: int) -> list[tuple[bool, str]]:
        """The power cuts' starts and ends due by ``t_us`` not given before, in time order:
        ``(on, node)`` each, ``on`` False when the power goes off (``node`` ``""``: every
        node process)."""
        out = []
        while self._next_edge < len(self._edges) and self._edges[self._next_edge][0] <= t_us:
            _, on, node = self._edges[self._next_edge]
            out.append((on, node))
            self._next_edge += 1
        return out

    def partitioned(self, t_us: int) -> bool:
        return any(p.covers(t_us) for p in self.partitions)

    def fate(self, direction: int, data: bytes, t_us: int) -> list[tuple[int, bytes]]:
        """The copies of a frame that crosses in ``direction`` at ``t_us``: ``(due_us,
        data)`` each, ``due_us >= t_us``; empty when lost or partitioned."""
        counts = self.counts[direction]
        if self.partitioned(t_us):
            counts.partitioned += 1
            return []
        copies = [(t_us + delay, out) for delay, out in self._injectors[direction].fate(data)]
        arriving = [(due, out) for due, out in copies if not self.partitioned(due)]
        counts.cut_in_flight += len(copies) - len(arriving)
        return arriving

    def as_json(self) -> dict[str, object]:
        """The seed, the faults and the counts so far, for a status file."""
        return {
            "seed": self.seed,
            "profile": asdict(self.profile),
            "partitions": [str(p) for p in self.partitions],
            "power_cuts": [str(c) for c in self.power_cuts],
            "directions": [c.as_json() for c in self.counts],
        }


PROBABILITIES = ("loss", "duplicate", "reorder", "corrupt")
DURATIONS = {"delay": "delay_us", "jitter": "jitter_us", "reorder_delay": "reorder_delay_us"}


def parse_faults(text: str) -> tuple[FaultProfile, tuple[Partition, ...], tuple[PowerCut, ...]]:
    """``loss=0.1,duplicate=0.05,delay=2ms,jitter=1ms,partition=2s+1s,cut=node1@3s+1s`` as a
    profile (no delay unless given), partitions and power cuts (``partition`` and ``cut``
    repeatable); ``ValueError`` naming the part."""
    kwargs: dict[str, object] = {"delay_us": 0, "jitter_us": 0}
    partitions = []
    cuts = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = (x.strip() for x in part.partition("="))
        try:
            if not eq:
                raise ValueError("give KEY=VALUE")
            if key in PROBABILITIES:
                kwargs[key] = float(value)
            elif key in DURATIONS:
                kwargs[DURATIONS[key]] = parse_duration(value)
            elif key == "partition":
                partitions.append(Partition.parse(value))
            elif key == "cut":
                cuts.append(PowerCut.parse(value))
            else:
                known = ", ".join((*PROBABILITIES, *DURATIONS, "partition", "cut"))
                raise ValueError(f"unknown fault (known: {known})")
        except ValueError as exc:
            raise ValueError(f"faults {_shown(text)}: {_shown(part)}: {exc}") from None
    try:
        return FaultProfile(**kwargs), tuple(partitions), tuple(cuts)  # type: ignore[arg-type]
    except ValueError as exc:
        raise ValueError(f"faults {_shown(text)}: {exc}") from None


class Held(Generic[T]):
    """Items waiting for their due time (integer µs), released in due order, ties in the order
    they were held."""

    def __init__(self) -> None:
        self._heap: list[tuple[int, int, T]] = []
        self._seq = itertools.count()

    def push(self, due_us: int, item: T) -> None:
        heapq.heappush(self._heap, (due_us, next(self._seq), item))

    def next_due(self) -> int | None:
        return self._heap[0][0] if self._heap else None

    def pop_due(self, now_us: int) -> list[T]:
        out = []
        while self._heap and self._heap[0][0] <= now_us:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def __len__(self) -> int:
        return len(self._heap)
