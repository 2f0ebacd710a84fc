"""Frames someone else sent on identifiers only this side transmits: a second supervisor, or a
device spoofing a node. Needs no key: a side never receives its own frames back, so every frame in
its own direction for a node it handles is foreign. Counted per node, the latest kept, logged.

In authenticated mode anyone on the bus can send frames without a MAC, with a wrong one, or
replay old ones: those are refused, and ``Refusals`` counts them per node and reason with a rate
and logs them at most once a second (a flood of them costs one log line a second, not one a
frame). They are never a reason to stop: only authentic evidence is (``Intrusions.record`` with
``authentic``).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

log = logging.getLogger(__name__)

KEPT = 20
LOG_EVERY = 100
"""After a node's first intrusion, log one in this many (all are counted)."""
RATE_WINDOW_US = 1_000_000
"""Refusal rates are per second, over a sliding window of this length."""
LOG_PERIOD_US = 1_000_000
"""Refusals: at most one log line in this long (the first refusal is logged at once)."""


def frame_text(frame: can.Message) -> str:
    """candump's compact form, ``0CE00901#0102``."""
    ident = f"{frame.arbitration_id:08X}" if frame.is_extended_id else f"{frame.arbitration_id:03X}"
    return f"{ident}#{'R' if frame.is_remote_frame else bytes(frame.data).hex().upper()}"


@dataclass
class Intrusions:
    who: str
    """Who saw them, for the log: ``supervisor`` or ``node 3``."""
    name: Callable[[int], int | str] = int
    """How reports name a node (a supervisor over several buses: ``bus/node``)."""
    by_node: dict[int, int] = field(default_factory=dict)
    recent: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=KEPT))
    first_at: int | None = None
    authentic_by_node: dict[int, int] = field(default_factory=dict)
    """Of them, authentic evidence: what only a key holder could have sent."""
    logged_by_node: dict[int, int] = field(default_factory=dict)
    """Of them, those not ``quiet``: the first of these per node is logged, then one in
    ``LOG_EVERY``."""

    @property
    def total(self) -> int:
        return sum(self.by_node.values())

    def record(
        self,
        node: int,
        what: str,
        kind: str,
        now: int,
        *,
        quiet: bool = False,
        authentic: bool = False,
    ) -> None:
        """``quiet``: not logged here (refused frames: ``Refusals`` logs them, rate-limited).
        ``authentic``: verified evidence (a frame checked under a key), marked in the report."""
        count = self.by_node.get(node, 0) + 1
        self.by_node[node] = count
        if authentic:
            self.authentic_by_node[node] = self.authentic_by_node.get(node, 0) + 1
        if self.first_at is None:
            self.first_at = now
        name = self.name(node)
        event = {"time_us": now, "node": name, "kind": kind, "frame": what}
        self.recent.append({**event, "authentic": True} if authentic else event)
        if quiet:
            return
        loud = self.logged_by_node.get(node, 0) + 1
        self.logged_by_node[node] = loud
        if loud == 1 or loud % LOG_EVERY == 0:
            log.warning("%s: intrusion #%d for node %s: %s (%s)", self.who, count, name, what, kind)

    def as_json(self) -> dict[str, Any]:
        authentic = sorted(self.authentic_by_node.items())
        return {
            "total": self.total,
            "by_node": {str(self.name(n)): c for n, c in sorted(self.by_node.items())},
            "first_at_us": self.first_at,
            "recent": list(self.recent),
            "authentic": {
                "total": sum(c for _, c in authentic),
                "by_node": {str(self.name(n)): c for n, c in authentic},
            },
        }


@dataclass(slots=True)
class Rate:
    """Events per second over a sliding window: the current window's count plus the previous
    one's, weighted by how much of it still lies within the last ``window_us``."""

    window_us: int = RATE_WINDOW_US
    index: int = 0
    current: int = 0
    previous: int = 0

    def _roll(self, now: int) -> None:
        index = now // self.window_us
        if index != self.index:
            self.previous = self.current if index == self.index + 1 else 0
            self.current, self.index = 0, index

    def add(self, now: int) -> None:
        self._roll(now)
        self.current += 1

    def per_s(self, now: int) -> float:
        self._roll(now)
        left = 1 - (now % self.window_us) / self.window_us
        return (self.previous * left + self.current) * 1_000_000 / self.window_us


@dataclass(slots=True)
class _Reason:
    count: int = 0
    rate: Rate = field(default_factory=Rate)
    unlogged: int = 0


@dataclass
class Refusals:
    """Frames refused by the MAC or freshness check (authenticated mode), per node and reason:
    a count, a rate (per second), the latest few; one log line at most every ``log_period_us``
    (the first at once). Anyone on the bus can send them: they are reported, never acted on."""

    who: str
    name: Callable[[int], int | str] = int
    log_period_us: int = LOG_PERIOD_US
    by_node: dict[int, dict[str, _Reason]] = field(default_factory=dict)
    recent: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=KEPT))
    rate: Rate = field(default_factory=Rate)
    first_at: int | None = None
    last_at: int | None = None
    logged_at: int | None = None

    @property
    def total(self) -> int:
        return sum(r.count for reasons in self.by_node.values() for r in reasons.values())

    def of_node(self, node: int) -> int:
        return sum(r.count for r in self.by_node.get(node, {}).values())

    def record(self, node: int, reason: str, what: str, now: int) -> None:
        entry = self.by_node.setdefault(node, {}).setdefault(reason, _Reason())
        entry.count += 1
        entry.unlogged += 1
        entry.rate.add(now)
        self.rate.add(now)
        if self.first_at is None:
            self.first_at = now
        self.last_at = now
        self.recent.append(
            {"time_us": now, "node": self.name(node), "reason": reason, "frame": what}
        )
        if self.logged_at is None:  # the first one at once, with its frame
            self.logged_at = now
            entry.unlogged = 0
            log.warning(
                "%s: refused a frame for node %s: %s (%s); refused frames are counted and "
                "reported (at most one line a second), never acted on",
                self.who,
                self.name(node),
                reason,
                what,
            )
        else:
            self.tick(now)

    def tick(self, now: int) -> None:
        """Log what was refused since the last line, if there is any and the period is over."""
        if self.logged_at is None or now - self.logged_at < self.log_period_us:
            return
        parts = []
        count = 0
        for node, reasons in sorted(self.by_node.items()):
            mine = [(reason, r.unlogged) for reason, r in sorted(reasons.items()) if r.unlogged]
            if mine:
                text = ", ".join(f"{reason} {n}" for reason, n in mine)
                parts.append(f"node {self.name(node)}: {text}")
                count += sum(n for _, n in mine)
                for r in reasons.values():
                    r.unlogged = 0
        if not count:
            return
        seconds = (now - self.logged_at) / 1e6
        self.logged_at = now
        log.warning(
            "%s: refused %d frame(s) in the last %.1f s (%.1f/s now; %s); %d since start, "
            "none acted on",
            self.who,
            count,
            seconds,
            self.rate.per_s(now),
            "; ".join(parts),
            self.total,
        )

    def as_json(self, now: int) -> dict[str, Any]:
        nodes: dict[str, Any] = {}
        for node, reasons in sorted(self.by_node.items()):
            nodes[str(self.name(node))] = {
                "total": sum(r.count for r in reasons.values()),
                "per_s": round(sum(r.rate.per_s(now) for r in reasons.values()), 1),
                "reasons": {
                    reason: {"count": r.count, "per_s": round(r.rate.per_s(now), 1)}
                    for reason, r in sorted(reasons.items())
                },
            }
        return {
            "total": self.total,
            "per_s": round(self.rate.per_s(now), 1),
            "by_node": nodes,
            "first_at_us": self.first_at,
            "last_at_us": self.last_at,
            "recent": list(self.recent),
        }
