"""A gateway: a client upstream and a supervisor downstream, with one persistent record.

Energy crosses between the two roles only through two pure rules, and only inside the step that
causes it, so the one ``Persist`` of that step covers both records:

* ``forward``: whatever the upstream client holds usable (a commit, a write-off's pay-back) is
  moved at once into the downstream usable budget: the client counts it as spent, the downstream
  supervisor as injected. Nothing is forwarded before the upstream commit.
* ``withdraw_for_return``: energy the downstream supervisor holds usable is taken out of it
  (counted as withdrawn) and returned upstream as the client's next numbered RETURN.

So ``up.spent == down.injected - down.withdrawn`` always holds (``link_gap`` is 0): the gateway
neither creates nor loses energy between its roles, and the tree's ledger is the sum of its
levels' ledgers.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from canergy.core.actions import Action, Persist
from canergy.core.client import Client
from canergy.core.errors import LocalProtocolError
from canergy.core.state import ClientState, SupervisorState
from canergy.core.supervisor import Supervisor, inject_into, withdraw_from
from canergy.core.timing import Timing
from canergy.core.variants import Variant
from canergy.frozen import evolve
from canergy.messages import ToClient


@dataclass(frozen=True, slots=True)
class GatewayState:
    """Both roles' records; the gateway persists them as one."""

    up: ClientState
    down: SupervisorState


def forward(up: ClientState, down: SupervisorState) -> tuple[ClientState, SupervisorState]:
    """Move all of the upstream usable budget into the downstream one (pure)."""
    amount = up.usable
    if amount <= 0:
        return up, down
    return evolve(up, usable=0, spent=up.spent + amount), inject_into(down, amount)


def withdraw_for_return(
    up: ClientState, down: SupervisorState, amount: int
) -> tuple[ClientState, SupervisorState]:
    """Take ``amount`` out of the downstream usable budget back into the upstream client's, to
    be returned upstream in the same step (pure)."""
    down = withdraw_from(down, amount)
    return evolve(up, usable=up.usable + amount, spent=up.spent - amount), down


def link_gap(up: ClientState, down: SupervisorState) -> int:
    """Energy created between the two roles (0 for every gateway that follows the rules)."""
    return down.injected - down.withdrawn - up.spent


class Gateway:
    """Node ``node`` of the bus above, supervisor of ``nodes`` on the bus below."""

    def __init__(
        self,
        node: int,
        nodes: Iterable[int],
        *,
        variant: str | Variant = "hardened",
        up_timing: Timing | None = None,
        down_timing: Timing | None = None,
        state: GatewayState | None = None,
    ) -> None:
        self.up = Client(node, variant=variant, timing=up_timing, state=state.up if state else None)
        self.down = Supervisor(
            nodes, 0, variant=variant, timing=down_timing, state=state.down if state else None
        )

    @property
    def state(self) -> GatewayState:
        return GatewayState(self.up.state, self.down.state)

    # -- upstream: the gateway as a client ---------------------------------------------------
    def receive_upstream(self, msg: ToClient, now: int) -> list[Action]:
        """A message of the supervisor above; what it credits goes downstream at once."""
        return self._forwarded(self.up.receive(msg, now))

    def handle_upstream_timer(self, now: int) -> list[Action]:
        return self.fire_command_timer(now) + self.fire_return_timer(now)

    def fire_command_timer(self, now: int) -> list[Action]:
        """No command came for the held intention: the timeout-commit is forwarded too."""
        return self._forwarded(self.up.fire_command_timer(now))

    def fire_return_timer(self, now: int) -> list[Action]:
        return self.up.fire_return_timer(now)

    def books_lost(self, nonce: int, now: int) -> list[Action]:
        """No valid upstream record: JOIN the supervisor above and wait for ADMIT; the
        downstream books are not touched."""
        return self.up.books_lost(nonce, now)

    def can_give_back(self) -> bool:
        return self.up.can_give_back()

    def give_back(self, amount: int, now: int) -> list[Action]:
        """Return ``amount`` µJ of the downstream usable budget upstream (numbered RETURN)."""
        if not self.up.can_give_back():
            raise LocalProtocolError("a return upstream is still waiting for its acknowledgement")
        if amount > self.down.state.usable:
            raise LocalProtocolError(
                f"cannot return {amount} µJ: {self.down.state.usable} µJ usable downstream"
            )
        before = self.state
        up, down = withdraw_for_return(self.up.state, self.down.state, amount)
        self.up.state, self.down.state = up, down
        try:
            actions = self.up.give_back(amount, now)
        except LocalProtocolError:
            self.up.state, self.down.state = before.up, before.down
            raise
        return _persist_first(actions)

    def power_loss(self, now: int) -> None:
        """Both roles restart from the one record."""
        self.up.power_loss(now)
        self.down.power_loss(now)

    # -- both --------------------------------------------------------------------------------
    def get_timer(self) -> int | None:
        timers = [t for t in (self.up.get_timer(), self.down.get_timer()) if t is not None]
        return min(timers) if timers else None

    def _forwarded(self, actions: list[Action]) -> list[Action]:
        if self.up.state.usable <= 0:
            return actions
        self.up.state, self.down.state = forward(self.up.state, self.down.state)
        return _persist_first(actions)


def _persist_first(actions: list[Action]) -> list[Action]:
    return actions if actions[:1] == [Persist()] else [Persist(), *actions]


__all__ = ["Gateway", "GatewayState", "forward", "link_gap", "withdraw_for_return"]
