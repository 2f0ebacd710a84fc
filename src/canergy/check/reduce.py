"""Two sound reductions of the explored state space; neither hides a violation or lengthens one.

**Symmetry.** Clients run the same rules and differ only in their node id, so a world and the
same world with node ids permuted (sessions, clients and frames alike) have mirror-image futures.
Only one representative of each class is stored: the one with nodes sorted by what they hold.

**Subsumption.** The run counters (transactions started, frames lost and duplicated, power
losses, timer expiries, forgeries, replays and re-syncs) are budgets: a world that has used less
of every budget can do everything the same world with more used can do, and so can one whose
replayer has seen more frames. A world is skipped when the same protocol state has been stored
with every counter lower or equal and every frame it has seen seen too. Breadth-first order
stores the cheaper one no later than at the same depth, so counterexamples stay shortest.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, TypeVar, cast

from canergy.check.model import Flight, Step, World
from canergy.core.state import ClientState, Session
from canergy.frozen import evolve
from canergy.ledger import LostRecord
from canergy.messages import Message

T = TypeVar("T")
Counters = tuple[int, int, int, int, int, int, int, int, int, int, int]
Perm = tuple[int, ...]


def counters(w: World) -> Counters:
    return (
        w.started,
        w.lost,
        w.duplicated,
        w.power_lost,
        w.timed_out,
        w.nv_lost,
        w.old_copied,
        w.forged,
        w.replayed,
        w.sup_old_copied,
        w.resynced,
    )


def _cheaper(
    a: tuple[Counters, frozenset[Message]], b: tuple[Counters, frozenset[Message]]
) -> bool:
    """``a`` can do all ``b`` can: no counter higher, every frame ``b`` can replay seen."""
    return a[1] >= b[1] and all(x <= y for x, y in zip(a[0], b[0], strict=True))


_RENAMED: dict[tuple[object, int], Any] = {}


def _renamed(obj: T, node: int) -> T:
    """``obj`` with its node id replaced; memoized (worlds share few distinct records)."""
    key = (obj, node)
    out = _RENAMED.get(key)
    if out is None:
        out = _RENAMED[key] = evolve(obj, node=node)
    return cast(T, out)


def relabel(w: World, perm: Perm) -> World:
    """``w`` with node ``i + 1`` renamed ``perm[i] + 1`` everywhere."""
    k = len(perm)
    sessions = [w.sup.sessions[0]] * k
    clients = [w.clients[0]] * k
    for i, j in enumerate(perm):
        sessions[j] = _renamed(w.sup.sessions[i], j + 1)
        clients[j] = _renamed(w.clients[i], j + 1)
    older = list(w.older)
    for i, j in enumerate(perm if w.older else ()):
        older[j] = _renamed(w.older[i], j + 1)
    flight: Flight = frozenset((_renamed(msg, perm[msg.node - 1] + 1), n) for msg, n in w.flight)
    return evolve(
        w,
        sup=evolve(w.sup, sessions=tuple(sessions)),
        clients=tuple(clients),
        flight=flight,
        older=tuple(older),
        lost_records=tuple(sorted((perm[n - 1] + 1, r) for n, r in w.lost_records)),
        seen=frozenset(_renamed(msg, perm[msg.node - 1] + 1) for msg in w.seen),
    )


def relabel_step(step: Step, perm: Perm) -> Step:
    node = perm[step.node - 1] + 1 if step.node else 0
    msg = step.message
    if msg is not None:
        msg = evolve(msg, node=perm[msg.node - 1] + 1)
    return evolve(step, node=node, message=msg)


def _plain(value: object) -> object:
    return -1 if value is None else value


_SIGNATURES: dict[object, tuple[object, ...]] = {}


def _signature(obj: object) -> tuple[object, ...]:
    """Everything in a record but its node id, as a comparable tuple; memoized."""
    sig = _SIGNATURES.get(obj)
    if sig is None:
        names = obj.__slots__  # type: ignore[attr-defined]
        values = (_plain(getattr(obj, n)) for n in names if n != "node")
        sig = _SIGNATURES[obj] = (type(obj).__name__, *values)
    return sig


NodeKey = tuple[object, ...]
Signature = tuple[object, ...]


def signature(obj: object) -> Signature:
    """Everything in a record but its node id (``_signature``)."""
    return _signature(obj)


def frames_key(frames: Iterable[tuple[Message, int]]) -> list[tuple[Signature, int]]:
    return sorted((_signature(msg), n) for msg, n in frames)


def seen_key(seen: Iterable[Message]) -> list[Signature]:
    return sorted(_signature(msg) for msg in seen)


def node_key(
    session: Session,
    client: ClientState,
    frames: Iterable[tuple[Message, int]],
    older: ClientState | None,
    ghost: LostRecord | None,
    seen: Iterable[Message],
) -> NodeKey:
    """What one node holds, its id left out: its session, client record, frames to or from it,
    its older record and lost record (when kept) and the frames seen for it."""
    older_sig = None if older is None else _signature(older)
    return compose_key(
        _signature(session),
        _signature(client),
        frames_key(frames),
        older_sig,
        ghost,
        seen_key(seen),
    )


def compose_key(
    session: Signature,
    client: Signature,
    frames: list[tuple[Signature, int]],
    older: Signature | None,
    ghost: LostRecord | None,
    seen: list[Signature],
) -> NodeKey:
    """``node_key`` from the signatures and keys of its parts."""
    return (
        session,
        client,
        frames,
        () if older is None else older,
        () if ghost is None else ghost,
        seen,
    )


def sorting_perm(w: World) -> Perm:
    """The relabeling that orders nodes by what they hold (``node_key``). Nodes with equal
    contents are interchangeable, so the result is canonical."""
    lost = dict(w.lost_records)
    keys = [
        node_key(
            session,
            client,
            (item for item in w.flight if item[0].node == client.node),
            w.older[client.node - 1] if w.older else None,
            lost.get(client.node),
            (msg for msg in w.seen if msg.node == client.node),
        )
        for session, client in zip(w.sup.sessions, w.clients, strict=True)
    ]
    order = sorted(range(len(keys)), key=keys.__getitem__)
    perm = [0] * len(order)
    for new, old in enumerate(order):
        perm[old] = new
    return tuple(perm)


def inverse(perm: Perm) -> Perm:
    out = [0] * len(perm)
    for i, j in enumerate(perm):
        out[j] = i
    return tuple(out)


class Reducer:
    """Decides which generated worlds to store, and in which canonical form."""

    def __init__(self, clients: int, *, symmetry: bool = True, subsumption: bool = True) -> None:
        _RENAMED.clear()  # memo tables live as long as one exploration
        _SIGNATURES.clear()
        self.symmetry = symmetry and clients > 1
        self.subsumption = subsumption
        self._stored: dict[World, list[tuple[Counters, frozenset[Message]]]] = {}
        self.subsumed = 0

    def perm(self, w: World) -> Perm:
        """The relabeling that makes ``w`` canonical (identity without symmetry)."""
        return sorting_perm(w) if self.symmetry else tuple(range(len(w.clients)))

    def canonical(self, w: World) -> World:
        perm = self.perm(w)
        return w if perm == tuple(range(len(perm))) else relabel(w, perm)

    def admit(self, w: World) -> bool:
        """Store ``w`` (canonical) unless its protocol state is stored with cheaper counters."""
        if not self.subsumption:
            return True
        core = evolve(
            w,
            started=0,
            lost=0,
            duplicated=0,
            power_lost=0,
            timed_out=0,
            nv_lost=0,
            old_copied=0,
            sup_old_copied=0,
            resynced=0,
            forged=0,
            replayed=0,
            seen=frozenset(),
        )
        mine = (counters(w), w.seen)
        stored = self._stored.get(core)
        if stored is None:
            self._stored[core] = [mine]
            return True
        if any(_cheaper(other, mine) for other in stored):
            self.subsumed += 1
            return False
        stored[:] = [o for o in stored if not _cheaper(mine, o)]
        stored.append(mine)
        return True
