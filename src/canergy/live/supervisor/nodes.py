"""What the supervisor service keeps per node besides the core's session: what was heard of it,
its counters for the status and the grants it was asked for."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from canergy.bus_keys import node_name
from canergy.live.supervisor.grants import GrantRequest
from canergy.live.supervisor.telemetry import Heard


@dataclass(slots=True)
class NodeInfo:
    """What the service knows about a node besides the core's session."""

    heard: Heard | Any
    """What its TELEMETRY said and when it was heard (``telemetry.Heard``, or the compiled
    core's record of it in C: the same attributes)."""
    ended_at: int = -1
    committed: int = 0
    committed_uj: int = 0
    aborted: int = 0
    written_off: int = 0
    admitted: int = 0
    """JOINs answered: the node started without books (new, wiped or corrupted NV)."""
    returns: int = 0
    decode_errors: int = 0
    supervisor_frames: int = 0
    """Listen-only: frames in the supervisor's direction for this node (another supervisor's:
    what listen-only watches, no intrusion)."""
    requests: list[GrantRequest] = field(default_factory=list)
    """Grants asked for and not begun, oldest first (lists: a node holds few, and an empty
    deque takes 760 bytes against a list's 56)."""
    active_request: GrantRequest | None = None
    resumes: int = 0
    """Starts with books answered (witnessed rules: RESUME confirmed or found behind)."""
    found_behind: int = 0
    """Of them, records older than the books (a debit number below the supervisor's): the node
    was admitted afresh and what that record held was dropped."""
    synced: int = 0
    """Supervisor starts this node answered with its books and counts (witnessed rules)."""
    ahead_of_image_uj: int = 0
    """What starts moved from Us to Gs for this node's debits past the state file's (its counts
    afresh: the file older than its admission afresh; ``core.AheadOfImage``), a loss."""
    rules: str | None = None
    """The client rules its last TELEMETRY said it runs (``Telemetry.WITNESSED``; None: none
    heard yet)."""
    variant_mismatch: int = 0
    """Its TELEMETRY frames that said other rules than the supervisor's: granted nothing."""
    counts_ignored: int = 0
    """Counts outside a start the rules ignored (witnessed.counts_taken): an earlier start's,
    replayed or late; they move nothing."""
    resyncs: int = 0
    """Re-syncs of this node alone (witnessed rules): its window used up, or its counts
    ignored."""
    resynced_at: int | None = None
    """When the last of them began (µs)."""


def name_of(buses: tuple[str, ...], node: int) -> int | str:
    """A node as status, replies and the state file name it: its id on one bus (every reply),
    or ``bus/node`` over the buses ``buses`` names."""
    return node_name(buses, node) if buses else node


def lost(
    nodes: Mapping[int, NodeInfo],
    liveness: Callable[[int, int], bool] | None,
    lost_after_us: int,
    node: int,
    now: int,
) -> bool:
    """Whether ``node`` is lost at ``now``: ``liveness`` (the CANopen heartbeat watchdog, the
    guarded drives') says so, or it was not heard for ``lost_after_us``."""
    if liveness is not None and not liveness(node, now):
        return True
    heard = nodes[node].heard.heard_at
    return heard is None or now - heard > lost_after_us
