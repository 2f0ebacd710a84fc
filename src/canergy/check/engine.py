"""The compact engine: the reference breadth-first search over worlds packed into ints.

It stores what ``explore``'s reference search stores, in the same order: the same canonical
representatives (nodes sorted by ``reduce.node_key``), successors in ``Model.steps`` order and
the same subsumption. So states, transitions, depth, violations and the counterexample are the
reference's. What differs is the representation: a world is one int (``packed.Layout``), a
node's content a small int (``nodes``), and a node's moves are worked out once per content and
position rather than once per world. Counterexamples are decoded into ``World`` objects, their
steps recovered through ``Model.steps`` and ``Model.apply``.
"""

from __future__ import annotations

import gc
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field

from canergy.check.model import UNIT, Model, StepKind, World, initial_world, supervisor_nonce
from canergy.check.nodes import INVALID, Keyed, Move, NodeMoves, NodeTable, Result
from canergy.check.packed import NODE_BITS, Budgets, Guards, Layout
from canergy.check.search import PROGRESS_EVERY
from canergy.check.workers import expansions

NODE_MASK = (1 << NODE_BITS) - 1
K = StepKind


@dataclass(slots=True)
class Explored:
    """What one compact search found. States are numbered in the order they were stored."""

    states: int = 0
    transitions: int = 0
    depth: int = 0
    violations: int = 0
    first_violation: int | None = None
    subsumed: int = 0
    quiescent_states: int = 0
    worst_quiescent_dissipation: int = 0
    complete: bool = True
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0


class Engine:
    """Breadth-first search of one model with packed worlds."""

    def __init__(self, model: Model, *, symmetry: bool, subsumption: bool) -> None:
        self.model = model
        b = model.bounds
        self.layout = layout = Layout(b)
        self.guards = Guards(b, layout)
        self.table = NodeTable(model, layout, self.guards)
        self.symmetry = symmetry and b.clients > 1
        self.budgets = Budgets(layout, self.table) if subsumption else None
        self.codes: list[int] = []
        """Every stored world's code, by state number (breadth-first order)."""
        self.parents = array("q")
        """The number of the state each one was first reached from (-1: the root)."""
        self.expander_from: int | None = None
        """The state from which a second process expanded (``workers``), if one did."""
        self.shifts = [NODE_BITS * (b.clients - 1 - p) for p in range(b.clients)]
        self.power_offset, width = layout.offsets[3], layout.widths[3]
        self.power_mask = (1 << width) - 1
        self.copies = b.supervisor_old_copies > 0
        self.backups = b.supervisor_backups
        """The supervisor's old copy is a backup taken by a step of its own: writes keep it."""
        self.olders: list[tuple[int, tuple[int, ...]]] = []
        """The supervisor's older states (its Us, each position's session part), numbered."""
        self._older_ids: dict[tuple[int, tuple[int, ...]], int] = {}
        self.copy_charge = self.table.charge[K.SUPERVISOR_OLD_COPY]
        self.lifts = model.variant.lifts_tx
        """The rules have every start confirmed (witnessed): worlds may wait for books."""

    # -- encoding ----------------------------------------------------------------------
    def encode(self, w: World) -> int:
        """The code of ``w``'s canonical form."""
        table = self.table
        nodes = [table.intern(table.content_of(w, p)) for p in range(len(w.clients))]
        if self.symmetry:
            nodes.sort(key=table.keys.__getitem__)
        older = 0
        if w.sup_older is not None:
            part = table.parts.part
            older = self.older(w.sup_older.usable, tuple(part(s) for s in w.sup_older.sessions))
        return self.layout.pack(w.sup.usable, nodes, self.layout.pack_counters(w), older)

    def decode(self, code: int) -> World:
        usable, nodes, packed = self.layout.unpack(code)
        older = self.olders[self.layout.older(code)] if self.copies else None
        return self.table.world(usable, nodes, self.layout.unpack_counters(packed), older)

    def older(self, usable: int, sessions: tuple[int, ...]) -> int:
        """The number of the supervisor state with this Us and these session parts."""
        key = (usable, sessions)
        i = self._older_ids.get(key)
        if i is None:
            i = self._older_ids[key] = len(self.olders)
            if i >> self.layout.older_bits:
                raise OverflowError("more supervisor states than a world's code has room for")
            self.olders.append(key)
        return i

    def path(self, state: int) -> list[World]:
        """The stored worlds from the root to state number ``state``."""
        numbers = [state]
        while (parent := self.parents[numbers[-1]]) >= 0:
            numbers.append(parent)
        return [self.decode(self.codes[n]) for n in reversed(numbers)]

    # -- expanding ---------------------------------------------------------------------
    def successors(self, code: int) -> list[int]:
        """The canonical codes of the world's successors in ``Model.steps`` order, one per
        transition (repeats included)."""
        if self.copies:
            return self._successors_with_copies(code)
        table, layout, in_flight = self.table, self.layout, self.model.bounds.in_flight
        counter_bits = layout.counter_bits
        packed = code & layout.counter_mask
        usable = code >> (counter_bits + layout.nodes_bits)
        cs = [code >> (counter_bits + shift) & NODE_MASK for shift in self.shifts]
        frames = 0
        for c in cs:
            frames += table.frames[c]
        syncing = self.table.syncing
        waiting = self.lifts and any(syncing[c] for c in cs)
        ok = self.guards.table(packed, usable, frames < in_flight, waiting)
        nms = [table.moves[p][c] or table.moves_of(c, p) for p, c in enumerate(cs)]
        if len(nms) == 2:  # the common case, with fewer steps
            nm0, nm1 = nms
            if nm0.flight and nm1.flight:
                flight = _merged(nms)
            else:
                flight = nm0.flight_moves or nm1.flight_moves
            before = nm0.session + nm1.session + flight + nm0.client + nm1.client
        else:
            before = [mv for nm in nms for mv in nm.session]
            before += _merged(nms)
            before += [mv for nm in nms for mv in nm.client]
        after: list[Move] = []
        if any(nm.attacks for nm in nms):
            after = [mv for nm in nms for mv in nm.forge]
            after += _merged(nms, replays=True)
        out: list[int] = []
        self._add(out, before, ok, usable, cs, packed, in_flight - frames)
        if ok[self.guards.power]:
            new, r = self._restart(nms, packed >> self.power_offset & self.power_mask)
            if r[0] >= 0 and r[3] <= in_flight - frames:
                out.append(self._place(usable, new, packed, r))
        if after:
            self._add(out, after, ok, usable, cs, packed, in_flight - frames)
        return out

    def _successors_with_copies(self, code: int) -> list[int]:
        """``successors`` when the supervisor's state file has an older copy: every step that
        writes it keeps the state before as that copy (with backups: a step of its own copies
        the state as it is), and the copy may come back (no symmetry: the copy holds every
        session)."""
        table, layout, in_flight = self.table, self.layout, self.model.bounds.in_flight
        usable, cs, packed = layout.unpack(code)
        older = layout.older(code)
        frames = sum(table.frames[c] for c in cs)
        room = in_flight - frames
        waiting = self.lifts and any(table.syncing[c] for c in cs)
        ok = self.guards.table(packed, usable, frames < in_flight, waiting)
        nms = [table.moves[p][c] or table.moves_of(c, p) for p, c in enumerate(cs)]
        sessions = tuple(table.contents[c].session for c in cs)
        out: list[int] = []

        def add(new: list[int], credit: int, delta: int, wrote: bool, keep: int) -> None:
            mine = self.older(usable, sessions) if wrote and not self.backups else keep
            out.append(layout.pack(usable + credit, new, packed + delta, mine))

        moves = [mv for nm in nms for mv in nm.session] + _merged(nms)
        moves += [mv for nm in nms for mv in nm.client]
        for mv in moves:
            if ok[mv[1]]:
                r = mv[0] or table.resolve(mv)
                if r[0] >= 0 and r[3] <= room:
                    new = cs.copy()
                    new[mv[2]] = r[0]
                    add(new, r[1], r[2], table.wrote(cs[mv[2]], r[0], r[1]), older)
        if ok[self.guards.power]:
            new, r = self._restart(nms, packed >> self.power_offset & self.power_mask)
            if r[0] >= 0 and r[3] <= room:
                wrote = r[1] != 0 or any(table.wrote(a, b, 0) for a, b in zip(cs, new, strict=True))
                add(new, r[1], r[2], wrote, older)
        back_usable, back = self.olders[older]
        if ok[self.guards.sup_copy] and (back_usable, back) != (usable, sessions):
            copied = layout.unpack_counters(packed)[9] + 1
            nonce = supervisor_nonce(K.SUPERVISOR_OLD_COPY, 0, copied)
            rs = [table.restored(c, p, back[p], nonce) for p, c in enumerate(cs)]
            if all(r[0] >= 0 for r in rs) and sum(r[3] for r in rs) <= room:
                credit = sum(r[1] for r in rs)
                new = [r[0] for r in rs]
                out.append(layout.pack(back_usable + credit, new, packed + self.copy_charge, older))
            if self.backups:  # the state file copied as it is now
                out.append(layout.pack(usable, cs, packed, self.older(usable, sessions)))
        after = [mv for nm in nms for mv in nm.forge] + _merged(nms, replays=True)
        for mv in after:
            if ok[mv[1]]:
                r = mv[0] or table.resolve(mv)
                if r[0] >= 0 and r[3] <= room:
                    new = cs.copy()
                    new[mv[2]] = r[0]
                    add(new, r[1], r[2], table.wrote(cs[mv[2]], r[0], r[1]), older)
        return out

    def _add(
        self,
        out: list[int],
        moves: list[Move],
        ok: tuple[bool, ...],
        usable: int,
        cs: list[int],
        packed: int,
        room: int,
    ) -> None:
        """Append the codes of the successors through ``moves`` whose guard holds, that stay
        in bounds and add at most ``room`` frames. A move is ``[result, guard, position...]``."""
        resolve = self.table.resolve
        if len(cs) != 2:
            for mv in moves:
                if ok[mv[1]]:
                    r = mv[0] or resolve(mv)
                    if r[0] >= 0 and r[3] <= room:
                        new = cs.copy()
                        new[mv[2]] = r[0]
                        out.append(self._place(usable, new, packed, r))
            return
        keys, symmetry = self.table.keys, self.symmetry
        nodes_bits, counter_bits = self.layout.nodes_bits, self.layout.counter_bits
        c0, c1 = cs
        for mv in moves:  # two nodes, the common case: inline
            if not ok[mv[1]]:
                continue
            nc, credit, delta, added = mv[0] or resolve(mv)
            if nc < 0 or added > room:
                continue
            a, b = (c0, nc) if mv[2] else (nc, c1)
            if symmetry and keys[b] < keys[a]:
                a, b = b, a
            out.append(
                ((usable + credit) << nodes_bits | a << NODE_BITS | b) << counter_bits
                | (packed + delta)
            )

    def _place(self, usable: int, new: list[int], packed: int, r: Result) -> int:
        """The code of the successor with these contents (in position order) after ``r``."""
        if self.symmetry:
            new.sort(key=self.table.keys.__getitem__)
        return self.layout.pack(usable + r[1], new, packed + r[2])

    def _restart(self, nms: list[NodeMoves], before: int) -> tuple[list[int], Result]:
        """A supervisor power loss restarts every session: each node's share, combined;
        ``before``: the power losses before it (the start's nonce)."""
        new: list[int] = []
        credit = added = delta = 0
        for nm in nms:
            move = nm.restart[before]
            r = move[0] or self.table.resolve(move)
            if r[0] < 0:
                return new, INVALID
            new.append(r[0])
            credit += r[1]
            delta = r[2]
            added += r[3]
        return new, (0, credit, delta, added)

    # -- search ------------------------------------------------------------------------
    def run(
        self,
        *,
        max_states: int | None = None,
        stop_at_first: bool = False,
        progress: Callable[[int, int, float], None] | None = None,
        workers: int = 1,
    ) -> Explored:
        """Breadth first from the initial world, as ``search.breadth_first`` explores (with
        ``workers`` 2, a second process expands: ``workers.expansions``)."""
        start = time.perf_counter()
        store = _Store(self, progress, start)
        store.add(-1, self.encode(initial_world(self.model.bounds)), checked=False)
        out = store.out
        level, level_end = 0, 1
        collecting = gc.isenabled()
        gc.disable()  # the search makes no cycles; the collector would walk every table (~10 %)
        try:
            for i, found in expansions(self, store.violating, workers):
                if i >= level_end:
                    level, level_end = level + 1, len(self.codes)
                out.transitions += len(found)
                visited = store.visited
                for n, code in enumerate(found):
                    if code not in visited and store.add(i, code, level + 1) and stop_at_first:
                        out.transitions -= len(found) - n - 1  # not looked at
                        break
                out.depth = level
                if max_states is not None and len(self.codes) >= max_states:
                    out.complete = False
                    out.notes.append(f"stopped at --max-states {max_states}")
                    break
                if stop_at_first and out.first_violation is not None:
                    break
        finally:
            if collecting:
                gc.enable()
        out.states = len(self.codes)
        out.subsumed = 0 if self.budgets is None else self.budgets.subsumed
        out.seconds = time.perf_counter() - start
        return out


class _Store:
    """The stored worlds of one search, and what was found in them."""

    def __init__(
        self, engine: Engine, progress: Callable[[int, int, float], None] | None, start: float
    ) -> None:
        self.engine, self.progress, self.start = engine, progress, start
        self.out = Explored()
        self.visited: set[int] = set()
        self.violating: set[int] = set()
        """The numbers of the stored worlds that generate energy (not expanded)."""
        b = engine.model.bounds
        self.initial = b.units * UNIT
        self.counter_bits, self.nodes_bits = engine.layout.counter_bits, engine.layout.nodes_bits
        self.usable_shift = self.nodes_bits + engine.layout.older_bits

    def add(self, parent: int, code: int, depth: int = 0, *, checked: bool = True) -> bool:
        """Store ``code``, reached from state ``parent``, unless it is stored or subsumed, and
        check its ledger (not the root's, as ``breadth_first``); True at the first violation."""
        engine, out = self.engine, self.out
        budgets = engine.budgets
        if code in self.visited or (budgets is not None and not budgets.admit(code)):
            return False
        self.visited.add(code)
        codes = engine.codes
        codes.append(code)
        engine.parents.append(parent)
        if self.progress is not None and len(codes) % PROGRESS_EVERY == 0:
            self.progress(len(codes), depth, time.perf_counter() - self.start)
        if not checked:
            return False
        held, quiet, syncing = engine.table.held, engine.table.quiet, engine.table.syncing
        nodes = code >> self.counter_bits
        usable = nodes >> self.usable_shift
        dissipated = self.initial
        still, waiting = True, False
        for shift in engine.shifts:
            c = nodes >> shift & NODE_MASK
            dissipated -= held[c]  # the ledger: less what each node holds...
            still = still and quiet[c]
            waiting = waiting or syncing[c]
        dissipated -= min(usable, 0) if waiting else usable  # ...less Us (none while waiting)
        if dissipated < 0:
            out.violations += 1
            self.violating.add(len(codes) - 1)
            if out.first_violation is None:
                out.first_violation = len(codes) - 1
                return True
        elif still:
            out.quiescent_states += 1
            out.worst_quiescent_dissipation = max(out.worst_quiescent_dissipation, dissipated)
        return False


def _merged(nms: list[NodeMoves], *, replays: bool = False) -> list[Move]:
    """The nodes' frames' (or replayed frames') moves in ``message_key`` order, as
    ``Model.steps`` sorts the frames."""
    keyed: list[Keyed] = []
    for nm in nms:
        keyed += nm.replay if replays else nm.flight
    keyed.sort(key=_by_key)
    return [mv for _, _, mv in keyed]


def _by_key(keyed: Keyed) -> tuple[tuple[int, str], int]:
    return keyed[0], keyed[1]
