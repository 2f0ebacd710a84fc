"""A client node: usable budget Uc, the last transaction it resolved, its return channel."""

from __future__ import annotations

from canergy.core.actions import Action, Persist
from canergy.core.common import ClientStep, spend
from canergy.core.errors import LocalProtocolError
from canergy.core.state import ClientState
from canergy.core.supervisor import check_amount
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
        return self._apply(self.rules.receive(self.timing, self.state, msg, now))

    def get_timer(self) -> int | None:
        deadlines = [d for d in (self.state.deadline, self.state.return_deadline) if d is not None]
        return min(deadlines) if deadlines else None

    def handle_timer(self, now: int) -> list[Action]:
        return self.fire_command_timer(now) + self.fire_return_timer(now)

    def fire_command_timer(self, now: int) -> list[Action]:
        return self._apply(self.rules.command_timer(self.timing, self.state, now))

    def fire_return_timer(self, now: int) -> list[Action]:
        return self._apply(self.rules.return_timer(self.timing, self.state, now))

    def spend(self, amount: int) -> list[Action]:
        """The actuator used ``amount`` µJ; refused beyond the usable budget."""
        if amount <= 0 or amount > self.state.usable:
            raise LocalProtocolError(f"cannot spend {amount} µJ of {self.state.usable} µJ")
        return self._apply((spend(self.state, amount), ()))

    def give_back(self, amount: int, now: int) -> list[Action]:
        """Return ``amount`` µJ of unused energy to the supervisor."""
        check_amount(amount)
        if amount > self.state.usable:
            raise LocalProtocolError(f"cannot return {amount} µJ of {self.state.usable} µJ")
        if not self.rules.can_give_back(self.state):
            raise LocalProtocolError("a return is still waiting for its acknowledgement")
        return self._apply(self.rules.give_back(self.timing, self.state, amount, now))

    def can_give_back(self) -> bool:
        return self.rules.can_give_back(self.state)

    def power_loss(self, now: int) -> None:
        """Lose volatile state and restart from the non-volatile record."""
        self.state = self.rules.power_loss(self.state, now)

    def _apply(self, step: ClientStep) -> list[Action]:
        new, actions = step
        old, self.state = self.state, new
        if self.rules.persistent(old) != self.rules.persistent(new):
            return [Persist(), *actions]
        return list(actions)


__all__ = ["Client"]
