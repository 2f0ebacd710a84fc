"""Frames someone else sent on identifiers only this side transmits: a second supervisor, or a
device spoofing a node. Needs no key: a side never receives its own frames back, so every frame in
its own direction for a node it handles is foreign. Counted per node, the latest kept, logged."""

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

    @property
    def total(self) -> int:
        return sum(self.by_node.values())

    def record(self, node: int, what: str, kind: str, now: int) -> None:
        count = self.by_node.get(node, 0) + 1
        self.by_node[node] = count
        if self.first_at is None:
            self.first_at = now
        name = self.name(node)
        self.recent.append({"time_us": now, "node": name, "kind": kind, "frame": what})
        if count == 1 or count % LOG_EVERY == 0:
            log.warning("%s: intrusion #%d for node %s: %s (%s)", self.who, count, name, what, kind)

    def as_json(self) -> dict[str, Any]:
        return {
            "total": self.total,
            "by_node": {str(self.name(n)): c for n, c in sorted(self.by_node.items())},
            "first_at_us": self.first_at,
            "recent": list(self.recent),
        }
