"""Channel models for the simulator: per-frame delay, Bernoulli or Gilbert–Elliott loss,
duplication, reordering and bit corruption (corrupted frames still go through the real codec).

Every (node, direction) pair has its own random stream, so two strategies that send the k-th
frame of a pair meet the same fate for it: the channel realisation is shared as far as the
strategies send alike.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field, replace


@dataclass(frozen=True, slots=True)
class ChannelModel:
    """Probabilities per frame; delays in µs, uniform in ``[delay_us - jitter_us, + jitter_us]``
    or exponential with mean ``delay_us`` (``delay="exp"``)."""

    delay_us: int = 1_000
    jitter_us: int = 0
    delay: str = "uniform"
    loss: float = 0.0
    burst_enter: float = 0.0
    """Gilbert–Elliott: probability per frame of moving from the good to the bad state."""
    burst_leave: float = 0.3
    burst_loss: float = 1.0
    """Loss probability while in the bad state (``loss`` applies in the good one)."""
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_extra_us: int = 500_000
    corrupt: float = 0.0
    sample_us: int = 0
    """Receivers look at their queue this often (0: at once, event driven)."""
    timeout_us: int = 10_000
    """Response timeout that suits this channel (a round trip: two legs, two queue samples)."""
    late_us: int = 0
    """A frame delayed beyond this times out in the channel and never arrives (0: no limit)."""

    def __post_init__(self) -> None:
        for name in (
            "loss",
            "burst_enter",
            "burst_leave",
            "burst_loss",
            "duplicate",
            "reorder",
            "corrupt",
        ):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} {p} outside 0..1")
        if min(self.delay_us, self.jitter_us, self.reorder_extra_us, self.sample_us) < 0:
            raise ValueError("times must be >= 0")
        if self.timeout_us <= 0 or self.late_us < 0:
            raise ValueError("timeout must be > 0")
        if self.jitter_us > self.delay_us and self.delay == "uniform":
            raise ValueError("jitter larger than the delay would need negative delays")
        if self.delay not in ("uniform", "exp"):
            raise ValueError(f"unknown delay distribution {self.delay!r} (uniform, exp)")


PRESETS: dict[str, ChannelModel] = {
    # Section IV: 1 s +- 0.5 s per message, queues sampled once per second, timeouts of 1 s per
    # message: a frame later than 1 s times out (half of them), one on time is answered within
    # the 3 s round trip of two legs and the client's sample.
    "paper": ChannelModel(
        delay_us=1_000_000,
        jitter_us=500_000,
        sample_us=1_000_000,
        timeout_us=3_000_000,
        late_us=1_000_000,
    ),
    "ideal": ChannelModel(delay_us=200, jitter_us=100),
    "lossy": ChannelModel(delay_us=2_000, jitter_us=1_000, loss=0.1),
    "bursty": ChannelModel(delay_us=2_000, jitter_us=1_000, burst_enter=0.05, burst_leave=0.3),
    "harsh": ChannelModel(
        delay_us=2_000, jitter_us=1_000, loss=0.2, duplicate=0.1, reorder=0.1, corrupt=0.02
    ),
}


def channel(preset: str, **overrides: object) -> ChannelModel:
    """A preset with some fields replaced (``None`` values are ignored)."""
    try:
        base = PRESETS[preset]
    except KeyError:
        raise ValueError(f"unknown channel {preset!r} (one of {', '.join(PRESETS)})") from None
    return replace(base, **{k: v for k, v in overrides.items() if v is not None})  # type: ignore[arg-type]


@dataclass(slots=True)
class ChannelCounters:
    frames: int = 0
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    late: int = 0


@dataclass(slots=True)
class Link:
    """One direction of one node's traffic: its own random stream and burst state."""

    model: ChannelModel
    rng: random.Random
    counters: ChannelCounters
    bad: bool = False

    def fate(self, data: bytes) -> list[tuple[int, bytes]]:
        """``(delay_us, payload)`` for each copy that arrives; empty when the frame is lost."""
        m, rng, n = self.model, self.rng, self.counters
        n.frames += 1
        # fixed number of draws per frame keeps streams aligned across strategies
        u_loss, u_burst, u_dup = rng.random(), rng.random(), rng.random()
        if m.burst_enter:
            self.bad = u_burst >= m.burst_leave if self.bad else u_burst < m.burst_enter
        if u_loss < (m.burst_loss if self.bad else m.loss):
            n.lost += 1
            return []
        copies = 2 if u_dup < m.duplicate else 1
        n.duplicated += copies - 1
        out = []
        for _ in range(copies):
            u_delay, u_reorder, u_extra, u_corrupt, u_bit = (rng.random() for _ in range(5))
            if m.delay == "exp":
                delay = int(-m.delay_us * math.log1p(-u_delay))
            else:
                delay = m.delay_us - m.jitter_us + int(u_delay * (2 * m.jitter_us + 1))
            if u_reorder < m.reorder:
                n.reordered += 1
                delay += 1 + int(u_extra * m.reorder_extra_us)
            if m.late_us and delay > m.late_us:
                n.late += 1
                continue
            payload = data
            if data and u_corrupt < m.corrupt:
                n.corrupted += 1
                bit = int(u_bit * len(data) * 8)
                flipped = bytearray(data)
                flipped[bit // 8] ^= 1 << (bit % 8)
                payload = bytes(flipped)
            out.append((delay, payload))
        return out


@dataclass(slots=True)
class Channel:
    """All links of one run, created on first use from one seed."""

    model: ChannelModel
    seed: int
    counters: ChannelCounters = field(default_factory=ChannelCounters)
    _links: dict[tuple[int, int], Link] = field(default_factory=dict)

    def link(self, node: int, to_client: bool) -> Link:
        key = (node, int(to_client))
        link = self._links.get(key)
        if link is None:
            rng = random.Random(f"{self.seed}/channel/{node}/{key[1]}")
            link = self._links[key] = Link(self.model, rng, self.counters)
        return link
