"""What no honest node sends, judged by the supervisor's books alone (no key needed): a fresh
debit above what the books let the node hold, an answer to a transaction never begun (a level
above them: the TELEMETRY table's verdict, ``telemetry.BEYOND_BOOKS``, worded here).

Sans-IO: the session's books, the message."""

from __future__ import annotations

from canergy.core.common import never_begun
from canergy.core.state import Session
from canergy.messages import (
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    Aborted,
    Ack,
    Committed,
    Debit,
    Message,
    Return,
)
from canergy.seqnum import unwrap
from canergy.units import format_energy


def holdable(s: Session) -> int:
    """What the books let the node whose session is ``s`` hold, µJ."""
    return s.delivered + s.reserved - s.returned


def beyond_books(level_mj: int, s: Session) -> str:
    """A level the TELEMETRY table found beyond the books (``telemetry.BEYOND_BOOKS``)."""
    level = format_energy(level_mj * QUANTUM_UJ)
    return f"reports {level}, its books allow {format_energy(holdable(s))}"


def impossible(msg: Message, s: Session) -> str | None:
    """Why ``msg``, a frame to the supervisor other than a TELEMETRY, cannot come from the
    honest node whose session is ``s`` (None: it can)."""
    if isinstance(msg, Debit) and msg.flags & (Debit.SYNC | Debit.BOOKS):
        return None  # books and counts: no amount the node debits
    elif isinstance(msg, Return | Debit):
        fresh = unwrap(msg.seq, s.returns_credited, SEQ_BITS) == s.returns_credited + 1
        amount = msg.amount_mj * QUANTUM_UJ
        verb = "returns" if isinstance(msg, Return) else "debits"
        if fresh and amount > (held := holdable(s)):
            return f"{verb} {format_energy(amount)}, it can hold {format_energy(held)}"
    elif isinstance(msg, Ack | Committed | Aborted) and never_begun(msg.tx, s):
        return f"answers transaction {unwrap(msg.tx, s.tx, TX_BITS)}, never begun"
    return None
