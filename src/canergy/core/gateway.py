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

The downstream role is any ``GatewayDown`` (``core.supervisor.SupervisorCore`` with ``withdraw``
and the ``hold`` below): ``Below`` here, or the compiled one (``canergy.ccore.supervisor.
CompiledBelow``, for ``canergy gateway --core c``), made by the ``below`` factory from the same
record. The gateway moves energy across only through ``inject`` and ``withdraw``, so either core
books it alike.

Under the witnessed rules upstream (``up_variant="witnessed"``) forwarding is the gateway's spend,
witnessed as a node's draw is: what the client is credited leaves its budget as a numbered DRAW,
persisted before it is sent, and goes below only on the supervisor's acknowledgement (the
client's ``spent`` moves then, and ``injected`` below in the same step). Every start of the
gateway is a RESUME the supervisor above confirms; until it has (``upstream_waiting``) nothing is
forwarded, returned or granted below. A record found behind (an older copy: the supervisor above
holds a debit it lacks) drops its upstream books as a node does, and its downstream Us too
(``dropped``): that Us may hold what the gateway returned upstream after the copy was taken. The
drop is booked as a withdrawal below that leaves ``spent`` above, so the link holds and the
energy counts as lost by the gateway's client role.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

from canergy.core.actions import Action, Persist
from canergy.core.client import Client
from canergy.core.errors import LocalProtocolError
from canergy.core.state import ClientState, Phase, SupervisorState
from canergy.core.supervisor import (
    Supervisor,
    SupervisorCore,
    inject_into,
    unconfirmed,
    withdraw_from,
)
from canergy.core.table import ClientTable
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.frozen import evolve
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, ToClient

STARTING = (Phase.RESUMING, Phase.SYNCING)
"""Upstream phases of a start the supervisor above has not confirmed yet (witnessed rules)."""


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


def may_give_back(rules: ClientTable, state: GatewayState) -> bool:
    """``Gateway.can_give_back`` of a state (``rules``: the client role's table)."""
    return bool(rules.can_give_back(state.up)) and not unconfirmed(state.down)


def link_gap(up: ClientState, down: SupervisorState) -> int:
    """Energy created between the two roles (0 for every gateway that follows the rules)."""
    return down.injected - down.withdrawn - up.spent


def found_behind(before: ClientState, after: ClientState) -> bool:
    """The step from ``before`` to ``after`` was the supervisor above finding the record behind
    (witnessed: a start answered with a debit number above the record's next one)."""
    return (
        before.phase in STARTING
        and after.phase is Phase.IDLE
        and after.return_seq > before.return_seq + 1
    )


def no_hold() -> str | None:
    """``GatewayDown.hold`` of a role that never waits (None: grants may go)."""
    return None


class GatewayDown(SupervisorCore, Protocol):
    """What the gateway needs of its supervisor role, beside what the service drives: energy
    taken out to above and the hold it sets on grants (the nodes a start waits for:
    ``SupervisorCore.unconfirmed``)."""

    hold: Callable[[], str | None]
    """Why no grant may begin below (None: it may); set by the gateway."""

    def withdraw(self, amount: int) -> None:
        """Take ``amount`` µJ out of Us to outside (counted as withdrawn)."""
        ...


class MakeDown(Protocol):
    """Makes a gateway's supervisor role (``Below`` takes these arguments)."""

    def __call__(
        self,
        nodes: Iterable[int],
        initial: int,
        *,
        variant: str | Variant,
        timing: Timing | None,
        state: SupervisorState | None,
        start_without: Iterable[int],
    ) -> GatewayDown: ...


class Below(Supervisor):
    """The gateway's supervisor role: it grants nothing while ``hold`` says why not (the
    gateway's own start, not yet confirmed above)."""

    hold: Callable[[], str | None] = staticmethod(no_hold)

    def begin(self, node: int, amount: int, now: int) -> list[Action]:
        if (why := self.hold()) is not None:
            raise LocalProtocolError(why)
        return super().begin(node, amount, now)


class Gateway:
    """Node ``node`` of the bus above, supervisor of ``nodes`` on the bus below. ``variant``:
    the rules of both legs, unless ``up_variant`` names the upstream leg's."""

    def __init__(
        self,
        node: int,
        nodes: Iterable[int],
        *,
        variant: str | Variant = "hardened",
        up_variant: str | Variant | None = None,
        up_timing: Timing | None = None,
        down_timing: Timing | None = None,
        state: GatewayState | None = None,
        start_without: Iterable[int] = (),
        below: MakeDown | None = None,
    ) -> None:
        """``start_without``: nodes below a start does not wait for (``Supervisor``'s, with
        its risk; a return upstream may then carry what such a node holds). ``below``: makes
        the supervisor role (default ``Below``, the Python core)."""
        above = variant if up_variant is None else up_variant
        above = get_variant(above) if isinstance(above, str) else above
        self.up = Client(node, variant=above, timing=up_timing, state=state.up if state else None)
        make: MakeDown = Below if below is None else below
        self.down: GatewayDown = make(
            nodes,
            0,
            variant=variant,
            timing=down_timing,
            state=state.down if state else None,
            start_without=start_without,
        )
        self.down.hold = self.upstream_waiting
        self.draws = above.name == "witnessed"
        """Forwarding is a witnessed DRAW (the witnessed rules upstream)."""
        self.dropped = 0
        """µJ of downstream Us dropped by starts found behind above (this run)."""
        self.behind = 0
        """Starts found behind above (this run)."""

    @property
    def state(self) -> GatewayState:
        return GatewayState(self.up.state, self.down.state)

    # -- upstream: the gateway as a client ---------------------------------------------------
    def receive_upstream(self, msg: ToClient, now: int) -> list[Action]:
        """A message of the supervisor above; what it credits goes downstream at once (under the
        witnessed rules: drawn at once, and below on the draw's acknowledgement)."""
        before = self.up.state
        return self._forwarded(before, self.up.receive(msg, now), now)

    def handle_upstream_timer(self, now: int) -> list[Action]:
        return self.fire_command_timer(now) + self.fire_return_timer(now)

    def fire_command_timer(self, now: int) -> list[Action]:
        """No command came for the held intention: the timeout-commit is forwarded too."""
        before = self.up.state
        return self._forwarded(before, self.up.fire_command_timer(now), now)

    def fire_return_timer(self, now: int) -> list[Action]:
        return self.up.fire_return_timer(now)

    def upstream_waiting(self) -> str | None:
        """Why the gateway neither forwards nor grants below (None: it does): its start is not
        confirmed by the supervisor above yet (witnessed rules upstream)."""
        phase = self.up.state.phase
        if phase is Phase.RESUMING:
            return (
                "started from the state file: RESUME sent upstream; no grant below until the "
                "supervisor above confirms this gateway's record (it may be an older copy)"
            )
        if phase is Phase.SYNCING:
            return (
                "the supervisor above started (SYNC): books and counts sent upstream; no grant "
                "below until it confirms them"
            )
        return None

    def books_lost(self, nonce: int, now: int) -> list[Action]:
        """No valid upstream record: JOIN the supervisor above and wait for ADMIT; the
        downstream books are not touched."""
        return self.up.books_lost(nonce, now)

    def can_give_back(self) -> bool:
        """A RETURN upstream may go: the client role can number one, and no start below waits
        for a node's books (witnessed rules below: Us may be an older copy's, holding what
        nodes were granted since; returned, it would be counted twice)."""
        return self.up.can_give_back() and not self.down.unconfirmed()

    def give_back(self, amount: int, now: int) -> list[Action]:
        """Return ``amount`` µJ of the downstream usable budget upstream (numbered RETURN)."""
        waiting = self.down.unconfirmed()
        if waiting:
            raise LocalProtocolError(
                "no return upstream before every node below has confirmed its books after this "
                f"start: waiting for node(s) {', '.join(map(str, waiting))}"
            )
        if not self.up.can_give_back():
            raise LocalProtocolError("a return upstream is still waiting for its acknowledgement")
        if amount > self.down.state.usable:
            raise LocalProtocolError(
                f"cannot return {amount} µJ: {self.down.state.usable} µJ usable downstream"
            )
        if amount <= 0:
            raise LocalProtocolError(f"cannot withdraw {amount} µJ of {self.down.usable} µJ usable")
        before = self.up.state  # ``withdraw_for_return``: the client's half first, then below
        self.up.state = evolve(before, usable=before.usable + amount, spent=before.spent - amount)
        try:
            actions = self.up.give_back(amount, now)
        except LocalProtocolError:
            self.up.state = before
            raise
        self.down.withdraw(amount)
        return _persist_first(actions)

    def power_loss(self, now: int, nonce: int | None = None, sync_nonce: int = 0) -> list[Action]:
        """Both roles restart from the one record. ``nonce``: a fresh random 16-bit number for
        the upstream start (witnessed: RESUME is sent, returned here); ``sync_nonce``: the
        downstream start's (witnessed below: SYNC)."""
        actions = self.up.power_loss(now, nonce if self.draws else None)
        self.down.power_loss(now, sync_nonce)
        return actions

    # -- both --------------------------------------------------------------------------------
    def get_timer(self) -> int | None:
        timers = [t for t in (self.up.get_timer(), self.down.get_timer()) if t is not None]
        return min(timers) if timers else None

    def _forwarded(self, before: ClientState, actions: list[Action], now: int) -> list[Action]:
        if self.draws:
            return self._drawn(before, actions, now)
        up = self.up.state
        if up.usable <= 0:
            return actions
        self.up.state = evolve(up, usable=0, spent=up.spent + up.usable)  # ``forward``
        self.down.inject(up.usable)
        return _persist_first(actions)

    def _drawn(self, before: ClientState, actions: list[Action], now: int) -> list[Action]:
        """Witnessed upstream: a released draw goes below; a start found behind drops the Us
        below (what is owed there stays); what the client holds usable is drawn (one debit at a
        time, at most one frame's amount)."""
        up = self.up.state
        moved = False
        released = up.spent - before.spent  # a draw acknowledged (a start found behind keeps it)
        if released > 0:
            self.down.inject(released)
            moved = True
        if found_behind(before, up):
            self.behind += 1
            dropped = min(max(self.down.usable, 0), up.spent)
            if dropped:  # out of Us below and back out of spent above: lost at the gateway
                self.dropped += dropped
                self.down.withdraw(dropped)
                self.up.state = up = evolve(up, spent=up.spent - dropped)
                moved = True
        if moved:
            actions = _persist_first(actions)
        chunk = min(up.usable // QUANTUM_UJ, AMOUNT_MAX_MJ) * QUANTUM_UJ
        if chunk and self.up.can_spend():
            actions = _persist_first([*actions, *self.up.spend(chunk, now)])
        return actions


def _persist_first(actions: list[Action]) -> list[Action]:
    return actions if actions[:1] == [Persist()] else [Persist(), *actions]


__all__ = [
    "Below",
    "Gateway",
    "GatewayDown",
    "GatewayState",
    "MakeDown",
    "forward",
    "found_behind",
    "link_gap",
    "withdraw_for_return",
]
