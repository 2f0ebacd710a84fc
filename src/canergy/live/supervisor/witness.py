"""The node as the witness for its own id, and RETURNs credited only once the node confirms them.

Without a key anyone can send a RETURN in a node's name, and the supervisor would credit it:
energy out of nothing. The node sees every frame on the bus; one in its own name that it did not
send, or an answer to something it never asked, is counted and reported in its next TELEMETRY
(``witness``), which it sends at once. The supervisor:

- raises an intrusion for the node whenever its reported ``witness`` count moves, or its
  TELEMETRY contradicts itself (its return number going back: two streams in one name), and
  stops topping that node up for ``block_us`` after;
- holds every RETURN (``ReturnGate``) until the node's own TELEMETRY shows it has made that
  return and ``hold_us`` has passed since that TELEMETRY with no such evidence: a forged RETURN,
  or a forged TELEMETRY confirming it, is then refuted by the genuine node's report before it can
  be credited. The node reports at once when ``WITNESS_REPORT_AT`` frames went unreported, so its
  8-bit count never hides a whole turn;
- holds the same way a RESUME (witnessed rules) whose pending return the core would credit (its
  number the next one): a forged RESUME is a forged RETURN too. Any RESUME resets the baseline
  its return number is judged by (a node started from an older record goes back, honestly);
- resynchronises returns: when the node's confirmed number is past the next one the supervisor
  expects (someone acknowledged a return in the supervisor's name while it was away), the missed
  numbers are credited as 0 mJ, so the node's later returns are credited again. What they held is
  lost (dissipated), never created.

Sans-IO: times in µs from the caller. Counters are unwrapped against the supervisor's own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from canergy.messages import (
    SEQ_BITS,
    WITNESS_BITS,
    Admit,
    Debit,
    Return,
    ReturnAck,
    Telemetry,
    ToClient,
)
from canergy.seqnum import unwrap, wrap

WITNESS_REPORT_AT = 128
"""A node reports at once once this many witnessed frames went unreported, so two reports never
differ by a whole turn of the 8-bit count; a count that moved by more went back: the node
restarted (its count starts at 0 again)."""

WITNESS_GAP_US = 10_000
"""A node brings its next TELEMETRY forward for a frame in its name no sooner than this after
its last one (the C node: ``CANERGY_WITNESS_GAP_US``; a gateway's upstream leg, Python's and
the C port's, the same). Two nodes on one id see each other's reports in their own name:
reported at once, they would answer each other with no pause (rv3 measured 9,102 frames/s on
the virtual bus, more than a 500 kbit/s bus carries). With the gap each sends at most one early
report per 10 ms, and a refutation still reaches the supervisor 10 ms after the forgery at the
latest, well inside its RETURN and JOIN holds (500 ms by default)."""

RETURN_HOLD_MIN_US = 100_000
"""The least hold (``--return-hold``, ``ServiceConfig.return_hold_us``): the node must have the
time to refute a forged RETURN, or a forged TELEMETRY confirming it. It reports at the frame that
reveals the forgery (the emulated node in the loop pass that took it, the C node at its next
poll), 0.2-40 ms on python-can's virtual bus on a loaded 2-core machine (docs/security.md), and
at most ``WITNESS_GAP_US`` later after a report of its own: 100 ms is twice that, and twice the
default response timeout (50 ms). A shorter hold lets a forged
RETURN through before the genuine report arrives."""


@dataclass(slots=True)
class ClientWitness:
    """A client's side (an emulated node, a gateway's upstream leg; the C node in node.c does
    the same): the frames it saw in its own name that it did not send."""

    join_nonce: int | None = None
    """The nonce of this start's JOIN or RESUME: an ADMIT that does not echo it was not for
    us."""
    count: int = 0
    reported: int = 0
    """The count its last TELEMETRY carried."""

    def never_asked(self, msg: ToClient, return_seq: int) -> bool:
        """An answer to something the client never sent: a RETURN_ACK for a return number it has
        not reached, an ADMIT that does not echo its JOIN's nonce (duplicates of genuine answers
        are not counted: a lossy bus makes them)."""
        if isinstance(msg, ReturnAck):
            return unwrap(msg.seq, return_seq, SEQ_BITS) > return_seq
        return isinstance(msg, Admit) and msg.nonce != self.join_nonce

    def seen(self) -> bool:
        """One more frame in its name; True: report now (``WITNESS_REPORT_AT`` unreported), so
        that no report is ever a whole turn of the 8-bit count after the last."""
        self.count += 1
        return self.count - self.reported >= WITNESS_REPORT_AT

    def report(self) -> int:
        """The count for a TELEMETRY about to leave, as the wire carries it."""
        self.reported = self.count
        return self.count % (1 << WITNESS_BITS)


@dataclass(slots=True)
class _Held:
    amount_mj: int
    since: int
    confirmed_at: int | None = None
    """When a TELEMETRY first showed the node had made this return: the hold runs from then,
    so the node has that long to refute a TELEMETRY that confirms a forged RETURN."""


@dataclass(slots=True)
class NodeWitness:
    """What one node's TELEMETRY has said, and its RETURNs waiting for it."""

    witness: int | None = None
    """The node's count as last reported (None: no report yet)."""
    return_seq: int | None = None
    """The highest return number the node reported (unwrapped)."""
    confirmed_at: int = 0
    evidence_at: int | None = None
    """When the node last reported frames in its name, or contradicted itself."""
    held: dict[int, _Held] = field(default_factory=dict)
    resume: tuple[Debit, _Held] | None = None
    """A RESUME whose pending return the core would credit, until the node confirms it."""
    resume_nonce: int | None = None
    """The nonce of the last RESUME seen: its copies leave the baseline as the first set it."""
    resynced: int = 0
    refuted: int = 0


class ReturnGate:
    """Per node: evidence from TELEMETRY, RETURNs held until confirmed (see the module doc)."""

    def __init__(self, hold_us: int, block_us: int) -> None:
        self.hold_us = hold_us
        self.block_us = block_us
        self.nodes: dict[int, NodeWitness] = {}
        self._holding: set[int] = set()
        """Nodes that may hold RETURNs (each one held was added here; emptied lazily), so the
        loop's every pass does not look at every node."""

    def holding(self) -> list[int]:
        """The nodes holding RETURNs, ascending."""
        nodes = self.nodes
        self._holding = {n for n in self._holding if nodes[n].held or nodes[n].resume}
        return sorted(self._holding)

    def _of(self, node: int) -> NodeWitness:
        return self.nodes.setdefault(node, NodeWitness())

    def telemetry(self, msg: Telemetry, credited: int, now: int) -> tuple[list[str], list[str]]:
        """A TELEMETRY: the evidence it carries, and what it says that is no evidence (frames
        the node saw before this supervisor heard from it; a restart), one line each."""
        w = self._of(msg.node)
        evidence: list[str] = []
        notes: list[str] = []
        if msg.flags & Telemetry.JOINING:
            return evidence, notes  # no books, no return number: nothing to compare yet
        seen = (msg.witness - (w.witness or 0)) % (1 << WITNESS_BITS)
        if w.witness is None and seen:
            notes.append(f"the node reports {seen} frame(s) in its name since it started")
        elif seen > WITNESS_REPORT_AT:
            notes.append("the node's witness count went back: it restarted")
        elif seen:
            evidence.append(f"the node saw {seen} frame(s) in its name that it did not send")
        w.witness = msg.witness
        seq = unwrap(msg.return_seq, max(credited, w.return_seq or 0), SEQ_BITS)
        if w.return_seq is not None and seq < w.return_seq:
            evidence.append(f"its TELEMETRY contradicts itself: return {seq} after {w.return_seq}")
        else:  # the node stands by the number: what it made is confirmed as of now
            w.return_seq, w.confirmed_at = seq, now
            for number, held in w.held.items():
                if number <= seq and held.confirmed_at is None:
                    held.confirmed_at = now
            resume = w.resume
            if resume and resume[0].seq == wrap(seq, SEQ_BITS) and resume[1].confirmed_at is None:
                resume[1].confirmed_at = now
        if evidence:
            self._refute(w, now)
        return evidence, notes

    def hold(self, msg: Return, credited: int, now: int) -> str | None:
        """A RETURN to hold until the node confirms it; evidence if it contradicts one held."""
        w = self._of(msg.node)
        seq = unwrap(msg.seq, credited, SEQ_BITS)
        if seq <= credited:
            return None  # an old number: the core re-acks it, no energy moves
        held = w.held.get(seq)
        if held is None:
            w.held[seq] = _Held(msg.amount_mj, now)  # confirmed by a later TELEMETRY only
            self._holding.add(msg.node)
        elif held.amount_mj != msg.amount_mj:
            self._refute(w, now)
            return f"two RETURNs numbered {seq}: {held.amount_mj} and {msg.amount_mj} mJ"
        return None

    def hold_resume(self, msg: Debit, credited: int, now: int, hold: bool) -> bool:
        """A RESUME: True when it is held (``hold``, and its pending return would be credited: a
        RETURN's number, next after ``credited``), until a TELEMETRY of the node shows that
        number. Any RESUME resets the return number the node's TELEMETRY is judged by."""
        w = self._of(msg.node)
        if msg.nonce != w.resume_nonce:  # a start: from an older record it goes back, honestly
            w.resume_nonce, w.return_seq = msg.nonce, None
        seq = unwrap(msg.seq, credited, SEQ_BITS)
        if not hold or seq != credited + 1 or not msg.amount_mj or msg.flags & Debit.DRAW:
            return False
        if w.resume is None or w.resume[0] != msg:
            w.resume = (msg, _Held(msg.amount_mj, now))
            self._holding.add(msg.node)
        return True

    def old(self, msg: Return, credited: int) -> bool:
        """A RETURN the core has credited already (its re-ack is harmless)."""
        return unwrap(msg.seq, credited, SEQ_BITS) <= credited

    def holds(self, node: int) -> bool:
        """A RETURN or a RESUME of ``node`` is held (``release`` may give something)."""
        w = self.nodes.get(node)
        return w is not None and bool(w.held or w.resume is not None)

    def release(self, node: int, credited: int, now: int) -> list[Return | Debit]:
        """The held RETURNs the node has confirmed and no evidence contradicts, in order, each
        missed number before them as a 0 mJ RETURN; then a held RESUME it has confirmed."""
        w = self.nodes.get(node)
        if w is None or w.return_seq is None:
            return []
        out: list[Return | Debit] = []
        for seq in sorted(w.held):
            held = w.held[seq]
            confirmed = held.confirmed_at
            ready = (
                confirmed is not None and seq <= w.return_seq and now >= confirmed + self.hold_us
            )
            if not ready or seq <= credited:
                if seq <= credited:
                    del w.held[seq]
                continue
            for missed in range(credited + 1, seq):
                out.append(Return(node, wrap(missed, SEQ_BITS), 0))
                w.resynced += 1
            out.append(Return(node, wrap(seq, SEQ_BITS), held.amount_mj))
            del w.held[seq]
            credited = seq
        if w.resume is not None:
            resume, held = w.resume
            if held.confirmed_at is not None and now >= held.confirmed_at + self.hold_us:
                out.append(resume)  # the core judges it against its count now
                w.resume = None
        return out

    def blocked(self, node: int, now: int) -> bool:
        """No top-ups for a node with recent evidence against its TELEMETRY."""
        w = self.nodes.get(node)
        return w is not None and w.evidence_at is not None and now < w.evidence_at + self.block_us

    def _refute(self, w: NodeWitness, now: int) -> None:
        """Evidence: every RETURN held so far is dropped (a genuine one is sent again)."""
        w.evidence_at = now
        w.refuted += len(w.held) + (w.resume is not None)
        w.held.clear()
        w.resume = None

    def next_release(self) -> int | None:
        if not self._holding:
            return None
        times = [
            h.confirmed_at + self.hold_us
            for n in self.holding()
            for h in [*self.nodes[n].held.values(), *self._resume_held(n)]
            if h.confirmed_at is not None
        ]
        return min(times, default=None)

    def resume_held(self, node: int) -> bool:
        """A RESUME of ``node`` is held (no grant for it meanwhile)."""
        w = self.nodes.get(node)
        return w is not None and w.resume is not None

    def _resume_held(self, node: int) -> list[_Held]:
        resume = self.nodes[node].resume
        return [] if resume is None else [resume[1]]

    def readmitted(self, node: int) -> None:
        """The node was admitted afresh: its return numbers start again from the supervisor's
        counters. Its witness count is kept (a JOIN forged in its name must not wipe the
        baseline it is judged by; a node that really restarted shows a count that went back)."""
        w = self.nodes.get(node)
        if w is not None:
            w.return_seq, w.confirmed_at = None, 0
            w.held.clear()
            w.resume = None

    def status(self, node: int) -> dict[str, int]:
        w = self.nodes.get(node)
        if w is None:
            return {}
        return {
            "returns_held": len(w.held),
            "returns_refuted": w.refuted,
            "returns_resynchronised": w.resynced,
        }
