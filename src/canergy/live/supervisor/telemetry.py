"""What the supervisor records of a node's TELEMETRY: the TELEMETRY table, sans-IO.

A node's TELEMETRY is information, not a protocol step: it moves no energy. The supervisor
keeps, per node, the level it last reported (µJ), when, its flags, when anything was last
heard from it, and the returns credited lately (a level reported before them may still show
them). A level above what the books let the node hold (delivered + reserved - returned, and the
returns credited within ``lost_after_us``) is evidence: no honest node reports it
(``BEYOND_BOOKS``); the TELEMETRY is taken all the same.

Written twice, once here and once in C (firmware/src/telemetry.c, canergy/telemetry.h), which
the compiled core runs on its frame path in the same call that decodes the frame;
tests/test_ccore_tables.py runs both side by side. The returns credited lately are kept in
at most ``RECENT_RETURNS`` entries: one more merges the oldest into the next (its amount then
lags as long as that one's), so a level is never judged against less than was credited.

Times in µs from the caller.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

from canergy.core.state import Session
from canergy.messages import LEVEL_MAX_MJ, QUANTUM_UJ

RECENT_RETURNS = 8
"""Returns credited lately kept per node (C: CANERGY_HEARD_RECENT)."""

TAKEN = 0x01
"""The TELEMETRY was taken: level, flags and times recorded."""
BEYOND_BOOKS = 0x02
"""Its level is above what the books let the node hold: evidence (C: CANERGY_HEARD_BEYOND)."""


@dataclass(slots=True)
class Heard:
    """One node's TELEMETRY record (C: struct canergy_heard)."""

    level: int | None = None
    """The level last reported, µJ (None: none yet, or the node restarted since)."""
    level_at: int | None = None
    flags: int = 0
    heard_at: int | None = None
    """When any frame of the node was last taken."""
    telemetry: int = 0
    """TELEMETRY frames taken."""
    recent: list[tuple[int, int]] = field(default_factory=list)
    """(time, µJ) of returns credited lately, oldest first, at most ``RECENT_RETURNS``."""


def _prune(h: Heard, now: int, lost_after_us: int) -> None:
    recent = h.recent
    while recent and now - recent[0][0] > lost_after_us:
        del recent[0]


def take_telemetry(
    h: Heard, s: Session, level_mj: int, flags: int, now: int, lost_after_us: int
) -> int:
    """A TELEMETRY of the node whose session is ``s``: recorded; its verdict (bits)."""
    _prune(h, now, lost_after_us)
    level = level_mj * QUANTUM_UJ
    holdable = s.delivered + s.reserved - s.returned
    lagging = sum(amount for _, amount in h.recent)
    verdict = TAKEN
    if level_mj < LEVEL_MAX_MJ and level > holdable + lagging:
        verdict |= BEYOND_BOOKS
    h.level, h.level_at, h.flags, h.heard_at = level, now, flags, now
    h.telemetry += 1
    return verdict


def credited(h: Heard, amount_uj: int, now: int, lost_after_us: int) -> None:
    """A return of ``amount_uj`` credited to the node."""
    _prune(h, now, lost_after_us)
    recent = h.recent
    if len(recent) == RECENT_RETURNS:  # the oldest lags as long as the next one
        recent[1] = (recent[1][0], recent[0][1] + recent[1][1])
        del recent[0]
    recent.append((now, amount_uj))


class TelemetryTable(Protocol):
    """The TELEMETRY table the service keeps: ``HeardTable``, or the compiled core's in C
    (``SupervisorCore.heard_table``)."""

    def of(self, node: int) -> Any:
        """The node's record: a ``Heard``, or the record in C with its attributes."""
        ...

    def telemetry(self, node: int, s: Session, level_mj: int, flags: int, now: int) -> int:
        """A TELEMETRY taken: the verdict's bits (``TAKEN``, ``BEYOND_BOOKS``)."""
        ...

    def credited(self, node: int, amount_uj: int, now: int) -> None:
        """A return credited by the books (a level reported before it may still show it)."""
        ...


class HeardTable:
    """Every node's record, in Python (the Python core's; the compiled core has its own in C:
    ``canergy.ccore.supervisor.CompiledHeard``)."""

    implementation = "python"

    def __init__(self, nodes: tuple[int, ...], lost_after_us: int) -> None:
        self.records = {n: Heard() for n in nodes}
        self.lost_after_us = lost_after_us

    def of(self, node: int) -> Heard:
        return self.records[node]

    def telemetry(self, node: int, s: Session, level_mj: int, flags: int, now: int) -> int:
        return take_telemetry(self.records[node], s, level_mj, flags, now, self.lost_after_us)

    def credited(self, node: int, amount_uj: int, now: int) -> None:
        credited(self.records[node], amount_uj, now, self.lost_after_us)
