"""What the core asks its caller to do, and what it reports. All frozen dataclasses."""

from __future__ import annotations

from dataclasses import dataclass

from canergy.core.state import Outcome
from canergy.frozen import fast_init
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, Message


@fast_init
@dataclass(frozen=True, slots=True)
class Send:
    """Put this message on the bus."""

    message: Message


@fast_init
@dataclass(frozen=True, slots=True)
class Persist:
    """Write the non-volatile record now, before any following ``Send`` leaves."""


@fast_init
@dataclass(frozen=True, slots=True)
class Acknowledged:
    """Supervisor: the node holds the intention; call ``commit`` or ``abort``."""

    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Resolved:
    """Supervisor: transaction ``tx`` ended with ``outcome`` for ``amount`` µJ."""

    node: int
    tx: int
    outcome: Outcome
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class ReturnCredited:
    """Supervisor: credited return ``seq`` of ``amount`` µJ to the usable budget."""

    node: int
    seq: int
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class Admitted:
    """Supervisor: a node without books asked to join and was sent the counters ``tx``/``seq``
    (anything open was written off first)."""

    node: int
    tx: int
    seq: int


@fast_init
@dataclass(frozen=True, slots=True)
class AheadOfImage:
    """Supervisor: a start found the counts of node ``node``, admitted afresh and holding nothing
    since, ``numbers`` debit numbers past C + 1: it started from an image older than that
    admission, and what the node drew since cannot be told; ``amount`` µJ (the most that many
    draws can take: a start uses a number too, so each is a draw at most) moved from Us to Gs,
    a loss (``witnessed.take_counts``)."""

    node: int
    numbers: int

    @property
    def amount(self) -> int:
        return self.numbers * AMOUNT_MAX_MJ * QUANTUM_UJ


@fast_init
@dataclass(frozen=True, slots=True)
class IntentionRefused:
    """Client: did not acknowledge intention ``tx``: it would take the usable budget past what
    the record holds (``USABLE_MAX_UJ``)."""

    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class ClientCommitted:
    """Client: committed ``tx``, ``amount`` µJ now usable; ``by_timeout`` if no command came."""

    node: int
    tx: int
    amount: int
    by_timeout: bool


@fast_init
@dataclass(frozen=True, slots=True)
class ClientAborted:
    """Client: aborted ``tx``."""

    node: int
    tx: int


@fast_init
@dataclass(frozen=True, slots=True)
class Credited:
    """Client: the supervisor's delivered count paid back ``amount`` µJ written off earlier."""

    node: int
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class RolledBack:
    """Client (paper variant): undid a timeout-commit of ``tx``, removing ``amount`` µJ."""

    node: int
    tx: int
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class ReturnAcknowledged:
    """Client: the supervisor confirmed return ``seq``."""

    node: int
    seq: int


Action = (
    Send
    | Persist
    | Acknowledged
    | Admitted
    | AheadOfImage
    | Resolved
    | ReturnCredited
    | ClientCommitted
    | ClientAborted
    | Credited
    | RolledBack
    | ReturnAcknowledged
    | IntentionRefused
)
