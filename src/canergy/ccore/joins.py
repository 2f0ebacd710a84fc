"""The compiled core's held JOINs: ``canergy.live.supervisor.joins.JoinHold``'s interface over
firmware/src/joins.c, one ``struct canergy_joins`` per session in C memory the frame path's call
reaches (``CompiledSupervisor.on_answer`` holds a JOIN and reads a TELEMETRY there). Python adds
the words of the JOINs a TELEMETRY refutes, read from the record as it was, and returns a
confirmed one for the caller to have the core admit."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from canergy.auth.frames import AuthFailure
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.messages import Join, Telemetry

if TYPE_CHECKING:
    from canergy.ccore.supervisor import CompiledSupervisor


class CompiledJoinHold:
    """``JoinHold`` in C (``CompiledSupervisor.join_hold``)."""

    implementation = "c"

    def __init__(
        self,
        core: CompiledSupervisor,
        hold_us: int,
        local_nodes: frozenset[int],
        intrusions: Intrusions,
        refusals: Refusals,
        authenticated: Callable[[], bool],
    ) -> None:
        b = core._b
        self._ffi, self._lib = b.ffi, b.lib
        self.records: Any = b.ffi.new("struct canergy_joins[]", len(core.nodes))
        self.tables = core.tables
        self.before: Any = b.ffi.addressof(core.tables, "joins_before")
        """The frame path's call leaves here the node's record as it was (for the words)."""
        self._nonce = b.ffi.new("uint16_t *")
        self._recs = {n: self.records + i for n, i in core._index.items()}
        """Each node's record (a pointer made once: the frame path reads them every pass)."""
        self.hold_us = hold_us
        self.local_nodes = local_nodes
        self.intrusions = intrusions
        self.refusals = refusals
        self.authenticated = authenticated
        self.due: set[int] = set()
        self.bits = {
            "due": int(b.lib.CANERGY_JOINS_DUE),
            "admit": int(b.lib.CANERGY_JOINS_ADMIT),
            "refused": int(b.lib.CANERGY_JOINS_REFUSED),
        }

    def _rec(self, node: int) -> Any:
        return self._recs[node]

    def hold_for(self, node: int) -> int:
        """How long a confirmed JOIN of ``node`` waits (0: a node only this process speaks for)."""
        return 0 if node in self.local_nodes else self.hold_us

    def on_join(self, join: Join) -> None:
        rec = self._rec(join.node)
        self._lib.canergy_joins_join(rec, join.nonce)
        if not rec.has_admitting:  # another start: only a TELEMETRY after it confirms it
            self.due.discard(join.node)

    def holding(self, node: int) -> bool:
        return bool(self._rec(node).held_count)

    def resent(self, node: int) -> int:
        return int(self._rec(node).resent)

    def on_telemetry(self, msg: Telemetry, now: int) -> list[Join]:
        """As ``JoinHold.on_telemetry``, for a TELEMETRY decoded in Python."""
        rec = self._rec(msg.node)
        self._ffi.memmove(self.before, rec, self._ffi.sizeof("struct canergy_joins"))
        found = self._lib.canergy_joins_telemetry(
            rec, msg.flags, now, self.hold_for(msg.node), self._nonce
        )
        return self.telemetry_taken(msg, now, found, int(self._nonce[0]))

    def telemetry_taken(
        self, msg: Telemetry, now: int, found: int, nonce: int | None = None
    ) -> list[Join]:
        """What C's table did with ``msg`` (``found``, its bits; ``nonce``: the JOIN to admit,
        by default the frame path's), the record before it in ``before``: refusals worded, a
        due node noted, an admission carried out."""
        bits = self.bits
        if found & bits["due"]:
            self.due.add(msg.node)
        if not self._rec(msg.node).has_admitting:  # admitted or refused: nothing waits
            self.due.discard(msg.node)
        if found & bits["admit"]:
            admitted = int(self.tables.admit) if nonce is None else nonce
            return [Join(msg.node, admitted)]
        if found & bits["refused"]:
            self._refused(msg.node, now)
        return []

    def _refused(self, node: int, now: int) -> None:
        w = self.before
        authenticated = self.authenticated()
        reason = (
            f"{AuthFailure.STALE.value} (a JOIN of an earlier life: the node has its books)"
            if authenticated
            else "a JOIN in its name while the node reports its books: forged or replayed"
        )
        for k in range(w.held_count):
            nonce = int(w.held[k])
            if w.has_admitted and nonce == w.admitted:
                continue
            join = Join(node, nonce)
            if authenticated:
                self.refusals.record(node, reason, repr(join), now)
            self.intrusions.record(node, repr(join), reason, now, quiet=authenticated)

    def on_wakeup(self, now: int) -> list[Join]:
        out: list[Join] = []
        for node in sorted(self.due):
            if self._lib.canergy_joins_due(self._rec(node), now, self._nonce):
                out.append(Join(node, int(self._nonce[0])))
            if not self._rec(node).has_admitting:
                self.due.discard(node)
        return out

    def next_wakeup(self) -> int | None:
        if not self.due:
            return None
        times = [int(r.admit_at) for n in self.due if (r := self._rec(n)).has_admitting]
        return min(times, default=None)
