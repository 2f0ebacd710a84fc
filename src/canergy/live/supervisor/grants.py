"""The grant desk: how much a node gets now, one-shot requests and the top-up policy, under the
safety limits and the rate limiter.

It decides amounts and answers requests; the service decides whether a node may be granted at
all (its session idle, its books in, no JOIN held...) and begins the transaction with the core.
Sans-IO: times in µs from the caller.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from canergy.live.supervisor.policy import (
    Limits,
    RateLimiter,
    TopUp,
    capped_grant,
    grant_caps,
)
from canergy.messages import USABLE_MAX_UJ
from canergy.units import format_energy

GrantCallback = Callable[[dict[str, Any]], None]


@dataclass(slots=True)
class GrantRequest:
    node: int
    amount: int
    reply: GrantCallback


@dataclass(frozen=True, slots=True)
class Books:
    """What the books say when a grant is sized: the usable budget and, when ``max_total``
    limits it, what was granted since the start."""

    usable: int
    granted_total: int


class GrantCaps(Protocol):
    """The grant caps as a table (``policy``'s functions, or their twin in C:
    ``canergy.ccore.grants.CompiledGrantCaps``): the rate limiter's tokens, the cap on one
    grant, what the top-up policy wants."""

    def available(self, now: int) -> int | None: ...

    def take(self, amount: int) -> None: ...

    def cap(
        self, wanted: int, level: int | None, usable: int, granted_total: int, tokens: int | None
    ) -> int: ...

    def wanted(self, level: int) -> int: ...


class PythonGrantCaps:
    """``GrantCaps`` in Python: ``RateLimiter``, ``capped_grant``, ``TopUp.wanted``."""

    implementation = "python"

    def __init__(self, limits: Limits, policy: TopUp | None) -> None:
        self.limits = limits
        self.policy = policy
        self.rate = RateLimiter(limits.rate_uj_per_s, limits.max_grant)

    def available(self, now: int) -> int | None:
        return self.rate.available(now)

    def take(self, amount: int) -> None:
        self.rate.take(amount)

    def cap(
        self, wanted: int, level: int | None, usable: int, granted_total: int, tokens: int | None
    ) -> int:
        return capped_grant(
            wanted,
            limits=self.limits,
            level=level,
            usable=usable,
            granted_total=granted_total,
            rate_tokens=tokens,
        )

    def wanted(self, level: int) -> int:
        assert self.policy is not None
        return self.policy.wanted(level)


class GrantDesk:
    """Sizes grants: ``one_shot`` for a queued request, ``top_up`` for the policy; ``took``
    once a transaction began (the rate limiter's tokens). ``caps``: the table that sizes them
    (default Python's; the compiled core's service hands its twin in C)."""

    def __init__(self, limits: Limits, policy: TopUp | None, caps: GrantCaps | None = None) -> None:
        self.limits = limits
        self.policy = policy
        self.caps: GrantCaps = PythonGrantCaps(limits, policy) if caps is None else caps

    def one_shot(
        self, req: GrantRequest, name: int | str, level: int | None, books: Books, now: int
    ) -> int | None:
        """The amount to begin for ``req``, or None: refused (``req`` has been answered)."""
        if level is not None and level + req.amount > USABLE_MAX_UJ:
            req.reply(
                {
                    "node": name,
                    "error": f"refused: node {name} reports {format_energy(level)}; "
                    f"{format_energy(req.amount)} more would lift it above "
                    f"{format_energy(USABLE_MAX_UJ)}, the most its record holds",
                }
            )
            return None
        amount = self.cap(req.amount, level, books, now)
        if amount != req.amount:
            allowed = f"{format_energy(amount)} allowed" if amount else "nothing allowed"
            why = "; ".join(self.limiting(req.amount, level, books, now))
            req.reply({"node": name, "error": f"refused by limits or budget ({allowed}: {why})"})
            return None
        return amount

    def top_up(self, level: int, books: Books, now: int) -> int:
        """What the policy wants for a node at ``level``, capped (0: nothing)."""
        assert self.policy is not None
        return self.cap(self.caps.wanted(level), level, books, now)

    def took(self, amount: int) -> None:
        self.caps.take(amount)

    def cap(self, wanted: int, level: int | None, books: Books, now: int) -> int:
        tokens = self.caps.available(now)
        return self.caps.cap(wanted, level, books.usable, books.granted_total, tokens)

    def limiting(self, wanted: int, level: int | None, books: Books, now: int) -> list[str]:
        """What keeps a grant below ``wanted``, one phrase each."""
        return [why for cap, why in grant_caps(**self._caps(level, books, now)) if cap < wanted]

    def _caps(self, level: int | None, books: Books, now: int) -> dict[str, Any]:
        return {
            "limits": self.limits,
            "level": level,
            "usable": books.usable,
            "granted_total": books.granted_total,
            "rate_tokens": self.caps.available(now),
        }
