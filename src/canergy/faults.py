"""Seeded channel faults: delay, Bernoulli or Gilbert–Elliott loss, duplication, reordering,
late frames and bit corruption. One model for the demo, the fault-injecting bus wrapper and the
simulator.

The injector decides the fate of each frame (``fate``) and leaves time to its caller, so a
virtual-time run and a wall-clock run draw the same faults from the same seed. A frame's draws
depend only on the frame's own fate (3 when lost, 8 per arriving copy otherwise), never on the
data or the caller, so two runs that send the same frames in a stream meet the same fates.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class FaultProfile:
    """Probabilities per frame; delays in µs, uniform in ``delay_us ± jitter_us`` or exponential
    with mean ``delay_us`` (``delay="exp"``)."""

    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    delay_us: int = 350
    jitter_us: int = 150
    reorder_delay_us: int = 20_000
    """A reordered copy is held back by up to this much more."""
    delay: str = "uniform"
    burst_enter: float = 0.0
    """Gilbert–Elliott: probability per frame of moving from the good to the bad state."""
    burst_leave: float = 0.3
    burst_loss: float = 1.0
    """Loss probability in the bad state (``loss`` applies in the good one)."""
    late_us: int = 0
    """A copy delayed beyond this times out in the channel and never arrives (0: no limit)."""

    def __post_init__(self) -> None:
        for name in (
            "loss",
            "duplicate",
            "reorder",
            "corrupt",
            "burst_enter",
            "burst_leave",
            "burst_loss",
        ):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} probability {p} outside 0..1")
        if min(self.delay_us, self.jitter_us, self.reorder_delay_us, self.late_us) < 0:
            raise ValueError("delays must be >= 0")
        if self.delay not in ("uniform", "exp"):
            raise ValueError(f"unknown delay distribution {self.delay!r} (uniform, exp)")
        if self.delay == "uniform" and self.jitter_us > self.delay_us:
            raise ValueError("jitter larger than the delay would need negative delays")


@dataclass(slots=True)
class FaultCounters:
    frames: int = 0
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    late: int = 0


@dataclass(slots=True)
class FaultInjector:
    """Draws each frame's fate from one seeded ``random.Random`` (and keeps the burst state)."""

    profile: FaultProfile
    rng: random.Random
    counters: FaultCounters = field(default_factory=FaultCounters)
    bad: bool = False

    def fate(self, data: bytes) -> list[tuple[int, bytes]]:
        """The copies of a frame that arrive: ``(delay_us, data)`` each; empty when lost."""
        p, rng, n = self.profile, self.rng, self.counters
        n.frames += 1
        u_loss, u_burst, u_dup = rng.random(), rng.random(), rng.random()
        if p.burst_enter:
            self.bad = u_burst >= p.burst_leave if self.bad else u_burst < p.burst_enter
        if u_loss < (p.burst_loss if self.bad else p.loss):
            n.lost += 1
            return []
        copies = 2 if u_dup < p.duplicate else 1
        n.duplicated += copies - 1
        out = []
        for _ in range(copies):
            u_delay, u_reorder, u_extra, u_corrupt, u_bit = (rng.random() for _ in range(5))
            if p.delay == "exp":
                delay = int(-p.delay_us * math.log1p(-u_delay))
            else:
                delay = p.delay_us - p.jitter_us + int(u_delay * (2 * p.jitter_us + 1))
            if u_reorder < p.reorder:
                n.reordered += 1
                delay += 1 + int(u_extra * p.reorder_delay_us)
            if p.late_us and delay > p.late_us:
                n.late += 1
                continue
            payload = data
            if data and u_corrupt < p.corrupt:
                n.corrupted += 1
                bit = int(u_bit * len(data) * 8)
                flipped = bytearray(data)
                flipped[bit // 8] ^= 1 << (bit % 8)
                payload = bytes(flipped)
            out.append((delay, payload))
        return out
