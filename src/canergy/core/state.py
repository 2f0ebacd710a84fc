"""Small frozen, hashable protocol states (a model checker stores millions of them)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from canergy.frozen import fast_init


class Phase(IntEnum):
    """Where a transaction stands, on either side."""

    IDLE = 0
    WAIT_ACK = 1  # supervisor: intention sent
    ACKED = 2  # supervisor: intention acknowledged, awaiting the local decision
    WAIT_CONFIRM = 3  # supervisor: commit/abort sent
    WAIT_STATUS = 4  # supervisor (paper): status request sent
    AWAIT_COMMAND = 5  # client (paper): intention acknowledged
    AWAIT_SUPERVISOR = 6  # client (paper): committed or aborted, awaiting the final ACK
    JOINING = 7  # client (hardened): no valid record; JOIN sent, awaiting ADMIT
    RESUMING = 8  # client (witnessed): started with a record; RESUME sent, awaiting ADMIT
    SYNCING = 9  # witnessed: supervisor: started, SYNC sent; client: SYNC answered, awaiting ADMIT
    SYNC_BOOKS = 10  # supervisor (witnessed): the node's Rc taken, awaiting its counts


SYNC_PHASES = frozenset({Phase.SYNCING, Phase.SYNC_BOOKS})
"""A supervisor's session in these waits for its node to confirm the books after a start: the
supervisor grants nothing to anyone meanwhile (``Supervisor.unconfirmed``)."""


class Decision(IntEnum):
    NONE = 0
    COMMIT = 1
    ABORT = 2


class Outcome(IntEnum):
    """How a transaction ended (client's record, or the supervisor's resolution)."""

    NONE = 0
    COMMITTED = 1
    ABORTED = 2
    SETTLED = 3  # client: skipped over, settled by the supervisor's delivered count
    WRITTEN_OFF = 4  # supervisor: gave up, counted as delivered


@fast_init
@dataclass(frozen=True, slots=True)
class Session:
    """The supervisor's record for one node. Energies in µJ.

    ``reserved`` is Ts; ``delivered`` is Gs, all energy that left the supervisor's books for this
    node (committed, written off, or in the paper variant lost with a reset).
    ``returns_credited`` is the number of the last RETURN credited. ``tries`` and ``deadline``
    are volatile. Witnessed rules: ``resume_*`` is the last RESUME answered (its nonce, the
    node's debit number and the number it voided; ``resume_to`` 0: none yet, as no answer voids
    number 0), so that a re-sent copy gets the same answer; ``witness`` is W, the highest
    transaction the node has shown it persisted (a transaction begins only within
    ``Timing.window`` of it), and ``sync_nonce`` the nonce of the SYNC this start sent (both
    volatile: every start sets them again); ``resync`` (volatile): the SYNC is a re-sync of this
    one session (``witnessed.resync_session``), which no other session waits for; ``join_*`` is the
    last JOIN admitted (its nonce and the k and C its ADMIT carried; ``join_seq`` 0: none yet,
    as every admission voids a number above 0), so that a copy of it gets the same ADMIT
    rather than a second admission.
    """

    node: int
    phase: Phase = Phase.IDLE
    tx: int = 0
    reserved: int = 0
    delivered: int = 0
    decision: Decision = Decision.NONE
    returns_credited: int = 0
    returned: int = 0
    tries: int = 0
    deadline: int | None = None
    resume_nonce: int = 0
    resume_from: int = 0
    resume_to: int = 0
    witness: int = 0
    sync_nonce: int = 0
    join_nonce: int = 0
    join_tx: int = 0
    join_seq: int = 0
    resync: bool = False


@fast_init
@dataclass(frozen=True, slots=True)
class SupervisorState:
    """Usable budget Us, energy injected from outside since start, energy withdrawn to outside
    (a gateway handing its budget back upstream), and one session per node."""

    initial: int
    usable: int
    injected: int = 0
    sessions: tuple[Session, ...] = ()
    withdrawn: int = 0


@fast_init
@dataclass(frozen=True, slots=True)
class ClientState:
    """A client's record. Energies in µJ.

    ``credited`` is Rc, all energy ever added to ``usable`` by the protocol (commits, write-off
    paybacks; paper: minus roll-backs). ``last_tx``/``outcome`` is the last transaction resolved
    or settled. ``credited_unknown``: admitted without books, Rc is taken from the next fresh
    intention (nothing paid back); until then ``credited`` is 0 after a JOIN, and under the
    witnessed rules the Rc a record found behind held, a floor its SYNC books report.
    ``held_*``, ``phase``, ``nonce`` (of the pending JOIN or RESUME), ``timeout_commit`` and the
    deadlines are volatile. ``pending_draw`` (witnessed rules): the
    pending debit is a draw for the actuator, not a return.
    """

    node: int
    usable: int = 0
    credited: int = 0
    spent: int = 0
    last_tx: int = 0
    outcome: Outcome = Outcome.NONE
    return_seq: int = 0
    return_pending: int = 0
    credited_unknown: bool = False
    held_tx: int = 0
    held_amount: int = 0
    phase: Phase = Phase.IDLE
    timeout_commit: bool = False
    nonce: int = 0
    deadline: int | None = None
    return_deadline: int | None = None
    pending_draw: bool = False
