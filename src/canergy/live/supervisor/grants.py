"""The grant desk: how much a node gets now, one-shot requests and the top-up policy, under the
safety limits and the rate limiter.

It decides amounts and answers requests; the service decides whether a node may be granted at
all (its session idle, its books in, no JOIN held...) and begins the transaction with the core.
Sans-IO: times in µs from the caller.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from canergy.live.supervisor.policy import Limits, RateLimiter, TopUp, capped_grant, grant_caps
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


class GrantDesk:
    """Sizes grants: ``one_shot`` for a queued request, ``top_up`` for the policy; ``took``
    once a transaction began (the rate limiter's tokens)."""

    def __init__(self, limits: Limits, policy: TopUp | None) -> None:
        self.limits = limits
        self.policy = policy
        self.rate = RateLimiter(limits.rate_uj_per_s, limits.max_grant)

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
        return self.cap(self.policy.wanted(level), level, books, now)

    def took(self, amount: int) -> None:
        self.rate.take(amount)

    def cap(self, wanted: int, level: int | None, books: Books, now: int) -> int:
        return capped_grant(wanted, **self._caps(level, books, now))

    def limiting(self, wanted: int, level: int | None, books: Books, now: int) -> list[str]:
        """What keeps a grant below ``wanted``, one phrase each."""
        return [why for cap, why in grant_caps(**self._caps(level, books, now)) if cap < wanted]

    def _caps(self, level: int | None, books: Books, now: int) -> dict[str, Any]:
        return {
            "limits": self.limits,
            "level": level,
            "usable": books.usable,
            "granted_total": books.granted_total,
            "rate_tokens": self.rate.available(now),
        }
