"""Grant policy (how much a node should get now) and safety limits (how much it may get).

The policy reads the nodes' telemetry, which is information only: a wrong level can make the
supervisor grant less or more, but never more than the limits and its own usable budget allow,
and the protocol stays passive whatever telemetry says.
"""

from __future__ import annotations

from dataclasses import dataclass

from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, USABLE_MAX_UJ, quantize
from canergy.units import format_energy


def level_room(max_grant: int) -> int:
    """The highest level a node may be planned to: what its record holds (``USABLE_MAX_UJ``)
    less one grant of ``max_grant`` that a write-off could pay back on top of it."""
    return USABLE_MAX_UJ - max_grant


@dataclass(frozen=True, slots=True)
class Limits:
    """Safety limits; energies in µJ, ``rate_uj_per_s`` sustained over all nodes."""

    max_grant: int = AMOUNT_MAX_MJ * QUANTUM_UJ
    max_node_level: int | None = None
    """A grant may not lift a node's last reported level above this."""
    max_total: int | None = None
    """Energy granted (committed) over this run, all nodes together."""
    rate_uj_per_s: int | None = None
    """Token bucket refilled at this rate, holding at most one second's worth or one grant."""

    def __post_init__(self) -> None:
        if not QUANTUM_UJ <= self.max_grant <= AMOUNT_MAX_MJ * QUANTUM_UJ:
            largest = AMOUNT_MAX_MJ * QUANTUM_UJ
            raise ValueError(
                f"max grant must be {format_energy(QUANTUM_UJ)} to {format_energy(largest)}"
            )
        for name in ("max_node_level", "max_total", "rate_uj_per_s"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ValueError(f"{name} must be >= 0")
        room = level_room(self.max_grant)
        if self.max_node_level is not None and self.max_node_level > room:
            raise ValueError(
                f"max node level must be at most {format_energy(room)} "
                f"({format_energy(USABLE_MAX_UJ)}, what a node's record holds, less a max grant)"
            )


class RateLimiter:
    """Token bucket in µJ over monotonic µs."""

    def __init__(self, rate_uj_per_s: int | None, burst: int) -> None:
        self.rate = rate_uj_per_s
        self.burst = max(burst, rate_uj_per_s or 0)
        self.tokens = self.burst
        self.stamp: int | None = None

    def available(self, now: int) -> int | None:
        if self.rate is None:
            return None
        if self.stamp is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate // 1_000_000)
        self.stamp = now
        return self.tokens

    def take(self, amount: int) -> None:
        if self.rate is not None:
            self.tokens -= amount


_Cap = tuple[int, str, tuple[int, ...]]
"""A cap on one grant: its value, and what it is as a template for the energies that follow
(formatted only when a refusal names it: a top-up on every frame formats nothing)."""


def _caps(
    limits: Limits, level: int | None, usable: int, granted_total: int, rate_tokens: int | None
) -> list[_Cap]:
    """Every cap on one grant now."""
    caps: list[_Cap] = [
        (usable, "the supervisor has {} left", (usable,)),
        (limits.max_grant, "--max-grant {}", (limits.max_grant,)),
        (AMOUNT_MAX_MJ * QUANTUM_UJ, "one transaction carries at most 65.535 J", ()),
    ]
    if level is not None:
        caps.append((USABLE_MAX_UJ - level, "the node's record holds no more", ()))
    if (most := limits.max_node_level) is not None:
        caps.append((0 if level is None else most - level, "--max-node-level {}", (most,)))
    if (total := limits.max_total) is not None:
        left = total - granted_total
        caps.append((left, "--max-total {} ({} left)", (total, max(left, 0))))
    if (tokens := rate_tokens) is not None:
        caps.append((tokens, "--rate ({} available now)", (max(tokens, 0),)))
    return caps


def grant_caps(
    *,
    limits: Limits,
    level: int | None,
    usable: int,
    granted_total: int,
    rate_tokens: int | None,
) -> list[tuple[int, str]]:
    """Every cap on one grant now, with what it is in a phrase. A node is never lifted above
    what its record holds (``USABLE_MAX_UJ``) from a level it reported; an unknown level fails
    ``--max-node-level`` closed."""
    caps = _caps(limits, level, usable, granted_total, rate_tokens)
    return [(cap, why.format(*map(format_energy, uj))) for cap, why, uj in caps]


def capped_grant(
    wanted: int,
    *,
    limits: Limits,
    level: int | None,
    usable: int,
    granted_total: int,
    rate_tokens: int | None,
) -> int:
    """The largest grant ≤ ``wanted`` every cap of ``grant_caps`` allows (0: none), in whole
    quanta."""
    caps = _caps(limits, level, usable, granted_total, rate_tokens)
    return max(0, quantize(min([wanted, *(cap for cap, _, _ in caps)])))


@dataclass(frozen=True, slots=True)
class TopUp:
    """Keep each node's reported level at ``target``: grant the shortfall, at least ``minimum``
    (small top-ups cost frames and write cycles for little energy)."""

    target: int
    minimum: int = QUANTUM_UJ

    def wanted(self, level: int) -> int:
        short = self.target - level
        return short if short >= self.minimum else 0
