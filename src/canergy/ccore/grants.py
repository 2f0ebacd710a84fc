"""The compiled core's grant caps: ``canergy.live.supervisor.grants.GrantCaps`` over
firmware/src/grants.c (the twin of ``policy.capped_grant``, ``RateLimiter`` and
``TopUp.wanted``), its rate limiter's state in C memory."""

from __future__ import annotations

from typing import Any

from canergy.live.supervisor.policy import Limits, TopUp

BOUND = 2**40
"""Limits the C caps take (µJ, µJ/s): larger ones are sized by Python's (``fits``)."""


def fits(limits: Limits, policy: TopUp | None) -> bool:
    """Whether the C caps take these settings exactly (64-bit arithmetic throughout)."""
    values = [limits.max_grant, limits.max_node_level, limits.max_total, limits.rate_uj_per_s]
    if policy is not None:
        values += [policy.target, policy.minimum]
    return all(v is None or 0 <= v < BOUND for v in values)


class CompiledGrantCaps:
    """``GrantCaps`` in C (``CompiledSupervisor.grant_caps``)."""

    implementation = "c"

    def __init__(self, module: Any, limits: Limits, policy: TopUp | None) -> None:
        if not fits(limits, policy):
            raise ValueError(f"the C grant caps take limits below {BOUND}")
        ffi, lib = module.ffi, module.lib
        self._lib = lib
        self.policy = policy
        self.limits = c = ffi.new("struct canergy_grant_limits *")
        c.max_grant_uj = limits.max_grant
        c.has_max_node_level = limits.max_node_level is not None
        c.max_node_level_uj = limits.max_node_level or 0
        c.has_max_total = limits.max_total is not None
        c.max_total_uj = limits.max_total or 0
        c.has_rate = limits.rate_uj_per_s is not None
        c.rate_uj_per_s = limits.rate_uj_per_s or 0
        self.rate = ffi.new("struct canergy_grant_rate *")
        lib.canergy_grant_rate_init(self.rate, c)
        self._tokens = ffi.new("int64_t *")

    def available(self, now: int) -> int | None:
        if not self._lib.canergy_grant_rate_available(self.rate, self.limits, now, self._tokens):
            return None
        return int(self._tokens[0])

    def take(self, amount: int) -> None:
        self._lib.canergy_grant_rate_take(self.rate, self.limits, amount)

    def cap(
        self, wanted: int, level: int | None, usable: int, granted_total: int, tokens: int | None
    ) -> int:
        """``capped_grant``'s (``wanted`` beyond ``BOUND`` is capped lower by the limits)."""
        bounded = max(-BOUND, min(wanted, BOUND))
        has_level, has_tokens = level is not None, tokens is not None
        return int(
            self._lib.canergy_grant_cap(
                self.limits, bounded, has_level, level or 0, usable, granted_total, has_tokens,
                tokens or 0,
            )
        )  # fmt: skip

    def wanted(self, level: int) -> int:
        assert self.policy is not None
        return int(self._lib.canergy_grant_wanted(self.policy.target, self.policy.minimum, level))
