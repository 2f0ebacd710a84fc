"""Closing the books of a test run, naming the first node (or the supervisor) that created energy.

``canergy ledger``'s sum, split by who holds what: the supervisor's own identity (usable +
reserved + delivered − returned = initial + injected − withdrawn) and, per node, what the
supervisor gave it net (delivered − returned) against what the node holds (usable + spent +
its return in flight − the overlap with a reservation). The terms add up to the ledger's
``dissipated``; a negative one is energy created there.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from canergy.ledger import (
    ledger_from_status,
    node_overlap,
    node_return_in_flight,
    node_usable,
    states_from_status,
    supervisor_usable,
)
from canergy.units import format_energy


@dataclass(frozen=True, slots=True)
class Term:
    """One party's share of the books: ``given`` to it, ``held`` by it, ``parts`` of ``held``."""

    who: str
    given: int
    held: int
    parts: tuple[tuple[str, int], ...]

    @property
    def dissipated(self) -> int:
        return self.given - self.held

    def describe(self) -> str:
        shown = " + ".join(f"{name} {format_energy(v)}" for name, v in self.parts if v)
        return (
            f"{self.who} created {format_energy(-self.dissipated)}: it holds "
            f"{format_energy(self.held)} ({shown or 'nothing'}) of {format_energy(self.given)} "
            "it was given"
        )


def terms(supervisor: dict[str, Any], clients: Iterable[dict[str, Any]]) -> list[Term]:
    """The supervisor's term, then each node's (one bus; plain node ids)."""
    sup, states, _ = states_from_status(supervisor, list(clients))
    returned = [int(v["returns_credited_uj"]) for v in supervisor["nodes"].values()]
    by_node = {c.node: c for c in states}
    delivered = sum(s.delivered for s in sup.sessions) - sum(returned)
    reserved = sum(s.reserved for s in sup.sessions)
    usable = supervisor_usable(sup)
    out = [
        Term(
            "the supervisor",
            sup.initial + sup.injected - sup.withdrawn,
            usable + reserved + delivered,
            (("usable", usable), ("reserved", reserved), ("given to nodes net", delivered)),
        )
    ]
    for s, back in zip(sup.sessions, returned, strict=True):
        c = by_node[s.node]
        parts = (
            ("usable", node_usable(c)),
            ("spent", c.spent),
            ("return in flight", node_return_in_flight(s, c)),
            ("overlap with a reservation", -node_overlap(s, c)),
        )
        out.append(Term(f"node {s.node}", s.delivered - back, sum(v for _, v in parts), parts))
    return out


def creation(supervisor: dict[str, Any], clients: Iterable[dict[str, Any]]) -> str | None:
    """None when the books close (nothing created); otherwise what was created and where: the
    whole run's figure, then the first party (supervisor, then nodes by id) that created it."""
    clients = list(clients)
    books = ledger_from_status(supervisor, clients)
    if books.passive:
        return None
    culprits = [t for t in terms(supervisor, clients) if t.dissipated < 0]
    where = culprits[0].describe() if culprits else "no single party (the terms disagree)"
    return f"the books do not close: {format_energy(-books.dissipated)} created; {where}"
