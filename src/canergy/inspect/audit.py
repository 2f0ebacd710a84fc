"""A passive observer that rebuilds every node's transactions from the frames alone.

What the bus proves, per node: intentions (with the supervisor's delivered count Gs), ACKs,
COMMIT/ABORT, COMMITTED/ABORTED, RETURN/RETURN_ACK. From these the audit counts transactions and
energy, and flags what a correct supervisor and client never put on the bus (hardened rules):

- an INTENTION older than one already seen (a replay), or re-sent with another amount;
- Gs going backwards;
- a COMMIT for a transaction whose intention was seen but never acknowledged, a COMMIT or ABORT
  for a transaction after a newer one began, a COMMIT after an ABORT (or the reverse), a COMMIT
  with another amount than its intention;
- a client reporting both COMMITTED and ABORTED for one transaction (a timeout-commit may
  answer an ABORT with COMMITTED: both rule sets allow that);
- a RETURN re-used with another amount, a RETURN_ACK for a return never sent;
- an ADMIT (answer to a node's JOIN after it lost its books) behind a transaction already begun;
- passivity: the clients booking (COMMITTED) more than the supervisor can have released since the
  capture began (the growth of Gs plus the last open reservation), or, with ``initial``, the net
  energy granted on the bus exceeding the initial budget.

Captures may start mid-run: checks that need an earlier frame apply only once it was seen. A
capture is taken to be in bus order (a CAN bus does not reorder); a capture taken behind a
reordering channel (``reordered=True``, e.g. the demo's fault injector) counts frames of older
transactions as stale instead. The audit cannot see frames a capture missed (candump overruns).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from canergy.inspect.frames import Described
from canergy.inspect.render import raw_part
from canergy.messages import (
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Intention,
    Join,
    Return,
    ReturnAck,
)
from canergy.seqnum import unwrap


@dataclass(frozen=True, slots=True)
class Violation:
    frame: int
    """1-based position of the frame in the capture."""
    timestamp: float | None
    node: int | None
    what: str
    line: str

    def as_json(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "timestamp": self.timestamp,
            "node": self.node,
            "what": self.what,
            "line": self.line,
        }


@dataclass(slots=True)
class NodeBooks:
    node: int
    intentions: dict[int, int] = field(default_factory=dict)
    acked: set[int] = field(default_factory=set)
    commits: dict[int, int] = field(default_factory=dict)
    aborts: set[int] = field(default_factory=set)
    committed: set[int] = field(default_factory=set)
    aborted: set[int] = field(default_factory=set)
    newest_tx: int | None = None
    first_gs: int | None = None
    last_gs: int | None = None
    returns: dict[int, int] = field(default_factory=dict)
    returns_acked: set[int] = field(default_factory=set)
    newest_return: int | None = None
    resends: int = 0
    joins: int = 0
    admits: int = 0

    booked_uj: int = 0
    """Amounts of committed transactions whose intention the capture saw."""

    def booked(self) -> int:
        return self.booked_uj

    def returned(self) -> int:
        return sum(self.returns[q] for q in self.returns_acked if q in self.returns)

    def released_max(self) -> int | None:
        """Upper bound of what the supervisor can have released since the capture began."""
        if self.first_gs is None or self.last_gs is None or self.newest_tx is None:
            return None
        return self.last_gs - self.first_gs + self.intentions.get(self.newest_tx, 0)

    def report(self) -> dict[str, Any]:
        seen = set(self.intentions)
        released = self.released_max()
        return {
            "transactions_seen": len(seen),
            "committed": len(self.committed),
            "aborted": len(self.aborted),
            "unresolved": len(seen - self.committed - self.aborted),
            "resent_intentions": self.resends,
            "joins": self.joins,
            "admits": self.admits,
            "granted_uj": self.booked(),
            "returned_uj": self.returned(),
            "released_max_uj": released,
            "holdable_max_uj": None if released is None else released - self.returned(),
        }


class Auditor:
    def __init__(self, *, initial: int | None = None, reordered: bool = False) -> None:
        self.initial = initial
        self.reordered = reordered
        self.stale = 0
        self.nodes: dict[int, NodeBooks] = {}
        self.violations: list[Violation] = []
        self.frames = 0
        self.foreign = 0
        self.damaged = 0

    def feed(self, d: Described) -> None:
        self.frames += 1
        if not d.ours:
            self.foreign += 1
            return
        if d.message is None or not d.crc_ok:
            self.damaged += 1  # a receiver drops it; so does the audit
            return
        m = d.message
        books = self.nodes.setdefault(m.node, NodeBooks(m.node))

        def flag(what: str) -> None:
            self.violations.append(Violation(self.frames, d.timestamp, m.node, what, raw_part(d)))

        if isinstance(m, Intention):
            self._intention(books, m, flag)
        elif isinstance(m, Ack):
            books.acked.add(self._tx(books, m.tx))
        elif isinstance(m, Commit | Abort):
            self._command(books, m, flag)
        elif isinstance(m, Committed | Aborted):
            self._outcome(books, m, flag)
        elif isinstance(m, Return):
            seq = self._seq(books, m.seq)
            amount = m.amount_mj * QUANTUM_UJ
            if books.returns.setdefault(seq, amount) != amount:
                flag(f"RETURN {seq} re-used with another amount")
            books.newest_return = max(seq, books.newest_return or seq)
        elif isinstance(m, ReturnAck):
            seq = self._seq(books, m.seq)
            if books.newest_return is not None and seq > books.newest_return:
                flag(f"RETURN_ACK {seq} for a return never sent")
            books.returns_acked.add(seq)
        elif isinstance(m, Join):
            books.joins += 1
        elif isinstance(m, Admit):
            self._admit(books, m, flag)

    # -- per message ------------------------------------------------------------------------
    def _tx(self, books: NodeBooks, wire: int) -> int:
        return wire if books.newest_tx is None else unwrap(wire, books.newest_tx, TX_BITS)

    def _seq(self, books: NodeBooks, wire: int) -> int:
        ref = books.newest_return
        return wire if ref is None else unwrap(wire, ref, SEQ_BITS)

    def _intention(self, books: NodeBooks, m: Intention, flag: Any) -> None:
        tx, amount = self._tx(books, m.tx), m.amount_mj * QUANTUM_UJ
        ref = books.last_gs // QUANTUM_UJ if books.last_gs is not None else None
        gs = (
            m.delivered_mj if ref is None else unwrap(m.delivered_mj, ref, DELIVERED_BITS)
        ) * QUANTUM_UJ
        if books.newest_tx is not None and tx < books.newest_tx:
            self._stale(
                flag, f"replayed old INTENTION tx {tx} (tx {books.newest_tx} already began)"
            )
            return
        if tx in books.intentions:
            books.resends += 1
            if books.intentions[tx] != amount:
                flag(f"INTENTION tx {tx} re-sent with another amount")
        if books.last_gs is not None and gs < books.last_gs:
            flag(f"delivered count went back from {books.last_gs} to {gs} µJ")
        books.intentions.setdefault(tx, amount)
        books.newest_tx = tx
        books.last_gs = gs
        if books.first_gs is None:
            books.first_gs = gs

    def _admit(self, books: NodeBooks, m: Admit, flag: Any) -> None:
        """The node starts afresh at the supervisor's counters: older frames move nothing."""
        books.admits += 1
        tx = self._tx(books, m.tx)
        if books.newest_tx is not None and tx < books.newest_tx:
            flag(f"ADMIT at tx {tx}, behind tx {books.newest_tx} already begun")
            return
        books.newest_tx = tx
        books.newest_return = self._seq(books, m.seq)

    def _stale(self, flag: Any, what: str) -> None:
        """A frame of an older transaction: impossible in bus order from a correct supervisor,
        normal behind a channel that reorders (``reordered``), where receivers ignore it."""
        if self.reordered:
            self.stale += 1
        else:
            flag(what)

    def _command(self, books: NodeBooks, m: Commit | Abort, flag: Any) -> None:
        tx, kind = self._tx(books, m.tx), type(m).__name__.upper()
        if books.newest_tx is not None and tx < books.newest_tx:
            self._stale(flag, f"{kind} for tx {tx} after tx {books.newest_tx} began")
            return
        if tx in books.intentions and tx not in books.acked:
            flag(f"{kind} for tx {tx}, which was never acknowledged")
        if tx in books.intentions and m.amount_mj * QUANTUM_UJ != books.intentions[tx]:
            flag(f"{kind} for tx {tx} with another amount than its intention")
        if isinstance(m, Commit):
            if tx in books.aborts:
                flag(f"COMMIT for tx {tx} after ABORT")
            books.commits.setdefault(tx, m.amount_mj * QUANTUM_UJ)
        else:
            if tx in books.commits:
                flag(f"ABORT for tx {tx} after COMMIT")
            books.aborts.add(tx)

    def _outcome(self, books: NodeBooks, m: Committed | Aborted, flag: Any) -> None:
        tx = self._tx(books, m.tx)
        if isinstance(m, Committed):
            if tx in books.aborted:
                flag(f"COMMITTED tx {tx} after ABORTED")
            if tx not in books.committed and tx in books.intentions:
                books.booked_uj += books.intentions[tx]
            books.committed.add(tx)
            released = books.released_max()
            if released is not None and books.booked() > released:
                flag(
                    f"node booked {books.booked() / 1e6:.3f} J, the supervisor released at most "
                    f"{released / 1e6:.3f} J: energy created"
                )
        else:
            if tx in books.committed:
                flag(f"ABORTED tx {tx} after COMMITTED")
            books.aborted.add(tx)

    # -- result -------------------------------------------------------------------------------
    def finish(self) -> None:
        if self.initial is None:
            return
        net = sum(b.booked() - b.returned() for b in self.nodes.values())
        if net > self.initial:
            self.violations.append(
                Violation(
                    self.frames,
                    None,
                    None,
                    f"net energy granted on the bus {net / 1e6:.3f} J exceeds the initial "
                    f"{self.initial / 1e6:.3f} J",
                    "",
                )
            )

    def report(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "foreign_frames": self.foreign,
            "damaged_frames": self.damaged,
            "stale_frames": self.stale,
            "nodes": {str(n): b.report() for n, b in sorted(self.nodes.items())},
            "violations": [v.as_json() for v in self.violations],
            "passive": not self.violations,
        }
