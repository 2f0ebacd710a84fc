"""A passive observer that rebuilds every node's transactions from the frames alone.

What the bus proves, per node: intentions (with the supervisor's delivered count Gs), ACKs,
COMMIT/ABORT, COMMITTED/ABORTED, RETURN/RETURN_ACK, JOIN/ADMIT. Nothing on the bus says who sent
a frame (the CRC-8 is public), so the audit judges each frame by whether a correct supervisor or
client could have put it there, given the frames before it (hardened rules), and names the frame
that cannot be theirs. Flagged frames are left out of the books, so the genuine traffic after a
forgery is judged against the genuine traffic before it.

Causality (a correct party only answers frames that were on the bus before):

- a COMMIT/ABORT for a transaction whose INTENTION was never on the bus, once the capture covers
  the node (an intention or ADMIT of an older transaction seen), or one whose intention was
  never acknowledged;
- a RETURN_ACK before any RETURN with that number, once the capture covers the node's returns
  (a RETURN, a fresh node's first transaction or an ADMIT seen).

The supervisor's sequence (one transaction at a time, tx + 1 each, Gs grows only when a
transaction ends, by its whole amount unless it was aborted, re-sends identical):

- an INTENTION behind the newest transaction begun (a replay, or a second supervisor's sequence
  interleaving), counted as stale instead with ``reordered``;
- an INTENTION whose Gs does not follow from the previous intention: Gs(k+1) must be Gs(k) or
  Gs(k) + amount(k) (forged credit, Gs going backwards);
- an INTENTION jumping ahead: every transaction skipped unseen was written off (all its
  intentions lost before the bus), so it must show in Gs (at least 1 mJ, at most 65.535 J each),
  and at most ``MAX_SKIPPED`` of them;
- two versions of one transaction's INTENTION (amount or Gs): the one whose Gs does not follow
  from the previous transaction is flagged at once; otherwise the supervisor's next intention
  decides (its Gs shows which amount was released) and the other version, all its frames, is
  flagged then. Undecided at the end of the capture (e.g. both fit an abort), one violation names
  both frames: the bus cannot tell which is forged.

The client's side:

- a RETURN for more than the node can hold: once the capture has seen the node start from zero
  (its first transaction, tx 1 with Gs 0, or an ADMIT answering its JOIN) the node holds at most
  the newest Gs plus the newest amount, minus that base and minus its returns (plus whatever a
  flagged forgery may have given it);
- two RETURNs with one number and different amounts: a node re-sends only identical copies. The
  later one is flagged when the node had already moved on to a later return; otherwise, when the
  earlier one was acknowledged before the later one appeared, the earlier one is flagged (the
  node still had that return to make, so the version the supervisor credited was not the
  node's: a forged return sent ahead of the real one). A forged copy sent after the node's own
  was acknowledged and before its next return would be blamed on the genuine one: a limit.
- a RETURN_ACK the supervisor never sent: a node's next RETURN then goes unanswered for good
  (the supervisor credits only the next number), so when the next return is left unanswered
  ``STARVED`` times in a row while the supervisor answers the node's other frames (an ACK
  followed by its COMMIT/ABORT after each copy), the acknowledgement of the previous return is
  flagged. Evidence rather than proof on a lossy channel: an honest capture shows it only when
  that many acknowledgements in a row were lost.

Also: COMMIT/ABORT with an amount no intention of that transaction carried, COMMIT and ABORT for
one transaction, COMMITTED and ABORTED for one transaction (a timeout-commit may answer an ABORT
with COMMITTED: allowed), an ADMIT behind a transaction already begun, and passivity: the node
booking (COMMITTED) more than the supervisor can have released since the capture began, or, with
``initial``, the net energy granted on the bus exceeding the initial budget.

A capture of several buses (candump of can0 and can1, an ASC or BLF file with channels) is
audited per bus: each (channel, node) has its own books, so node 5 on two buses are two nodes,
reported as ``can0/5`` and ``can1/5`` when the capture has more than one channel.

Limits: captures may start mid-run, so rules that need an earlier frame apply only once it was
seen. A capture is taken to be in bus order; frames lost before the bus (a failed transmission,
the demo's losses) are fine, but a capture that misses frames others received (candump overruns)
can cause false alarms. ``reordered=True`` (a capture behind a reordering channel, e.g. the demo's
fault injector) counts frames of older transactions as stale and does not require skipped
transactions to show in Gs or starved returns. A forgery identical to a frame the genuine party
would send (a copy of a real intention, an acknowledgement sent right after the supervisor's)
is indistinguishable and harmless. The RETURN bound assumes the 24-bit Gs has not wrapped since
the base was seen.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from canergy.inspect.frames import Described
from canergy.inspect.render import raw_part
from canergy.messages import (
    AMOUNT_MAX_MJ,
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

MAX_SKIPPED = 16
"""Most transactions an intention may skip unseen (each needs all its intentions lost)."""
STARVED = 8
"""Unanswered copies of a node's next return (while the supervisor answers the node) that
convict the previous RETURN_ACK."""
_MAX_UJ = AMOUNT_MAX_MJ * QUANTUM_UJ


def _j(uj: int) -> str:
    return f"{uj / 1e6:.3f} J"


@dataclass(frozen=True, slots=True)
class Violation:
    frame: int
    """1-based position of the frame in the capture."""
    timestamp: float | None
    node: int | None
    what: str
    line: str
    channel: str = ""

    def as_json(self, channels: bool = False) -> dict[str, Any]:
        """``channels``: the capture has several, name the node ``channel/node``."""
        return {
            "frame": self.frame,
            "timestamp": self.timestamp,
            "node": node_label(self.channel, self.node, channels),
            "what": self.what,
            "line": self.line,
        }


@dataclass(frozen=True, slots=True)
class Seen:
    """Where a frame is in the capture."""

    frame: int
    timestamp: float | None
    described: Described

    @property
    def line(self) -> str:
        """The frame as candump shows it (formatted only for a violation)."""
        return raw_part(self.described)


@dataclass(slots=True)
class Version:
    """One content of an INTENTION (amount, Gs) or RETURN (amount, gs 0) and its frames."""

    amount: int
    gs: int
    frames: list[Seen]
    forged: bool = False


@dataclass(slots=True)
class Starving:
    """The node's next return after ``ack`` acknowledged the previous one, not yet answered."""

    seq: int
    ack: Seen
    last_copy: int
    counted: bool = False
    evidence: int = 0


def node_label(channel: str, node: int | None, channels: bool) -> int | str | None:
    """A node as reports name it: its id, or ``channel/node`` in a capture of several channels."""
    return f"{channel}/{node}" if channels and node is not None else node


def _live(versions: Iterable[Version]) -> list[Version]:
    return [v for v in versions if not v.forged]


@dataclass(slots=True)
class NodeBooks:
    node: int
    channel: str = ""
    intentions: dict[int, list[Version]] = field(default_factory=dict)
    acked: set[int] = field(default_factory=set)
    last_ack: dict[int, int] = field(default_factory=dict)
    commits: dict[int, int] = field(default_factory=dict)
    aborts: set[int] = field(default_factory=set)
    committed: set[int] = field(default_factory=set)
    aborted: set[int] = field(default_factory=set)
    booked_tx: set[int] = field(default_factory=set)
    booked_uj: int | None = None
    """``booked()`` as last summed; None once an intention version changed (a capture of a
    long run books thousands of transactions: summing them at every COMMITTED is quadratic)."""
    newest_tx: int | None = None
    first_gs: int | None = None
    last_gs: int | None = None
    returns: dict[int, list[Version]] = field(default_factory=dict)
    return_frames: set[int] = field(default_factory=set)
    return_acks: dict[int, Seen] = field(default_factory=dict)
    returns_acked: set[int] = field(default_factory=set)
    newest_return: int | None = None
    return_floor: int | None = None
    """Every RETURN from this number on is in the capture."""
    hold_base: int | None = None
    """Gs at which the node held nothing (a fresh node: 0), once known."""
    hold_after: int | None = None
    """Admitted at this tx: the node holds nothing until its next intention sets the base."""
    return_base: int = 0
    forged_uj: int = 0
    """What flagged frames may have given the node."""
    starving: Starving | None = None
    join_nonces: set[int] = field(default_factory=set)
    admitted: int | None = None
    """Nonce of the ADMIT the node took (None again at its next JOIN)."""
    resends: int = 0
    joins: int = 0
    admits: int = 0

    def live(self, tx: int | None) -> list[Version]:
        return _live(self.intentions.get(tx, ())) if tx is not None else []

    def amount(self, tx: int) -> int:
        live = self.live(tx)
        return live[0].amount if live else 0

    def booked(self) -> int:
        """Amounts of committed transactions whose intention the capture saw."""
        if self.booked_uj is None:
            self.booked_uj = sum(self.amount(tx) for tx in self.booked_tx)
        return self.booked_uj

    def returned(self, exclude: int | None = None) -> int:
        """Amounts of the node's returns since its base (one per number)."""
        return sum(
            live[0].amount
            for q, versions in self.returns.items()
            if q != exclude and q > self.return_base and (live := _live(versions))
        )

    def acked_returns(self) -> int:
        return sum(
            live[0].amount for q in self.returns_acked if (live := _live(self.returns.get(q, ())))
        )

    def released_max(self) -> int | None:
        """Upper bound of what the supervisor can have released since the capture began."""
        if self.first_gs is None or self.last_gs is None:
            return None
        return (
            self.last_gs
            - self.first_gs
            + max((v.amount for v in self.live(self.newest_tx)), default=0)
        )

    def holdable(self, exclude: int | None = None) -> int | None:
        """Most the node can hold, when the capture saw it start from zero."""
        if self.hold_after is not None:
            return self.forged_uj
        if self.hold_base is None:
            return None
        top = max((v.gs + v.amount for v in self.live(self.newest_tx)), default=self.hold_base)
        return top - self.hold_base - self.returned(exclude) + self.forged_uj

    def holdable_bound(self) -> int | None:
        """Most the node can hold: ``holdable`` when the capture saw it start from zero, else
        what the supervisor can have released since the capture began, less acknowledged
        returns; None before any intention."""
        hold = self.holdable()
        released = self.released_max()
        if hold is None and released is not None:
            hold = released - self.acked_returns()
        return hold

    def report(self) -> dict[str, Any]:
        seen = {tx for tx in self.intentions if self.live(tx)}
        released = self.released_max()
        hold = self.holdable_bound()
        return {
            "transactions_seen": len(seen),
            "committed": len(self.committed),
            "aborted": len(self.aborted),
            "unresolved": len(seen - self.committed - self.aborted),
            "resent_intentions": self.resends,
            "joins": self.joins,
            "admits": self.admits,
            "granted_uj": self.booked(),
            "returned_uj": self.acked_returns(),
            "released_max_uj": released,
            "holdable_max_uj": hold,
        }


Flag = Callable[[str], None]


class Auditor:
    def __init__(self, *, initial: int | None = None, reordered: bool = False) -> None:
        self.initial = initial
        self.reordered = reordered
        self.stale = 0
        self.nodes: dict[tuple[str, int], NodeBooks] = {}
        """Books per (channel, node): the same id on two buses is two nodes."""
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
        b = self.nodes.setdefault((d.channel, m.node), NodeBooks(m.node, d.channel))
        seen = Seen(self.frames, d.timestamp, d)

        def flag(what: str) -> None:
            self._flag(b, seen, what)

        if isinstance(m, Intention):
            self._intention(b, m, seen, flag)
        elif isinstance(m, Ack):
            tx = self._tx(b, m.tx)
            b.acked.add(tx)
            b.last_ack[tx] = seen.frame
        elif isinstance(m, Commit | Abort):
            self._command(b, m, flag)
        elif isinstance(m, Committed | Aborted):
            self._outcome(b, m, flag)
        elif isinstance(m, Return):
            self._return(b, m, seen, flag)
        elif isinstance(m, ReturnAck):
            self._return_ack(b, m, seen, flag)
        elif isinstance(m, Join):
            b.joins += 1
            b.join_nonces.add(m.nonce)
            b.admitted = None
        elif isinstance(m, Admit):
            self._admit(b, m, flag)

    def _flag(self, b: NodeBooks, seen: Seen, what: str) -> None:
        self.violations.append(
            Violation(seen.frame, seen.timestamp, b.node, what, seen.line, b.channel)
        )

    # -- intentions ---------------------------------------------------------------------------
    def _tx(self, b: NodeBooks, wire: int) -> int:
        return wire if b.newest_tx is None else unwrap(wire, b.newest_tx, TX_BITS)

    def _seq(self, b: NodeBooks, wire: int) -> int:
        ref = b.newest_return
        return wire if ref is None else unwrap(wire, ref, SEQ_BITS)

    def _follows(self, prev: Version, gs: int, skipped: int) -> bool:
        """Gs after ``prev`` and ``skipped`` unseen (written-off) transactions."""
        low = 0 if self.reordered else skipped * QUANTUM_UJ
        return any(low <= gs - prev.gs - r <= skipped * _MAX_UJ for r in (0, prev.amount))

    def _gs_problem(self, b: NodeBooks, prev_tx: int, tx: int, gs: int) -> str | None:
        prev = b.live(prev_tx)
        skipped = tx - prev_tx - 1
        if skipped > MAX_SKIPPED:
            return (
                f"INTENTION tx {tx} jumps {skipped} transactions ahead of tx {prev_tx}: "
                "the supervisor's tx advances by one per transaction"
            )
        if not prev or any(self._follows(v, gs, skipped) for v in prev):
            return None
        if gs < min(v.gs for v in prev):
            return f"delivered count went back from {prev[0].gs} to {gs} µJ"
        what = f"skipping {skipped} unseen transaction(s) " if skipped else ""
        return (
            f"INTENTION tx {tx} {what}claims Gs {_j(gs)}, but after tx {prev_tx} "
            f"(Gs {_j(prev[0].gs)}, amount {_j(prev[0].amount)}) the supervisor's Gs is "
            "one of the two or grew by the write-offs of skipped transactions"
        )

    def _intention(self, b: NodeBooks, m: Intention, seen: Seen, flag: Flag) -> None:
        tx, amount = self._tx(b, m.tx), m.amount_mj * QUANTUM_UJ
        ref = b.last_gs // QUANTUM_UJ if b.last_gs is not None else None
        gs = m.delivered_mj if ref is None else unwrap(m.delivered_mj, ref, DELIVERED_BITS)
        gs *= QUANTUM_UJ
        newest = b.newest_tx
        if newest is not None and tx < newest:
            self._stale(
                flag,
                f"replayed old INTENTION tx {tx} (tx {newest} already began): a replay, or a "
                "second supervisor's sequence",
            )
            return
        if newest is None or tx > newest:
            problem = None if newest is None else self._gs_problem(b, newest, tx, gs)
            if problem is not None:
                flag(problem)
                b.forged_uj += amount + max(0, gs - (b.last_gs or 0))
                return
            if newest is not None:
                self._decide(b, newest, lambda v: self._follows(v, gs, tx - newest - 1), seen)
            self._new_tx(b, tx, Version(amount, gs, [seen]))
            return
        versions = b.intentions.setdefault(tx, [])
        for v in _live(versions):
            if (v.amount, v.gs) == (amount, gs):
                v.frames.append(seen)
                b.resends += 1
                return
        if not _live(versions):  # newest came from an ADMIT
            versions.append(Version(amount, gs, [seen]))
            b.booked_uj = None
            return
        problem = self._gs_problem(b, tx - 1, tx, gs) if b.live(tx - 1) else None
        if problem is not None:
            flag(f"INTENTION tx {tx} re-sent with another amount or Gs: {problem}")
            b.forged_uj += amount + max(0, gs - versions[0].gs)
            return
        versions.append(Version(amount, gs, [seen]))  # disputed until the next intention
        b.booked_uj = None

    def _new_tx(self, b: NodeBooks, tx: int, v: Version) -> None:
        fresh = b.first_gs is None and tx == 1 and v.gs == 0
        b.intentions[tx] = [v]
        b.booked_uj = None if tx in b.booked_tx else b.booked_uj
        b.newest_tx = tx
        b.last_gs = v.gs
        if b.first_gs is None:
            b.first_gs = v.gs
        if fresh:  # the supervisor's first transaction for this node: it held nothing
            b.hold_base, b.return_floor = 0, 1
        if b.hold_after is not None and tx > b.hold_after:
            b.hold_base, b.hold_after = v.gs, None

    def _decide(self, b: NodeBooks, tx: int, fits: Callable[[Version], bool], by: Seen) -> None:
        """Versions of ``tx`` in dispute: the one the next intention's Gs fits is the genuine."""
        live = b.live(tx)
        if len(live) < 2:
            return
        genuine = [v for v in live if fits(v)]
        if len(genuine) != 1:
            return
        for v in live:
            if v is not genuine[0]:
                self._forge(
                    b,
                    v,
                    f"INTENTION tx {tx} amount {_j(v.amount)} Gs {_j(v.gs)} is "
                    f"not the supervisor's: its next intention (frame {by.frame}) shows "
                    f"it released {_j(genuine[0].amount)} or nothing for tx {tx}",
                )
                b.forged_uj += v.amount + max(0, v.gs - genuine[0].gs)

    def _forge(self, b: NodeBooks, v: Version, what: str) -> None:
        v.forged = True
        b.booked_uj = None
        for seen in v.frames:
            self._flag(b, seen, what)

    def _admit(self, b: NodeBooks, m: Admit, flag: Flag) -> None:
        """The node starts afresh at the supervisor's counters: older frames move nothing."""
        b.admits += 1
        tx = self._tx(b, m.tx)
        if b.newest_tx is not None and tx < b.newest_tx:
            flag(f"ADMIT at tx {tx}, behind tx {b.newest_tx} already begun")
            return
        b.newest_tx = tx
        if (b.join_nonces and m.nonce not in b.join_nonces) or m.nonce == b.admitted:
            return  # answers no JOIN on the bus, or a JOIN already answered: the node ignores it
        b.admitted = m.nonce
        seq = self._seq(b, m.seq)
        b.newest_return, b.return_base, b.return_floor = seq, seq, seq + 1
        b.returns = {q: v for q, v in b.returns.items() if q <= seq}  # the earlier life's
        b.hold_after, b.hold_base, b.forged_uj, b.starving = tx, None, 0, None

    def _stale(self, flag: Flag, what: str) -> None:
        """A frame of an older transaction: impossible in bus order from a correct supervisor,
        normal behind a channel that reorders (``reordered``), where receivers ignore it."""
        if self.reordered:
            self.stale += 1
        else:
            flag(what)

    # -- commands and outcomes ----------------------------------------------------------------
    def _command(self, b: NodeBooks, m: Commit | Abort, flag: Flag) -> None:
        tx, kind, amount = self._tx(b, m.tx), type(m).__name__.upper(), m.amount_mj * QUANTUM_UJ
        if b.newest_tx is not None and tx < b.newest_tx:
            self._stale(flag, f"{kind} for tx {tx} after tx {b.newest_tx} began")
            return
        live = b.live(tx)
        if b.newest_tx is not None and tx > b.newest_tx:
            flag(
                f"{kind} for tx {tx}, whose INTENTION never was on the bus (the capture "
                f"covers this node since before tx {b.newest_tx + 1})"
            )
            b.forged_uj += amount if isinstance(m, Commit) else 0
            return
        if live and tx not in b.acked:
            flag(f"{kind} for tx {tx}, which was never acknowledged")
        if live and amount not in {v.amount for v in live}:
            flag(f"{kind} for tx {tx} with another amount than its intention")
        self._reaction(b, tx)
        if isinstance(m, Commit):
            if tx in b.aborts:
                flag(f"COMMIT for tx {tx} after ABORT")
            b.commits.setdefault(tx, amount)
        else:
            if tx in b.commits:
                flag(f"ABORT for tx {tx} after COMMIT")
            b.aborts.add(tx)

    def _outcome(self, b: NodeBooks, m: Committed | Aborted, flag: Flag) -> None:
        tx = self._tx(b, m.tx)
        if isinstance(m, Committed):
            if tx in b.aborted:
                flag(f"COMMITTED tx {tx} after ABORTED")
            if tx not in b.committed and b.live(tx):
                b.booked_tx.add(tx)
                if b.booked_uj is not None:
                    b.booked_uj += b.amount(tx)
            b.committed.add(tx)
            released = b.released_max()
            if released is not None and b.booked() > released:
                flag(
                    f"node booked {_j(b.booked())}, the supervisor released at most "
                    f"{_j(released)}: energy created"
                )
        else:
            if tx in b.committed:
                flag(f"ABORTED tx {tx} after COMMITTED")
            b.aborted.add(tx)

    # -- returns ------------------------------------------------------------------------------
    def _return(self, b: NodeBooks, m: Return, seen: Seen, flag: Flag) -> None:
        seq, amount = self._seq(b, m.seq), m.amount_mj * QUANTUM_UJ
        b.return_frames.add(seq)
        if b.return_floor is None:
            b.return_floor = seq
        versions = b.returns.setdefault(seq, [])
        live = _live(versions)
        for v in live:
            if v.amount == amount:
                v.frames.append(seen)
                self._copy(b, seq, seen)
                return
        limit = b.holdable(exclude=seq)
        if limit is not None and amount > limit:
            flag(f"RETURN {seq} of {_j(amount)}, but the node can hold at most {_j(limit)}")
            return
        if live:
            newest = b.newest_return
            if newest is not None and newest > seq:
                flag(f"RETURN {seq} re-used with another amount after return {newest} began")
                return
            ack = b.return_acks.get(seq)
            if ack is None or ack.frame < live[0].frames[0].frame:
                flag(
                    f"RETURN {seq} re-used with another amount while frame "
                    f"{live[0].frames[0].frame} was outstanding"
                )
                return
            for v in live:
                self._forge(
                    b,
                    v,
                    f"RETURN {seq} of {_j(v.amount)} is not the node's: the "
                    f"supervisor acknowledged it (frame {ack.frame}), yet the node "
                    f"still had return {seq} to make ({_j(amount)}, frame {seen.frame})",
                )
        versions.append(Version(amount, 0, [seen]))
        if b.newest_return is None or seq > b.newest_return:
            b.newest_return = seq
            prev = b.return_acks.get(seq - 1)
            b.starving = None
            if prev is not None and not self.reordered:
                b.starving = Starving(seq, prev, seen.frame)

    def _copy(self, b: NodeBooks, seq: int, seen: Seen) -> None:
        if b.starving is not None and b.starving.seq == seq:
            b.starving.last_copy, b.starving.counted = seen.frame, False

    def _reaction(self, b: NodeBooks, tx: int) -> None:
        """The supervisor answered an ACK of this node: did it also hear the return before?"""
        s = b.starving
        if s is None or s.counted or b.last_ack.get(tx, 0) < s.last_copy:
            return
        s.counted, s.evidence = True, s.evidence + 1
        if s.evidence >= STARVED:
            self._flag(
                b,
                s.ack,
                f"RETURN_ACK {s.seq - 1} was not the supervisor's: it left "
                f"RETURN {s.seq} unanswered {s.evidence} times while answering this "
                f"node, so it never credited return {s.seq - 1}",
            )
            b.starving = None

    def _return_ack(self, b: NodeBooks, m: ReturnAck, seen: Seen, flag: Flag) -> None:
        seq = self._seq(b, m.seq)
        if seq not in b.return_frames and b.return_floor is not None and seq >= b.return_floor:
            flag(f"RETURN_ACK {seq} before any RETURN {seq} on the bus")
            return
        b.returns_acked.add(seq)
        b.return_acks.setdefault(seq, seen)
        if b.starving is not None and b.starving.seq == seq:
            b.starving = None

    # -- result -------------------------------------------------------------------------------
    def finish(self) -> None:
        for b in self.nodes.values():
            for tx, versions in b.intentions.items():
                live = _live(versions)
                if len(live) > 1:
                    first = live[0].frames[0]
                    for v in live[1:]:
                        self._flag(
                            b,
                            v.frames[0],
                            f"INTENTION tx {tx} with another amount or "
                            f"Gs than frame {first.frame}: one of the two is forged",
                        )
        self.violations.sort(key=lambda v: v.frame)
        if self.initial is None:
            return
        net = sum(b.booked() - b.acked_returns() for b in self.nodes.values())
        if net > self.initial:
            self.violations.append(
                Violation(
                    self.frames,
                    None,
                    None,
                    f"net energy granted on the bus {_j(net)} exceeds the initial "
                    f"{_j(self.initial)}",
                    "",
                )
            )

    @property
    def channels(self) -> bool:
        """Whether the canergy frames so far came from more than one channel."""
        return len({channel for channel, _ in self.nodes}) > 1

    def report(self) -> dict[str, Any]:
        many = self.channels
        return {
            "frames": self.frames,
            "foreign_frames": self.foreign,
            "damaged_frames": self.damaged,
            "stale_frames": self.stale,
            "nodes": {
                str(node_label(ch, n, many)): b.report()
                for (ch, n), b in sorted(self.nodes.items())
            },
            "violations": [v.as_json(many) for v in self.violations],
            "passive": not self.violations,
        }
