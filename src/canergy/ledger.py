"""The observer's conservation ledger over one supervisor and its clients.

    initial + injected − withdrawn
        = Us + ΣTs + Σ(Uc + spent) + returns in flight − overlap + dissipated

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
from dataclasses import asdict, dataclass, replace
from typing import Any, NamedTuple

from canergy.bus_keys import session_key
from canergy.core.state import SYNC_PHASES, ClientState, Phase, Session, SupervisorState


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
    withdrawn: int = 0
    """Energy a gateway's supervisor handed back upstream (out of this level)."""
    drive_debt: int = 0
    """Energy guarded CiA 402 drives were charged past their budgets and no grant has paid
    yet: spent as surely as ``spent``, so it counts against what the system holds."""

    @property
    def held(self) -> int:
        """Energy the system holds, travelling energy counted once (spent on credit too)."""
        return (
            self.supervisor_usable
            + self.supervisor_reserved
            + self.clients_usable
            + self.spent
            + self.drive_debt
            + self.returns_in_flight
            - self.overlap
        )

    @property
    def dissipated(self) -> int:
        """Energy lost so far; negative means energy was generated."""
        return self.initial + self.injected - self.withdrawn - self.held

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
    """The pending return not yet credited (a pending draw goes to nobody: it is not counted),
    none while the node's session waits for its books in a start (witnessed rules: the start
    voids it, as it leaves Us out meanwhile: ``supervisor_usable``)."""
    if c.pending_draw or c.return_seq <= s.returns_credited:
        return 0
    return 0 if start_waits(s) else c.return_pending


def start_waits(s: Session) -> bool:
    """Whether the session waits for its node's books in a supervisor's start (witnessed rules;
    a re-sync of one node is no start: nothing restored, grants to others go on)."""
    return s.phase in SYNC_PHASES and not s.resync


def node_usable(c: ClientState) -> int:
    """What the node can use: nothing while its supervisor has not confirmed its books
    (witnessed rules, RESUMING, or SYNCING: answering a supervisor's start); they count from the
    moment they are confirmed."""
    return 0 if c.phase in (Phase.RESUMING, Phase.SYNCING) else c.usable


def supervisor_usable(sup: SupervisorState) -> int:
    """Us, but none of it while a start waits for a node's books (witnessed rules: the books
    may be an older copy's, and grant nothing meanwhile): it counts from the moment every node
    has confirmed them. A debt (Us below zero) always counts, and so does Us while a node is
    only re-synced (``Session.resync``: nothing restored, grants to others go on)."""
    if any(start_waits(s) for s in sup.sessions):
        return min(sup.usable, 0)
    return sup.usable


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
        supervisor_usable=supervisor_usable(sup),
        supervisor_reserved=sum(s.reserved for s, _ in pairs),
        clients_usable=sum(node_usable(c) for _, c in pairs),
        spent=sum(c.spent for _, c in pairs) + sum(r.spent for r in lost.values()),
        returns_in_flight=sum(node_return_in_flight(s, c) for s, c in pairs),
        overlap=sum(node_overlap(s, c, lost.get(s.node, NOT_LOST)) for s, c in pairs),
        withdrawn=sup.withdrawn,
    )


def ledger_from_status(
    supervisor: dict[str, Any],
    clients: Iterable[dict[str, Any]] | Mapping[str, Iterable[dict[str, Any]]],
) -> Ledger:
    """The ledger from the JSON status files of a supervisor and its client emulators (or real
    nodes reporting the same keys), as the processes last wrote them. The proxies of guarded
    CiA 402 drives and of guarded devices of other profiles (ODrive axes) are in the supervisor's
    own status and count as clients.

    A supervisor over several buses names its nodes ``bus/node``: ``clients`` then maps each
    bus name to the statuses of the clients on that bus (whose ``node`` is their plain id)."""
    sup, states, debt = states_from_status(supervisor, clients)
    books = ledger(sup, states)
    return replace(books, drive_debt=debt) if debt else books


def states_from_status(
    supervisor: dict[str, Any],
    clients: Iterable[dict[str, Any]] | Mapping[str, Iterable[dict[str, Any]]],
) -> tuple[SupervisorState, list[ClientState], int]:
    """The supervisor's and the clients' states in ``ledger_from_status``'s status files, and
    the guarded drives' and devices' unpaid debt."""
    guarded_status = supervisor.get("cia402", {})
    guarded = [
        *guarded_status.get("drives", {}).values(),
        *(d for profile in guarded_status.get("devices", {}).values() for d in profile.values()),
    ]
    buses = list(dict.fromkeys(name.rpartition("/")[0] for name in supervisor["nodes"]))
    if buses == [""]:  # one bus: nodes are plain ids
        buses = []
    if bool(buses) != isinstance(clients, Mapping):
        raise ValueError(
            "give the clients per bus name exactly when the supervisor names its nodes bus/node"
        )

    def key(bus: str, node: int) -> int:
        if bus not in buses:
            raise ValueError(f"no bus named {bus!r} in the supervisor's status")
        return session_key(buses.index(bus), node)

    sessions = tuple(
        Session(
            key(*_split(name)) if buses else int(name),
            reserved=v["reserved_uj"],
            delivered=v["delivered_uj"],
            returns_credited=v["returns_credited"],
        )
        for name, v in supervisor["nodes"].items()
    )
    sup = SupervisorState(
        supervisor["initial_uj"],
        supervisor["usable_uj"],
        supervisor["injected_uj"],
        sessions,
        supervisor.get("withdrawn_uj", 0),
    )
    if isinstance(clients, Mapping):
        keyed = [(key(bus, c["node"]), c) for bus, cs in clients.items() for c in cs]
    else:
        keyed = [(c["node"], c) for c in (*clients, *guarded)]
    states = [
        ClientState(
            node,
            usable=c["usable_uj"],
            credited=c["credited_uj"],
            spent=c["spent_uj"],
            return_seq=c["return_seq"],
            return_pending=c["return_pending_uj"],
        )
        for node, c in keyed
    ]
    return sup, states, sum(int(d.get("debt_uj", 0)) for d in guarded)


def _split(name: str) -> tuple[str, int]:
    """``bus/node`` as (bus, node)."""
    bus, _, node = name.rpartition("/")
    return bus, int(node)


@dataclass(frozen=True, slots=True)
class TreeLedger:
    """The ledgers of every level of a tree of supervisors and gateways.

    Each level is one bus (a supervisor, or a gateway's downstream side, and its clients); a
    gateway is a client of the level above, its spent count being what it injected below net of
    what it withdrew. ``link_gaps`` is, per gateway, energy created between its two roles
    (always 0 under the gateway rules). The tree is passive when no level and no gateway created
    energy; ``dissipated`` is the whole tree's loss.
    """

    levels: Mapping[str, Ledger]
    link_gaps: Mapping[str, int]

    @property
    def dissipated(self) -> int:
        levels = sum(led.dissipated for led in self.levels.values())
        return levels - sum(self.link_gaps.values())

    @property
    def passive(self) -> bool:
        return all(led.passive for led in self.levels.values()) and all(
            gap <= 0 for gap in self.link_gaps.values()
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "passive": self.passive,
            "dissipated_uj": self.dissipated,
            "levels": {name: led.as_json() for name, led in self.levels.items()},
            "link_gaps_uj": dict(self.link_gaps),
        }
