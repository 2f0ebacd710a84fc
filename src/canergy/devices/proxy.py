"""The proxy half of every guard (CiA 402 drives and the device profiles alike). Sans-IO.

A guarded device never runs canergy: the host keeps a hardened ``Client`` in its name, which the
supervisor grants to like any node, and spends from it what the guard's meter says the device
may have drawn. What the budget does not cover becomes **debt** (``debt_uj``, all of it counted
in ``overrun_uj``), paid first from the next grant; the proxy never spends more than it holds.
Its record is volatile: a host that starts has no books for it, so it JOINs and the supervisor
writes off what an earlier life held.

A guard subclasses ``ProxyBooks`` and says when it is running (``running``, for the HALTED flag)
and where it stops (``threshold_uj``, for the LOW flag); the rest of its rules are its own.
"""

from __future__ import annotations

from typing import Any

from canergy.core import Action, Client, ClientCommitted, Credited, Send, Timing
from canergy.core.state import Phase
from canergy.messages import LEVEL_MAX_MJ, QUANTUM_UJ, Message, Telemetry, quantize

NO_BUDGET = "no budget yet"
"""A guard's stop reason before its device was first released."""
EXHAUSTED = "budget exhausted"
HELD = "held: "
"""The start of the stop reason of a device whose budget does not reach where it would stop."""


class ProxyBooks:
    """A guard's proxy client, its debt and its TELEMETRY."""

    def __init__(
        self, node: int, timing: Timing, telemetry_period_us: int, now: int, nonce: int
    ) -> None:
        self.client = Client(node, timing=timing)
        self.telemetry_period_us = telemetry_period_us
        self.overrun_uj = 0
        self.debt_uj = 0
        self.next_telemetry = now
        self.outbox = self._carry_out(self.client.books_lost(nonce, now), now)
        """Frames to the supervisor not sent yet (the JOIN of a proxy without books)."""

    @property
    def node(self) -> int:
        return self.client.node

    @property
    def usable(self) -> int:
        return self.client.state.usable

    @property
    def joining(self) -> bool:
        return self.client.state.phase is Phase.JOINING

    def running(self) -> bool:
        """The device may draw (TELEMETRY without HALTED)."""
        raise NotImplementedError

    def threshold_uj(self) -> int:
        """Where the guard stops the device (TELEMETRY's LOW at or below it)."""
        raise NotImplementedError

    def release_uj(self) -> int:
        """The level its guard releases a device stopped for its budget above: the stop
        threshold, and the resume margin of a guard that has one."""
        return self.threshold_uj()

    def telemetry(self, now: int) -> Telemetry:
        self.next_telemetry = now + self.telemetry_period_us
        flags = (
            (Telemetry.LOW if self.usable <= self.threshold_uj() else 0)
            | (0 if self.running() else Telemetry.HALTED)
            | (Telemetry.JOINING if self.joining else 0)
        )
        return Telemetry(self.node, min(self.usable // QUANTUM_UJ, LEVEL_MAX_MJ), flags)

    def _carry_out(self, actions: list[Action], now: int) -> list[Message]:
        out: list[Message] = []
        for action in actions:
            if isinstance(action, Send):
                out.append(action.message)
            elif isinstance(action, ClientCommitted | Credited):
                self.next_telemetry = now  # report the new level at the next wakeup
        return out

    def _spend_drawn(self, drawn: int, now: int) -> list[Message]:
        """Spend what was drawn; what the budget does not cover becomes debt."""
        take = min(drawn, self.usable)
        self.overrun_uj += drawn - take
        self.debt_uj += drawn - take
        return self._carry_out(self.client.spend(take, now), now) if take else []

    def _pay_debt(self, now: int) -> list[Message]:
        """New budget pays the debt first."""
        pay = min(self.debt_uj, self.usable)
        if not pay:
            return []
        self.debt_uj -= pay
        return self._carry_out(self.client.spend(pay, now), now)

    def held_back(self, reason: str | None, why: str | None) -> str | None:
        """The stop reason of a device not released since it was set up (``reason``) while the
        guard's rules say nothing but the budget keeps it (``why``: None, or "budget
        exhausted"): while its proxy holds budget, what it holds against what it needs (where
        the guard stops: the bound at its limits, with the reaction and latency it measured,
        and the reserve), so the status and the supervisor's report say why, not "no budget
        yet". Any other reason is returned as it is."""
        if reason != NO_BUDGET and not (reason or "").startswith(HELD):
            return reason
        if why not in (None, EXHAUSTED):
            return reason
        if self.usable <= 0:
            return NO_BUDGET
        return (
            f"{HELD}{self.usable / 1e6:.3f} J in hand, {self.threshold_uj() / 1e6:.3f} J needed "
            "to stop within the bound (raise the supervisor's --target and --max-grant, or lower "
            "the limits)"
        )

    def parked(self, reason: str | None, target: int, minimum: int) -> str | None:
        """The stop reason of a device its guard stopped for its budget (``reason`` "budget
        exhausted") under a supervisor whose top-up keeps a node's level at ``target`` with
        grants of at least ``minimum`` (``--target``, ``--min-grant``), when that top-up can
        never lift what the proxy holds above where the guard stops: the budget is not
        exhausted but held, with what it holds against what it needs and what to raise. None
        otherwise (the supervisor tops it up and the guard releases it, or it stopped for
        another reason). TELEMETRY's LOW says the same to the supervisor, whose top-up does not
        read it: it sees the level at its target."""
        if reason != EXHAUSTED or self.usable <= 0:
            return None
        level = min(self.usable, LEVEL_MAX_MJ * QUANTUM_UJ)
        level = quantize(level)  # as TELEMETRY reports it
        short = target - level
        grant = quantize(short) if short >= minimum else 0
        topped = self.usable + grant
        needed, release = self.threshold_uj(), self.release_uj()
        if topped > release:
            return None
        return (
            f"{HELD}{self.usable / 1e6:.3f} J in hand, {needed / 1e6:.3f} J needed to stop within "
            f"the bound; the supervisor tops up to --target {target / 1e6:.3f} J only (raise "
            f"--target above {release / 1e6:.3f} J, or lower the limits)"
        )

    def _proxy_due(self, now: int) -> list[Message]:
        """What the proxy sends at a wakeup: the outbox, and its timer's frames when due."""
        out, self.outbox = self.outbox, []
        if (timer := self.client.get_timer()) is not None and timer <= now:
            out += self._carry_out(self.client.handle_timer(now), now)
        return out

    def _proxy_wakeups(self) -> list[int]:
        """The proxy's deadlines: its next TELEMETRY and its client's timer."""
        timer = self.client.get_timer()
        return [self.next_telemetry] if timer is None else [self.next_telemetry, timer]

    def books_status(self) -> dict[str, Any]:
        """The proxy's books, as every guard's status shows them."""
        c = self.client.state
        return {
            "usable_uj": c.usable,
            "spent_uj": c.spent,
            "credited_uj": c.credited,
            "return_seq": c.return_seq,
            "return_pending_uj": c.return_pending,
        }
