"""The protocol's messages as frozen dataclasses holding exactly what travels on the wire.

Counters are the wire's narrow wrapping values (``tx`` and ``seq`` 16 bits, ``delivered_mj``
24 bits); the receiving core widens them with serial-number arithmetic (``canergy.seqnum``).
Amounts travel in whole millijoules (the wire quantum, ``QUANTUM_UJ``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar

from canergy.frozen import fast_init

QUANTUM_UJ = 1000
"""One wire energy unit: amounts and the delivered count travel in millijoules."""


def quantize(amount: int) -> int:
    """``amount`` µJ rounded down to whole wire quanta (what a grant can carry)."""
    return amount - amount % QUANTUM_UJ


TX_BITS = 16
SEQ_BITS = 16
DELIVERED_BITS = 24
AMOUNT_MAX_MJ = 0xFFFF
"""Largest amount in one frame: 65.535 J."""

COUNTER_BOUND = 1 << 30
"""The theorem's bounded life (``canergy prove``, assumption 4): every 32-bit counter of a record
(a node's transaction and return numbers, the supervisor's and the client's) stays below this. A
record holding one at or beyond it is refused when it is loaded."""
COUNTER_END = COUNTER_BOUND - (1 << 16)
"""No rule moves a counter to this or beyond: a node's numbering ends one below it (the
supervisor begins no transaction and credits no return numbered here; a client takes neither).
A multiple of 2**16, so an admission's lift (a counter's low 16 bits under the larger high part
of the two) keeps counters below it."""


def counter_beyond(value: int) -> str:
    """Why a record's counter ``value`` (at or beyond ``COUNTER_BOUND``) is refused."""
    return f"{value} is beyond the bound 2^30 - 1 the proof assumes"


USABLE_MAX_UJ = 0xFFFF_FFFF
"""Most a client's record holds in its usable budget (the NV record's u32 µJ field): 4294.967295 J.
A supervisor never plans a node above it; a client refuses (does not acknowledge) an intention
that would take it there."""

MIN_NODE = 1
MAX_NODE = 127


class Direction(IntEnum):
    """Who sends a message; bit 3 of the type code."""

    TO_CLIENT = 0
    TO_SUPERVISOR = 1


class MsgType(IntEnum):
    """4-bit message type code carried in the CAN identifier (bit 3 = from client)."""

    INTENTION = 0x1
    COMMIT = 0x2
    ABORT = 0x3
    RETURN_ACK = 0x4
    STATUS_REQUEST = 0x5  # paper variant only
    FINAL_ACK = 0x6  # paper variant only
    ADMIT = 0x7  # hardened: a node without books joins at the supervisor's counters
    ACK = 0x9
    COMMITTED = 0xA
    ABORTED = 0xB
    RETURN = 0xC
    TELEMETRY = 0xD  # moves no energy; the protocol's safety never depends on it
    JOIN = 0xE  # hardened: a node without a valid NV record asks to be admitted
    DEBIT = 0xF  # witnessed: a numbered draw, a start's debit count (RESUME), a SYNC's answer

    @property
    def direction(self) -> Direction:
        return Direction.TO_SUPERVISOR if self & 0x8 else Direction.TO_CLIENT


@fast_init
@dataclass(frozen=True, slots=True)
class Intention:
    """INT: the supervisor reserved ``amount_mj`` for transaction ``tx``; ``delivered_mj`` is Gs."""

    TYPE: ClassVar[MsgType] = MsgType.INTENTION
    node: int
    tx: int
    amount_mj: int
    delivered_mj: int


@fast_init
@dataclass(frozen=True, slots=True)
class Commit:
    """COMMIT: move the reserved amount into the client's usable budget."""

    TYPE: ClassVar[MsgType] = MsgType.COMMIT
    node: int
    tx: int
    amount_mj: int


@fast_init
@dataclass(frozen=True, slots=True)
class Abort:
    """ABORT: discard the intention; the supervisor takes its reservation back."""

    TYPE: ClassVar[MsgType] = MsgType.ABORT
    node: int
    tx: int
    amount_mj: int


@fast_init
@dataclass(frozen=True, slots=True)
class ReturnAck:
    """RETACK: the supervisor has credited return number ``seq``."""

    TYPE: ClassVar[MsgType] = MsgType.RETURN_ACK
    node: int
    seq: int


@fast_init
@dataclass(frozen=True, slots=True)
class StatusRequest:
    """Paper variant: the supervisor asks what the client did with ``tx``."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS_REQUEST
    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class FinalAck:
    """Paper variant: the supervisor closes transaction ``tx``."""

    TYPE: ClassVar[MsgType] = MsgType.FINAL_ACK
    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Admit:
    """ADMIT: answer to JOIN(``nonce``): the supervisor's transaction and return counters.

    The node starts afresh from them, so every frame of its earlier life is below its counters
    and moves nothing; the supervisor has written off what was open. Witnessed rules: it also
    answers a RESUME or a SYNC's counts, and one that answers nothing the node asked (a nonce
    not its own) is a supervisor's start, SYNC(``nonce``, ``tx``, ``seq``): the node answers it
    with its books.
    """

    TYPE: ClassVar[MsgType] = MsgType.ADMIT
    node: int
    nonce: int
    tx: int
    seq: int


@fast_init
@dataclass(frozen=True, slots=True)
class Ack:
    """ACK: the client holds intention ``tx``."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Committed:
    """COMMITTED: the client committed ``tx`` (on command or by timeout)."""

    TYPE: ClassVar[MsgType] = MsgType.COMMITTED
    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Aborted:
    """ABORTED: the client aborted ``tx``."""

    TYPE: ClassVar[MsgType] = MsgType.ABORTED
    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Return:
    """RETURN: the client gave back ``amount_mj`` as return number ``seq``."""

    TYPE: ClassVar[MsgType] = MsgType.RETURN
    node: int
    seq: int
    amount_mj: int


@fast_init
@dataclass(frozen=True, slots=True)
class Join:
    """JOIN: the node has no valid record (new, wiped or corrupted); ``nonce`` is drawn at random
    at start so that only an ADMIT answering this very request is taken."""

    TYPE: ClassVar[MsgType] = MsgType.JOIN
    node: int
    nonce: int


@fast_init
@dataclass(frozen=True, slots=True)
class Debit:
    """DEBIT (witnessed rules), told apart by ``flags``:

    - a *draw* (``DRAW``): the node debited ``amount_mj`` for its actuator as debit number
      ``seq`` (the numbering RETURN uses), acknowledged by RETURN_ACK(``seq``); the actuator
      gets it only on the ack;
    - a *resume* (``START``, maybe ``DRAW``): the node started with books whose last debit number
      is ``seq``, ``amount_mj`` of it still unacknowledged (0: none; a draw when ``DRAW`` is
      set); it moves nothing until ADMIT(``nonce``) confirms them or finds them behind;
    - the two frames that answer a supervisor's start, SYNC(``nonce``), each bound to its nonce:
      *books* (``BOOKS``): the node's Rc in mJ, its low 16 bits in ``seq`` and its high 8 in
      ``amount_mj`` (with ``RC_UNKNOWN`` and both 0: the node was admitted without books and has
      taken no fresh intention since, so it holds nothing and knows no Rc); and *counts*
      (``START | SYNC``): the node's last debit number ``seq`` and, in ``amount_mj``, the last
      transaction it has settled (ltx, 16 bits on the wire); with ``RC_UNKNOWN`` too
      (``afresh``), the node was admitted afresh and has taken no fresh intention since, so its
      books cannot say what it received before (Rc unknown, or a floor its record kept).
    """

    TYPE: ClassVar[MsgType] = MsgType.DEBIT
    node: int
    nonce: int
    flags: int
    seq: int
    amount_mj: int

    DRAW: ClassVar[int] = 0x01
    """Flag: the amount is a draw for the actuator (credited to nobody), not a return."""
    START: ClassVar[int] = 0x02
    """Flag: the node's start (RESUME), not a draw."""
    SYNC: ClassVar[int] = 0x04
    """Flag, with ``START``: the counts answering a supervisor's SYNC (``amount_mj`` is ltx)."""
    BOOKS: ClassVar[int] = 0x08
    """Flag, alone: the books answering a supervisor's SYNC (Rc in ``seq`` and ``amount_mj``)."""
    RC_UNKNOWN: ClassVar[int] = 0x10
    """Flag, with ``BOOKS``: the node's Rc is unknown (admitted, no fresh intention since); with
    ``START | SYNC``: the counts of a node admitted afresh that has taken no fresh intention
    since (its books are unknown or a floor)."""

    @property
    def is_resume(self) -> bool:
        """A node's start: a RESUME, or the counts answering a SYNC."""
        return bool(self.flags & Debit.START)

    @property
    def is_counts(self) -> bool:
        return self.flags & ~Debit.RC_UNKNOWN == Debit.START | Debit.SYNC

    @property
    def afresh(self) -> bool:
        """Counts of a node admitted afresh that has taken no fresh intention since: its books
        cannot say what it received before its admission."""
        return self.flags == Debit.START | Debit.SYNC | Debit.RC_UNKNOWN

    @property
    def is_books(self) -> bool:
        return self.flags & ~Debit.RC_UNKNOWN == Debit.BOOKS

    @property
    def rc_unknown(self) -> bool:
        """Books of a node that knows no Rc (and holds nothing): they say nothing of Gs."""
        return self.flags == Debit.BOOKS | Debit.RC_UNKNOWN

    @property
    def pending_mj(self) -> int:
        """A RESUME's unacknowledged debit (none in the answer to a SYNC: it is voided)."""
        return 0 if self.flags & (Debit.SYNC | Debit.BOOKS) else self.amount_mj

    @property
    def credited_mj(self) -> int:
        """The books' Rc in mJ (24 bits)."""
        return self.seq | self.amount_mj << 16

    @staticmethod
    def books(node: int, nonce: int, credited_mj: int | None) -> Debit:
        """The books frame answering SYNC(``nonce``): Rc (24 bits, mJ), or None: Rc unknown."""
        if credited_mj is None:
            return Debit(node, nonce, Debit.BOOKS | Debit.RC_UNKNOWN, 0, 0)
        return Debit(node, nonce, Debit.BOOKS, credited_mj & 0xFFFF, credited_mj >> 16 & 0xFF)

    @staticmethod
    def counts(node: int, nonce: int, seq: int, last_tx: int, afresh: bool = False) -> Debit:
        """The counts frame answering SYNC(``nonce``): debit number and ltx (wire values);
        ``afresh``: admitted afresh, no fresh intention since (``Debit.afresh``)."""
        flags = Debit.START | Debit.SYNC | (Debit.RC_UNKNOWN if afresh else 0)
        return Debit(node, nonce, flags, seq, last_tx)


@fast_init
@dataclass(frozen=True, slots=True)
class Telemetry:
    """TELEMETRY: the client's usable level (24-bit mJ, saturating), status flags, its current
    return number (as its RETURN frames carry it) and how many frames it has seen in its own
    name that it did not send (``witness``, modulo 256). Information for grant policies and for
    the supervisor's checks: it moves no energy and the core never sees it.
    """

    TYPE: ClassVar[MsgType] = MsgType.TELEMETRY
    node: int
    level_mj: int
    flags: int = 0
    return_seq: int = 0
    witness: int = 0

    LOW: ClassVar[int] = 0x01
    """Flag: the level fell below the client's low-water mark."""
    HALTED: ClassVar[int] = 0x02
    """Flag: the actuator is halted (budget exhausted or not operational)."""
    JOINING: ClassVar[int] = 0x04
    """Flag: the node has no books yet and waits to be admitted."""
    WITNESSED: ClassVar[int] = 0x08
    """Flag: the node runs the witnessed client rules (a gateway: its rules above); absent, the
    hardened ones. A supervisor whose rules differ grants it nothing (the status and stderr say
    why). It moves no energy: one forged without a key can only withhold grants."""


LEVEL_MAX_MJ = (1 << 24) - 1
WITNESS_BITS = 8

NONCE_BITS = 16
SYNC_CONFIRMED = 0x8000
"""The ADMIT that confirms the answer to SYNC(n) carries n with this bit flipped (witnessed
rules): a SYNC re-sent with the same nonce and counters never reads as its own confirmation."""

ToClient = Intention | Commit | Abort | ReturnAck | StatusRequest | FinalAck | Admit
ToSupervisor = Ack | Committed | Aborted | Return | Join | Debit
Message = ToClient | ToSupervisor | Telemetry

MESSAGE_CLASSES: dict[MsgType, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Intention,
        Commit,
        Abort,
        ReturnAck,
        StatusRequest,
        FinalAck,
        Admit,
        Ack,
        Committed,
        Aborted,
        Return,
        Join,
        Telemetry,
        Debit,
    )
}
