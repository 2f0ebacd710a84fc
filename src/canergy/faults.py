"""Seeded channel faults: loss, duplication, reordering, delay and bit corruption.

The injector decides the fate of each frame (``fate``) and leaves time to its caller, so a
virtual-time run and a wall-clock run draw the same faults from the same seed.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class FaultProfile:
    """Probabilities per frame, and latencies in µs."""

    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    delay_us: int = 200
    jitter_us: int = 300
    reorder_delay_us: int = 20_000

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder", "corrupt"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability {p} outside 0..1")
        if min(self.delay_us, self.jitter_us, self.reorder_delay_us) < 0:
            raise ValueError("delays must be >= 0")


@dataclass(slots=True)
class FaultCounters:
    frames: int = 0
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0


@dataclass(slots=True)
class FaultInjector:
    """Draws each frame's fate from one seeded ``random.Random``."""

    profile: FaultProfile
    rng: random.Random
    counters: FaultCounters = field(default_factory=FaultCounters)

    def fate(self, data: bytes) -> list[tuple[int, bytes]]:
        """The copies of a frame that arrive: ``(delay_us, data)`` each; empty when lost."""
        p, rng, n = self.profile, self.rng, self.counters
        n.frames += 1
        if rng.random() < p.loss:
            n.lost += 1
            return []
        copies = 2 if rng.random() < p.duplicate else 1
        n.duplicated += copies - 1
        out = []
        for _ in range(copies):
            delay = p.delay_us + rng.randint(0, p.jitter_us)
            if rng.random() < p.reorder:
                n.reordered += 1
                delay += rng.randint(1, p.reorder_delay_us)
            payload = data
            if data and rng.random() < p.corrupt:
                n.corrupted += 1
                bit = rng.randrange(len(data) * 8)
                flipped = bytearray(data)
                flipped[bit // 8] ^= 1 << (bit % 8)
                payload = bytes(flipped)
            out.append((delay, payload))
        return out
