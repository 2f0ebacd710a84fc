"""Charging by the host's clock at the largest envelope in force: the sound meter every guard
shares (a CiA 402 drive's in envelope mode and after a write behind it, a profile device's).
Sans-IO, integers: fW, µs, µJ (1 µJ = 1e15 fW·µs).

Each µs is charged at the envelope in force at its start; its owner raises ``fw`` at once when
an envelope is raised (``raise_to``), and a lowered envelope keeps counting until the device had
its latency to act on it (``lower``, ``held``). What is below a whole µJ is carried over. An
envelope found out late (a write behind the guard seen at a time already charged) is charged
back over that time (``back_charge``), against what each stretch of it was charged at, and its
whole µJ are the owner's to meter at once.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from canergy.cia402.meter import FW_US_PER_UJ

STRETCHES_KEPT = 64
"""Stretches of charged time at one envelope kept for ``back_charge`` (the oldest go first; a
stretch lasts until the envelope changes, so these cover far more than any late finding)."""


@dataclass(slots=True)
class ClockCharge:
    """Charged up to ``until`` (None: not charging yet) at ``fw``."""

    until: int | None = None
    fw: int = 0
    """The largest envelope in force since ``until``."""
    remainder: int = 0
    """fW·µs charged that do not make a whole µJ yet."""
    lowered_fw: int = 0
    lowered_until: int = 0
    """A lowered envelope still charged until the device has had time to act on it."""
    charged: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=STRETCHES_KEPT))
    """Where each recent stretch of charged time began and its envelope (it ends where the next
    begins, the last at ``until``)."""

    def start(self, at: int, fw: int) -> None:
        self.until, self.fw = at, fw

    def held(self, fw: int, now: int) -> int:
        """``fw``, or the lowered envelope while it still counts."""
        return max(fw, self.lowered_fw) if now < self.lowered_until else fw

    def lower(self, before_fw: int, until: int) -> None:
        """The envelope was ``before_fw`` and went down: it counts until ``until``."""
        self.lowered_fw, self.lowered_until = before_fw, until

    def raise_to(self, fw: int) -> None:
        """An envelope in force went up: charged from now."""
        self.fw = max(self.fw, fw)

    def run(self, now: int, in_force: Callable[[int], int]) -> int:
        """Charge up to ``now`` (a lowered envelope's end first); the whole µJ charged.
        ``in_force(t)``: the envelope in force at ``t``."""
        if self.until is None:
            return 0
        drawn = 0
        if self.until < self.lowered_until < now:
            drawn += self._to(self.lowered_until, in_force)
        if now > self.until:
            drawn += self._to(now, in_force)
        return drawn

    def back_charge(self, since: int, fw: int) -> int:
        """Envelope ``fw`` was in force from ``since`` on, found out only now: the time from
        ``since`` to ``until`` is charged again up to ``fw``, each stretch by what it lacks (time
        older than the stretches kept counts as charged at nothing); the whole µJ charged, at
        once (left in the remainder, they would count only when the clock next runs, and a host
        that exits first would never meter them)."""
        if self.until is None or since >= self.until:
            return 0
        end = self.until
        for begin, charged_fw in reversed(self.charged):
            if end <= since:
                break
            start = max(begin, since)
            self.remainder += max(0, fw - charged_fw) * (end - start)
            end = start
        else:
            if end > since:
                self.remainder += fw * (end - since)
        self._charged_up_to(since, fw)
        return self.owed(0)

    def owed(self, fw_us: int) -> int:
        """``fw_us`` fW·µs found owed now (time already charged, charged again): their whole µJ
        and the remainder's, for the owner to meter at once; what is below a µJ carried over."""
        drawn, self.remainder = divmod(self.remainder + fw_us, FW_US_PER_UJ)
        return drawn

    def _charged_up_to(self, since: int, fw: int) -> None:
        """The stretches from ``since`` on are charged at ``fw`` at least now: a later finding
        over the same time charges only what they still lack (each write behind the guard
        taken in after one stall is not charged over it again)."""
        kept: list[tuple[int, int]] = []
        for i, (begin, charged_fw) in enumerate(self.charged):
            end = self.charged[i + 1][0] if i + 1 < len(self.charged) else self.until
            assert end is not None
            if end <= since:
                kept.append((begin, charged_fw))
            elif begin < since:
                kept += [(begin, charged_fw), (since, max(charged_fw, fw))]
            else:
                kept.append((begin, max(charged_fw, fw)))
        if not kept or kept[0][0] > since:
            kept.insert(0, (since, fw))
        merged: list[tuple[int, int]] = []
        for begin, charged_fw in kept:
            if not merged or merged[-1][1] != charged_fw:
                merged.append((begin, charged_fw))
        self.charged.clear()
        self.charged.extend(merged[-STRETCHES_KEPT:])

    def _to(self, until: int, in_force: Callable[[int], int]) -> int:
        assert self.until is not None
        if not self.charged or self.charged[-1][1] != self.fw:
            self.charged.append((self.until, self.fw))
        self.remainder += self.fw * (until - self.until)
        drawn, self.remainder = divmod(self.remainder, FW_US_PER_UJ)
        self.until, self.fw = until, in_force(until)
        return drawn
