"""A client node: usable budget Uc, the last transaction it resolved, its return channel."""

from __future__ import annotations

from canergy.core.actions import Action, Persist
from canergy.core.inputs import (
    COMMAND_TIMEOUT,
    POWER_LOSS,
    RETURN_TIMEOUT,
    BooksLost,
    GiveBack,
    PowerLoss,
    Spend,
)
from canergy.core.state import ClientState
from canergy.core.table import Event
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.messages import MAX_NODE, MIN_NODE, ToClient


class Client:
    """Receives budgets from the supervisor, spends them, and gives unused energy back."""

    def __init__(
        self,
        node: int,
        *,
        variant: str | Variant = "hardened",
        timing: Timing | None = None,
        state: ClientState | None = None,
    ) -> None:
        if not MIN_NODE <= node <= MAX_NODE:
            raise ValueError(f"node {node} outside {MIN_NODE}-{MAX_NODE}")
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        self.rules = self.variant.client
        self.timing = timing or Timing()
        self.node = node
        self.state = state or ClientState(node)

    def receive(self, msg: ToClient, now: int) -> list[Action]:
        """Feed a decoded supervisor message; messages for other nodes are ignored."""
        if msg.node != self.node:
            return []
        return self._step(msg, now)

    def get_timer(self) -> int | None:
        command, give_back = self.state.deadline, self.state.return_deadline
        if command is None or give_back is None:
            return give_back if command is None else command
        return min(command, give_back)

    def handle_timer(self, now: int) -> list[Action]:
        return self.fire_command_timer(now) + self.fire_return_timer(now)

    def fire_command_timer(self, now: int) -> list[Action]:
        return self._step(COMMAND_TIMEOUT, now)

    def fire_return_timer(self, now: int) -> list[Action]:
        return self._step(RETURN_TIMEOUT, now)

    def spend(self, amount: int, now: int = 0) -> list[Action]:
        """The actuator used (hardened) or asks for (witnessed: a DRAW, re-sent from ``now`` on
        until acknowledged) ``amount`` µJ; refused beyond the usable budget. ``now`` matters only
        where a re-send is timed: pass it (0 keeps the hardened callers that have no clock)."""
        return self._step(Spend(amount), now)

    def give_back(self, amount: int, now: int) -> list[Action]:
        """Return ``amount`` µJ of unused energy to the supervisor."""
        return self._step(GiveBack(amount), now)

    def can_give_back(self) -> bool:
        return self.rules.can_give_back(self.state)

    def can_spend(self) -> bool:
        """Whether the rules let the actuator spend now (witnessed: no debit waiting, books
        confirmed); the amount is the budget's to guard."""
        return self.rules.can_spend(self.state)

    def power_loss(self, now: int, nonce: int | None = None) -> list[Action]:
        """Lose volatile state and restart from the non-volatile record; ``nonce``: a fresh
        random 16-bit number for rules that confirm every start (witnessed: RESUME is sent)."""
        return self._step(POWER_LOSS if nonce is None else PowerLoss(nonce & 0xFFFF), now)

    def books_lost(self, nonce: int, now: int) -> list[Action]:
        """Started without a valid NV record; ``nonce``: a fresh random 16-bit number. The
        hardened rules JOIN and wait to be admitted; they never trust an old pay-back."""
        return self._step(BooksLost(nonce & 0xFFFF), now)

    def _step(self, event: Event, now: int) -> list[Action]:
        old = self.state
        self.state, actions = self.rules.step(self.timing, old, event, now)
        record = self.rules.persistent(self.state)
        if record and record != self.rules.persistent(old):  # (): no record to write
            return [Persist(), *actions]
        return list(actions)


__all__ = ["Client"]
