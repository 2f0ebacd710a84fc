"""One node's transactions as the bus shows them, kept in constant memory.

Fed canergy frames in bus order, a ``NodeTrack`` follows the newest transaction through its
phases (INTENTION, ACK, COMMIT or ABORT) to its outcome, counts commits, aborts, write-offs and
returns, and keeps the node's telemetry and its latest frames. A write-off is never a frame of its
own: the supervisor books a transaction as delivered when its re-sends ran out, so the bus shows
it when the node's next INTENTION carries a delivered count Gs grown by that amount without a
COMMITTED before it (or an ADMIT answers the node's JOIN while it was open). A transaction that
ends with neither is counted as aborted.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import Enum

from canergy.inspect.frames import Described
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
    Direction,
    Intention,
    Join,
    Return,
    ReturnAck,
    Telemetry,
)
from canergy.seqnum import unwrap

RAW_KEPT = 400
"""Latest frames kept per node for the raw view."""


class Phase(Enum):
    """Where the newest transaction is, as far as the bus shows."""

    INTENTION = "INTENTION"
    ACKED = "ACK"
    COMMIT = "COMMIT"
    ABORT = "ABORT"


class Ending(Enum):
    COMMITTED = "commit"
    ABORTED = "abort"
    WRITTEN_OFF = "write-off"


@dataclass(frozen=True, slots=True)
class Outcome:
    ending: Ending
    tx: int
    amount_uj: int
    at: float


@dataclass(slots=True)
class NodeTrack:
    channel: str
    node: int
    frames: int = 0
    damaged: int = 0
    """Frames for this node whose CRC failed (they move nothing)."""
    last_frame: float | None = None
    heard: float | None = None
    """Time of the node's own latest frame (client to supervisor)."""
    tx: int | None = None
    amount_uj: int = 0
    gs_uj: int | None = None
    """Delivered count Gs of the newest INTENTION (None before any)."""
    phase: Phase | None = None
    """The newest transaction's phase; None once it ended (or before any)."""
    opened: float = 0.0
    sends: int = 0
    """Copies of the open transaction's INTENTION on the bus."""
    commits: int = 0
    aborts: int = 0
    write_offs: int = 0
    granted_uj: int = 0
    """Committed and written-off amounts: what left the supervisor's books for the node."""
    returns: int = 0
    returned_uj: int = 0
    pending_return: tuple[int, int] | None = None
    """(number, µJ) of the latest RETURN not yet acknowledged."""
    return_seq: int | None = None
    level_uj: int | None = None
    flags: int = 0
    joining: bool = False
    last_outcome: Outcome | None = None
    raw: deque[Described] = field(default_factory=lambda: deque(maxlen=RAW_KEPT))

    def feed(self, d: Described, t: float) -> None:
        """One frame of this node (``d.message`` set, CRC good or not) seen at ``t``."""
        self.frames += 1
        self.last_frame = t
        self.raw.append(d)
        m = d.message
        if not d.crc_ok or m is None:
            self.damaged += 1
            return
        if m.TYPE.direction is Direction.TO_SUPERVISOR:
            self.heard = t
        if isinstance(m, Intention):
            self._intention(m, t)
        elif isinstance(m, Ack):
            if self._current(m.tx) and self.phase is Phase.INTENTION:
                self.phase = Phase.ACKED
        elif isinstance(m, Commit | Abort):
            if self._current(m.tx) and self.phase is not None:
                self.phase = Phase.COMMIT if isinstance(m, Commit) else Phase.ABORT
        elif isinstance(m, Committed):  # also a timeout-commit answering a late ABORT
            if self._current(m.tx) and self.phase is not None:
                self._end(Ending.COMMITTED, t)
        elif isinstance(m, Aborted):
            if self._current(m.tx) and self.phase is not None:
                self._end(Ending.ABORTED, t)
        elif isinstance(m, Return):
            self._return(m)
        elif isinstance(m, ReturnAck):
            self._return_ack(m)
        elif isinstance(m, Telemetry):
            self.level_uj, self.flags = m.level_mj * QUANTUM_UJ, m.flags
            self.joining = bool(m.flags & Telemetry.JOINING)
        elif isinstance(m, Join):
            self.joining = True
        elif isinstance(m, Admit):
            if self.phase is not None:  # the supervisor writes off what was open, then admits
                self._end(Ending.WRITTEN_OFF, t)
            self.tx = self._widen_tx(m.tx)
            self.joining = False
            self.pending_return, self.return_seq = None, None

    def _widen_tx(self, wire: int) -> int:
        return wire if self.tx is None else unwrap(wire, self.tx, TX_BITS)

    def _current(self, wire: int) -> bool:
        return self.tx is not None and self._widen_tx(wire) == self.tx

    def _intention(self, m: Intention, t: float) -> None:
        tx = self._widen_tx(m.tx)
        gs = m.delivered_mj
        if self.gs_uj is not None:
            gs = unwrap(gs, self.gs_uj // QUANTUM_UJ, DELIVERED_BITS)
        gs *= QUANTUM_UJ
        if self.tx is not None and tx <= self.tx:
            if tx == self.tx and self.phase is not None:
                self.sends += 1
            return  # a re-send of an ended transaction, or a late copy of an older one
        if self.phase is not None:
            grew = self.gs_uj is not None and gs - self.gs_uj >= self.amount_uj
            self._end(Ending.WRITTEN_OFF if grew else Ending.ABORTED, t)
        self.tx, self.amount_uj, self.gs_uj = tx, m.amount_mj * QUANTUM_UJ, gs
        self.phase, self.opened, self.sends = Phase.INTENTION, t, 1

    def _end(self, ending: Ending, t: float) -> None:
        assert self.tx is not None
        if ending is Ending.COMMITTED:
            self.commits += 1
        elif ending is Ending.ABORTED:
            self.aborts += 1
        else:
            self.write_offs += 1
        if ending is not Ending.ABORTED:
            self.granted_uj += self.amount_uj
        self.phase = None
        self.last_outcome = Outcome(ending, self.tx, self.amount_uj, t)

    def _return(self, m: Return) -> None:
        seq = m.seq if self.return_seq is None else unwrap(m.seq, self.return_seq, SEQ_BITS)
        if self.return_seq is None or seq > self.return_seq:
            self.pending_return = (seq, m.amount_mj * QUANTUM_UJ)

    def _return_ack(self, m: ReturnAck) -> None:
        pending = self.pending_return
        if pending is None:
            return
        seq, amount = pending
        if unwrap(m.seq, seq, SEQ_BITS) == seq:
            self.returns += 1
            self.returned_uj += amount
            self.return_seq, self.pending_return = seq, None
