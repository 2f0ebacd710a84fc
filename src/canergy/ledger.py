"""The observer's conservation ledger over one supervisor and its clients.

    initial + injected = Us + ΣTs + Σ(Uc + spent) + returns in flight − overlap + dissipated

``overlap`` counts the travelling energy once: per node, the part of the client's credited
count Rc beyond the supervisor's delivered count Gs, capped at Ts (what the client has committed
while the supervisor still holds it reserved). The system is passive while ``dissipated >= 0``.

A node that lost its NV record no longer knows its Rc nor what its actuator spent. An observer
that saw the loss passes what the record held (``lost``): the energy spent stays spent, and
energy the node received before the loss is still counted once until the supervisor writes the
open reservation off. What the node still held is what the loss dissipated.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

from canergy.core.state import ClientState, Session, SupervisorState


@dataclass(frozen=True, slots=True)
class Ledger:
    initial: int
    injected: int
    supervisor_usable: int
    supervisor_reserved: int
    clients_usable: int
    spent: int
    returns_in_flight: int
    overlap: int

    @property
    def held(self) -> int:
        """Energy the system holds, travelling energy counted once."""
        return (
            self.supervisor_usable
            + self.supervisor_reserved
            + self.clients_usable
            + self.spent
            + self.returns_in_flight
            - self.overlap
        )

    @property
    def dissipated(self) -> int:
        """Energy lost so far; negative means energy was generated."""
        return self.initial + self.injected - self.held

    @property
    def passive(self) -> bool:
        return self.dissipated >= 0

    def as_json(self) -> dict[str, int]:
        """Integer microjoule terms under the ``*_uj`` keys the CLI prints."""
        terms = {f"{k}_uj": v for k, v in asdict(self).items()}
        terms["dissipated_uj"] = self.dissipated
        return terms


class LostRecord(NamedTuple):
    """What an observer saw in a node's records before they were lost (spent: all of them)."""

    credited: int
    spent: int


NOT_LOST = LostRecord(0, 0)


def node_overlap(s: Session, c: ClientState, lost: LostRecord = NOT_LOST) -> int:
    return min(s.reserved, max(0, max(c.credited, lost.credited) - s.delivered))


def node_return_in_flight(s: Session, c: ClientState) -> int:
    return c.return_pending if c.return_seq > s.returns_credited else 0


def ledger(
    sup: SupervisorState, clients: Iterable[ClientState], lost: Mapping[int, LostRecord] = {}
) -> Ledger:
    """Compute the ledger; ``clients`` must hold one state per supervised node; ``lost`` maps a
    node that lost its record to what the record held."""
    by_node = {c.node: c for c in clients}
    if set(by_node) != {s.node for s in sup.sessions}:
        raise ValueError("the ledger needs exactly one client state per supervised node")
    pairs = [(s, by_node[s.node]) for s in sup.sessions]
    return Ledger(
        initial=sup.initial,
        injected=sup.injected,
        supervisor_usable=sup.usable,
        supervisor_reserved=sum(s.reserved for s, _ in pairs),
        clients_usable=sum(c.usable for _, c in pairs),
        spent=sum(c.spent for _, c in pairs) + sum(r.spent for r in lost.values()),
        returns_in_flight=sum(node_return_in_flight(s, c) for s, c in pairs),
        overlap=sum(node_overlap(s, c, lost.get(s.node, NOT_LOST)) for s, c in pairs),
    )


def ledger_from_status(supervisor: dict[str, Any], clients: Iterable[dict[str, Any]]) -> Ledger:
    """The ledger from the JSON status files of a supervisor and its client emulators (or real
    nodes reporting the same keys), as the processes last wrote them. The proxies of guarded
    CiA 402 drives are in the supervisor's own status and count as clients."""
    guarded = supervisor.get("cia402", {}).get("drives", {}).values()
    sessions = tuple(
        Session(
            int(node),
            reserved=v["reserved_uj"],
            delivered=v["delivered_uj"],
            returns_credited=v["returns_credited"],
        )
        for node, v in supervisor["nodes"].items()
    )
    sup = SupervisorState(
        supervisor["initial_uj"], supervisor["usable_uj"], supervisor["injected_uj"], sessions
    )
    states = [
        ClientState(
            c["node"],
            usable=c["usable_uj"],
            credited=c["credited_uj"],
            spent=c["spent_uj"],
            return_seq=c["return_seq"],
            return_pending=c["return_pending_uj"],
        )
        for c in (*clients, *guarded)
    ]
    return ledger(sup, states)
