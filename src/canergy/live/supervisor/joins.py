"""JOINs held as evidence until the node's own TELEMETRY says whether it lost its books.

A JOIN writes off what the node held, and anyone can send one (without a key), or replay an
earlier life's (with one). So a JOIN is held, not answered: the node's next TELEMETRY decides.
Without books (JOINING; with a key bound to that JOIN) the latest held JOIN is admitted
``hold_us`` later, unless the node shows its books meanwhile; with books every held JOIN was a
replay or a forgery and is refused (nothing written off, nobody admitted), except a copy of the
JOIN admitted just before: the node re-sent it while its ADMIT was on the way.

Sans-IO: times in µs from the caller; what is to be admitted is returned, the admission itself
(the core's answer) is the caller's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from canergy.auth.frames import AuthFailure
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.messages import Join, Telemetry

HELD_JOINS = 8
"""Distinct JOINs held per node until its next TELEMETRY (replays or forgeries beyond it push
out the oldest, which is then neither admitted nor reported)."""
JOIN_HOLD_US = 500_000
"""A held JOIN is admitted this long after the node's TELEMETRY without books confirmed it,
unless the node shows its books meanwhile (``ServiceConfig.join_hold_us``)."""


@dataclass(slots=True)
class HeldJoins:
    """One node's JOINs waiting for its TELEMETRY."""

    held: list[Join] = field(default_factory=list)
    """Distinct, the latest last, at most ``HELD_JOINS`` (verified, in authenticated mode)."""
    admitting: tuple[Join, int] | None = None
    """The held JOIN a TELEMETRY without books confirmed, and when it is admitted unless the
    node shows its books before; a new JOIN cancels it."""
    admitted_nonce: int | None = None
    """The nonce of the JOIN admitted last, until the node's first TELEMETRY with books: a copy
    of that JOIN held meanwhile is the node's own re-send, not a replay."""
    resent: int = 0
    """Copies of the JOIN just admitted, re-sent before the node heard its ADMIT: dropped."""


class JoinHold:
    """The held JOINs of every node; ``authenticated()`` tells the mode. What a TELEMETRY or
    a deadline confirms is returned: the JOINs for the caller to have the core admit."""

    def __init__(
        self,
        nodes: tuple[int, ...],
        hold_us: int,
        local_nodes: frozenset[int],
        intrusions: Intrusions,
        refusals: Refusals,
        authenticated: Callable[[], bool],
    ) -> None:
        """``local_nodes``: nodes only this process speaks for (a guarded drive's proxy): no
        hold for their JOINs."""
        self.nodes = {n: HeldJoins() for n in nodes}
        self.hold_us = hold_us
        self.local_nodes = local_nodes
        self.intrusions = intrusions
        self.refusals = refusals
        self.authenticated = authenticated
        self.due: set[int] = set()
        """Exactly the nodes with a JOIN confirmed and waiting for its hold (a node leaves as
        it is admitted, refused or cancelled), so the loop's every pass does not look at every
        node that ever joined."""

    def on_join(self, join: Join) -> None:
        """A JOIN in a node's name: held (a replay or forgery looks the same)."""
        h = self.nodes[join.node]
        if join in h.held:
            h.held.remove(join)
        else:  # another start (or a replay): only a TELEMETRY after it confirms it
            h.admitting = None
            self.due.discard(join.node)
        h.held.append(join)
        del h.held[:-HELD_JOINS]

    def holding(self, node: int) -> bool:
        """JOINs wait for this node's TELEMETRY (no grant meanwhile: it would be lost)."""
        return bool(self.nodes[node].held)

    def resent(self, node: int) -> int:
        """Copies of the JOIN just admitted that ``node`` re-sent (dropped)."""
        return self.nodes[node].resent

    def on_telemetry(self, msg: Telemetry, now: int) -> list[Join]:
        """The node's report: without books it confirms the latest held JOIN (admitted after
        the hold), with books it refutes every held one."""
        h = self.nodes[msg.node]
        if msg.flags & Telemetry.JOINING:
            if not h.held:
                return []
            if h.admitting is None:
                hold = 0 if msg.node in self.local_nodes else self.hold_us
                h.admitting = (h.held[-1], now + hold)
                self.due.add(msg.node)
            return self._admit_due(msg.node, now)
        joins, h.held, h.admitting = h.held, [], None
        self.due.discard(msg.node)
        admitted, h.admitted_nonce = h.admitted_nonce, None
        authenticated = self.authenticated()
        reason = (
            f"{AuthFailure.STALE.value} (a JOIN of an earlier life: the node has its books)"
            if authenticated
            else "a JOIN in its name while the node reports its books: forged or replayed"
        )
        for join in joins:
            if join.nonce == admitted:
                h.resent += 1
                continue
            if authenticated:
                self.refusals.record(msg.node, reason, repr(join), now)
            self.intrusions.record(msg.node, repr(join), reason, now, quiet=authenticated)
        return []

    def on_wakeup(self, now: int) -> list[Join]:
        """The confirmed JOINs whose hold is over, admitted."""
        out: list[Join] = []
        for node in sorted(self.due):
            out += self._admit_due(node, now)
        return out

    def next_wakeup(self) -> int | None:
        times = [a[1] for n in self.due if (a := self.nodes[n].admitting) is not None]
        return min(times, default=None)

    def _admit_due(self, node: int, now: int) -> list[Join]:
        """Admit the confirmed JOIN once its hold is over (the others held are dropped)."""
        h = self.nodes[node]
        if h.admitting is None or now < h.admitting[1]:
            return []
        join = h.admitting[0]
        h.held, h.admitting, h.admitted_nonce = [], None, join.nonce
        self.due.discard(node)
        return [join]
