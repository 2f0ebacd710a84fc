"""How the compact engine packs a world into one int, and which budgets each step needs.

A world's code is ``usable | content of node 1 | ... | content of node K | run counters``: the
supervisor's usable budget on top (any size, even negative), one interned node content
(``nodes.NodeTable``) per ``NODE_BITS`` and the run counters, each in a field one bit wider than
its bound. The spare top bit of each counter field lets one subtraction compare every counter at
once (``cheaper``), which is how subsumption compares budgets.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from canergy.check.model import (
    OLD_COPY_NONCE,
    RESTART_NONCE,
    RESYNC_NONCE,
    UNIT,
    Bounds,
    Model,
    StepKind,
    World,
    initial_world,
)
from canergy.check.reduce import counters

if TYPE_CHECKING:
    from canergy.check.nodes import NodeTable

K = StepKind
NODE_BITS = 32
"""Bits per node content id: room for 4 billion distinct contents."""


class Layout:
    """The fields of a world's code under one set of bounds, for ``clients`` nodes."""

    def __init__(self, bounds: Bounds) -> None:
        limits = (
            bounds.transactions,
            bounds.losses,
            bounds.duplicates,
            bounds.power_losses,
            bounds.timeouts or 0,
            bounds.nv_losses,
            bounds.old_copies,
            bounds.forgeries,
            bounds.replays,
            bounds.supervisor_old_copies,
            bounds.resyncs,
        )
        self.offsets: list[int] = []
        self.widths: list[int] = []
        offset = 0
        for limit in limits:
            width = max(limit, 1).bit_length() + 1
            self.offsets.append(offset)
            self.widths.append(width)
            offset += width
        self.counter_bits = offset
        self.counter_mask = (1 << offset) - 1
        self.spare = sum(1 << (o + w - 1) for o, w in zip(self.offsets, self.widths, strict=True))
        """The top bit of every counter field (never set in a counter within its bound)."""
        self.clients = clients = bounds.clients
        self.node_mask = (1 << NODE_BITS) - 1
        self.nodes_bits = NODE_BITS * clients
        self.older_bits = NODE_BITS if bounds.supervisor_old_copies else 0
        """With the supervisor's old copies: the number of its state before its last write,
        between Us and the nodes (``Engine.older``)."""

    def charges(self, model: Model) -> dict[StepKind, int]:
        """What each kind of step adds to the packed counters (``Model.charge``; the channel
        counts its own losses and duplicates)."""
        zero = initial_world(model.bounds)
        charge = {kind: self.pack_counters(model.charge(zero, kind)) for kind in StepKind}
        charge[K.LOSE] += 1 << self.offsets[1]
        charge[K.DUPLICATE] += 1 << self.offsets[2]
        return charge

    def pack_counters(self, w: World) -> int:
        return sum(v << o for v, o in zip(counters(w), self.offsets, strict=True))

    def unpack_counters(self, packed: int) -> tuple[int, ...]:
        return tuple(
            packed >> o & ((1 << w) - 1) for o, w in zip(self.offsets, self.widths, strict=True)
        )

    def cheaper(self, a: int, b: int) -> bool:
        """Packed counters ``a`` no higher than ``b`` in any field."""
        return ((b | self.spare) - a) & self.spare == self.spare

    def pack(self, usable: int, nodes: list[int], packed_counters: int, older: int = 0) -> int:
        code = usable << self.older_bits | older
        for node in nodes:
            code = code << NODE_BITS | node
        return code << self.counter_bits | packed_counters

    def older(self, code: int) -> int:
        """The number of the supervisor's older state (0 when its old copies are off)."""
        return code >> (self.counter_bits + self.nodes_bits) & ((1 << self.older_bits) - 1)

    def unpack(self, code: int) -> tuple[int, list[int], int]:
        """(usable, node contents, packed counters)."""
        packed = code & self.counter_mask
        rest = code >> self.counter_bits
        nodes = [
            rest >> (NODE_BITS * (self.clients - 1 - p)) & self.node_mask
            for p in range(self.clients)
        ]
        return rest >> (self.nodes_bits + self.older_bits), nodes, packed


class Guards:
    """Each step needs a budget left (or a usable budget, or room in flight): ``of`` numbers the
    condition a step needs and ``table`` says which hold in a world. ``Model.steps`` states the
    same conditions; tests compare the two engines on every kind of bound."""

    always = 0

    def __init__(self, bounds: Bounds, layout: Layout) -> None:
        self.bounds = bounds
        self.layout = layout
        units = bounds.units
        # 0: always; 1..units: a BEGIN of that many units; then one per budget; then NV losses.
        lose, duplicate, timer, power, old_copy, forge, replay = range(units + 1, units + 8)
        self._nv = units + 7
        # then one per client restart nonce (the power loss or old copy it is the next one of)
        self._restart = self._nv + bounds.nv_losses + 1
        self._old_copy = self._restart + bounds.power_losses
        self.sup_copy = self._old_copy + bounds.old_copies
        # then one per re-sync nonce (the re-sync it is the next one of)
        self._resync = self.sup_copy + 1
        self.size = self._resync + bounds.resyncs
        self.power = power
        self._by_kind = {
            K.DECIDE: self.always,
            K.DELIVER: self.always,
            K.SPEND: self.always,
            K.GIVE_BACK: self.always,
            K.NV_BACKUP: self.always,
            K.LOSE: lose,
            K.DUPLICATE: duplicate,
            K.SUPERVISOR_TIMER: timer,
            K.COMMAND_TIMER: timer,
            K.RETURN_TIMER: timer,
            K.CLIENT_POWER_LOSS: power,
            K.SUPERVISOR_POWER_LOSS: power,
            K.NV_OLD_COPY: old_copy,
            K.FORGE: forge,
            K.REPLAY: replay,
        }
        self._tables: dict[tuple[int, int, bool, bool], tuple[bool, ...]] = {}

    def of(self, kind: StepKind, arg: int = 0) -> int:
        """The condition a step needs: a BEGIN of ``arg`` units, an NV loss with nonce ``arg``
        (that it is the next one drawn), any other kind its budget (or none)."""
        if kind is K.BEGIN:
            return arg
        if kind is K.NV_LOST:
            return self._nv + arg
        if kind is K.CLIENT_POWER_LOSS:
            return self._restart + arg - RESTART_NONCE - 1
        if kind is K.NV_OLD_COPY:
            return self._old_copy + arg - OLD_COPY_NONCE - 1
        if kind is K.RESYNC:
            return self._resync + arg - RESYNC_NONCE - 1
        return self._by_kind[kind]

    def table(
        self, packed: int, usable: int, room: bool, waiting: bool = False
    ) -> tuple[bool, ...]:
        """Which conditions hold with these counters, this usable budget, (``room``) fewer
        frames in flight than the bound and (``waiting``) a start waiting for a node's books
        (no BEGIN); memoized."""
        key = (packed, usable, room, waiting)
        table = self._tables.get(key)
        if table is None:
            b = self.bounds
            cap = min(max(usable // UNIT, 0), b.units)
            started, lost, dup, power, timed, nv, old, forged, replayed, sup_old, resynced = (
                self.layout.unpack_counters(packed)
            )
            k = self._by_kind
            ok = [False] * self.size
            ok[self.always] = True
            for units in range(1, b.units + 1):
                ok[units] = started < b.transactions and units <= cap and not waiting
            ok[k[K.LOSE]] = lost < b.losses
            ok[k[K.DUPLICATE]] = dup < b.duplicates and room
            ok[k[K.SUPERVISOR_TIMER]] = b.timeouts is None or timed < b.timeouts
            ok[k[K.SUPERVISOR_POWER_LOSS]] = power < b.power_losses
            ok[k[K.NV_OLD_COPY]] = old < b.old_copies
            ok[k[K.FORGE]] = forged < b.forgeries
            ok[k[K.REPLAY]] = replayed < b.replays
            for nonce in range(1, b.nv_losses + 1):
                ok[self._nv + nonce] = nv == nonce - 1
            for n in range(b.power_losses):
                ok[self._restart + n] = power == n
            for n in range(b.old_copies):
                ok[self._old_copy + n] = old == n
            ok[self.sup_copy] = sup_old < b.supervisor_old_copies
            for n in range(b.resyncs):
                ok[self._resync + n] = resynced == n
            table = self._tables[key] = tuple(ok)
        return table


class Budgets:
    """Subsumption (``reduce.Reducer.admit``) on codes: per protocol state — the code without
    its counters, and without the frames seen — the budgets it was stored with, none of them
    no larger than another (packed counters, with the seen frames' masks when replays are on)."""

    def __init__(self, layout: Layout, table: NodeTable) -> None:
        self.layout, self.table = layout, table
        self.subsumed = 0
        self._stored: dict[int, Any] = {}
        self._replays = table.bounds.replays > 0

    def admit(self, code: int) -> bool:
        """Store ``code`` unless its protocol state is stored with budgets no larger."""
        layout = self.layout
        if self._replays:
            return self._admit_seen(code)
        core, mine, spare = code >> layout.counter_bits, code & layout.counter_mask, layout.spare
        have = self._stored.get(core)
        if have is None:
            self._stored[core] = mine
            return True
        if type(have) is int:
            if ((mine | spare) - have) & spare == spare:  # have <= mine
                self.subsumed += 1
                return False
            if ((have | spare) - mine) & spare == spare:  # mine <= have: it replaces it
                self._stored[core] = mine
            else:
                self._stored[core] = [have, mine]
            return True
        return self._admit_among(have, mine, layout.cheaper)

    def _admit_among(self, have: list[Any], mine: Any, cheaper: Callable[[Any, Any], bool]) -> bool:
        if any(cheaper(other, mine) for other in have):
            self.subsumed += 1
            return False
        have[:] = [other for other in have if not cheaper(mine, other)]
        have.append(mine)
        return True

    def _admit_seen(self, code: int) -> bool:
        layout, table = self.layout, self.table
        usable, nodes, packed = layout.unpack(code)
        core = layout.pack(usable, [table.bare[c] for c in nodes], 0)
        mine = (packed, tuple(table.seen[c] for c in nodes))
        have = self._stored.setdefault(core, [])
        return self._admit_among(have, mine, self._cheaper_seen)

    def _cheaper_seen(self, a: tuple[int, tuple[int, ...]], b: tuple[int, tuple[int, ...]]) -> bool:
        """No counter higher, and every frame ``b`` has seen seen too."""
        return self.layout.cheaper(a[0], b[0]) and all(
            x & y == y for x, y in zip(a[1], b[1], strict=True)
        )
