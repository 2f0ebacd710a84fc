"""Channel models for the simulator: ``canergy.faults`` plus queue sampling and a timeout, and
presets (corrupted frames still go through the real codec).

Every (node, direction) pair has its own random stream, so two strategies that send the k-th
frame of a pair meet the same fate for it: the channel realisation is shared as far as the
strategies send alike.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field, replace

from canergy.faults import FaultCounters, FaultInjector, FaultProfile


@dataclass(frozen=True, slots=True)
class ChannelModel(FaultProfile):
    """The fault model plus how receivers look at their queue and which timeout suits it."""

    delay_us: int = 1_000
    jitter_us: int = 0
    reorder_delay_us: int = 500_000
    sample_us: int = 0
    """Receivers look at their queue this often (0: at once, event driven)."""
    timeout_us: int = 10_000
    """Response timeout that suits this channel (a round trip: two legs, two queue samples)."""

    def __post_init__(self) -> None:
        FaultProfile.__post_init__(self)
        if self.sample_us < 0 or self.timeout_us <= 0:
            raise ValueError("sample time must be >= 0 and the timeout > 0")


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
class Channel:
    """All links of one run, created on first use from one seed."""

    model: ChannelModel
    seed: int
    counters: FaultCounters = field(default_factory=FaultCounters)
    _links: dict[tuple[int, int], FaultInjector] = field(default_factory=dict)

    def link(self, node: int, to_client: bool) -> FaultInjector:
        key = (node, int(to_client))
        link = self._links.get(key)
        if link is None:
            rng = random.Random(f"{self.seed}/channel/{node}/{key[1]}")
            link = self._links[key] = FaultInjector(self.model, rng, self.counters)
        return link
