"""A hand-driven channel between one supervisor and its clients, for scripted scenarios.

Messages in flight are kept per direction in send order; a scenario delivers, drops or duplicates
them by index, fires timers, spends, returns and resets, then reads the ledger.
"""

from __future__ import annotations

from canergy.core import Acknowledged, Action, Client, Phase, Send, Supervisor, Timing
from canergy.ledger import Ledger, ledger
from canergy.messages import Direction, Message, ToClient, ToSupervisor

J = 1_000_000


class Harness:
    def __init__(self, variant: str, nodes: tuple[int, ...] = (1,), initial: int = 10 * J) -> None:
        self.timing = Timing()
        self.sup = Supervisor(nodes, initial, variant=variant, timing=self.timing)
        self.clients = {n: Client(n, variant=variant, timing=self.timing) for n in nodes}
        self.to_client: list[ToClient] = []
        self.to_sup: list[ToSupervisor] = []
        self.acked: list[Acknowledged] = []
        self.notes: list[Action] = []
        self.now = 0

    # -- bookkeeping -------------------------------------------------------------------
    def _take(self, actions: list[Action]) -> list[Action]:
        for a in actions:
            if isinstance(a, Send):
                msg: Message = a.message
                if msg.TYPE.direction is Direction.TO_CLIENT:
                    self.to_client.append(msg)  # type: ignore[arg-type]
                else:
                    self.to_sup.append(msg)  # type: ignore[arg-type]
            else:
                self.notes.append(a)
                if isinstance(a, Acknowledged):
                    self.acked.append(a)
        return actions

    @property
    def ledger(self) -> Ledger:
        return ledger(self.sup.state, [c.state for c in self.clients.values()])

    def client(self, node: int = 1) -> Client:
        return self.clients[node]

    # -- supervisor side ---------------------------------------------------------------
    def begin(self, amount: int, node: int = 1) -> None:
        self._take(self.sup.begin(node, amount, self.now))

    def commit(self, node: int = 1) -> None:
        self._take(self.sup.commit(node, self.now))

    def abort(self, node: int = 1) -> None:
        self._take(self.sup.abort(node, self.now))

    def sup_timer(self, node: int = 1) -> None:
        deadline = self.sup.session(node).deadline
        assert deadline is not None, "supervisor timer not armed"
        self.now = max(self.now, deadline)
        self._take(self.sup.fire_timer(node, self.now))

    def sup_reset(self) -> None:
        self.sup.power_loss(self.now)

    # -- client side -------------------------------------------------------------------
    def client_timer(self, node: int = 1) -> bool:
        """Fire the client's command timer if armed; False when nothing was armed."""
        deadline = self.clients[node].state.deadline
        if deadline is None:
            return False
        self.now = max(self.now, deadline)
        self._take(self.clients[node].fire_command_timer(self.now))
        return True

    def spend(self, amount: int | None = None, node: int = 1) -> None:
        c = self.clients[node]
        self._take(c.spend(c.state.usable if amount is None else amount))

    def give_back(self, amount: int, node: int = 1) -> None:
        self._take(self.clients[node].give_back(amount, self.now))

    def client_reset(self, node: int = 1) -> None:
        self.clients[node].power_loss(self.now)

    # -- channel -----------------------------------------------------------------------
    def deliver_to_client(self, index: int = 0) -> None:
        msg = self.to_client.pop(index)
        self._take(self.clients[msg.node].receive(msg, self.now))

    def deliver_to_sup(self, index: int = 0) -> None:
        self._take(self.sup.receive(self.to_sup.pop(index), self.now))

    def duplicate_to_client(self, index: int = 0) -> None:
        self.to_client.insert(index, self.to_client[index])

    def duplicate_to_sup(self, index: int = 0) -> None:
        self.to_sup.insert(index, self.to_sup[index])

    def drop_to_sup(self) -> None:
        self.to_sup.clear()

    def drop_to_client(self) -> None:
        self.to_client.clear()

    def settle(self, commit: bool = True, limit: int = 100) -> None:
        """Deliver everything in flight, oldest first, deciding each ACK, until quiet."""
        for _ in range(limit):
            if self.acked:
                a = self.acked.pop(0)
                if self.sup.session(a.node).phase is Phase.ACKED:
                    (self.commit if commit else self.abort)(a.node)
            elif self.to_sup:
                self.deliver_to_sup()
            elif self.to_client:
                self.deliver_to_client()
            else:
                return
        raise AssertionError("scenario did not settle")
