"""What no honest node sends, judged by the supervisor's books alone (no key needed): a level or
a fresh debit above what the books let the node hold, an answer to a transaction never begun.

Sans-IO: the session's books, the returns credited lately, the message."""

from __future__ import annotations

from canergy.core.state import Session
from canergy.messages import (
    LEVEL_MAX_MJ,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    Aborted,
    Ack,
    Committed,
    Debit,
    Message,
    Return,
    Telemetry,
)
from canergy.seqnum import unwrap
from canergy.units import format_energy


def impossible(msg: Message, s: Session, lagging_uj: int) -> str | None:
    """Why ``msg`` cannot come from the honest node whose session is ``s`` (None: it can).
    ``lagging_uj``: returns credited lately, which a level reported before them may still
    show."""
    holdable = s.delivered + s.reserved - s.returned
    if isinstance(msg, Telemetry):
        level = msg.level_mj * QUANTUM_UJ
        if msg.level_mj < LEVEL_MAX_MJ and level > holdable + lagging_uj:
            return f"reports {format_energy(level)}, its books allow {format_energy(holdable)}"
    elif isinstance(msg, Debit) and msg.flags & (Debit.SYNC | Debit.BOOKS):
        return None  # books and counts: no amount the node debits
    elif isinstance(msg, Return | Debit):
        fresh = unwrap(msg.seq, s.returns_credited, SEQ_BITS) == s.returns_credited + 1
        amount = msg.amount_mj * QUANTUM_UJ
        verb = "returns" if isinstance(msg, Return) else "debits"
        if fresh and amount > holdable:
            return f"{verb} {format_energy(amount)}, it can hold {format_energy(holdable)}"
    elif isinstance(msg, Ack | Committed | Aborted) and unwrap(msg.tx, s.tx, TX_BITS) > s.tx:
        return f"answers transaction {unwrap(msg.tx, s.tx, TX_BITS)}, never begun"
    return None
