"""Energy from a cumulative counter object: on the drive, or on a power-meter node on the bus.

A counter that wraps (``bits`` wide) is read as the difference between two readings modulo its
range. Where the drive could have drawn a whole range or more between two readings (the envelope
times the time between them), the difference is ambiguous: the largest value the envelope allows
is charged, never the smallest. Integers only: µJ, µs, fW.
"""

from __future__ import annotations

from dataclasses import dataclass

from canergy.cia402.meter import FW_US_PER_UJ

COUNTER_KEY = 0x1_0000
"""Where the counter's raw value travels among a drive's TPDO values (beyond any OD index)."""


@dataclass(frozen=True, slots=True)
class CounterConfig:
    """Where the counter is and what one count is."""

    index: int
    subindex: int = 0
    node: int | None = None
    """The power-meter node that holds it; None: the drive itself."""
    bits: int = 32
    unit_uj: int = 1
    """µJ per count."""

    @property
    def range_uj(self) -> int:
        return (1 << self.bits) * self.unit_uj

    def describe(self) -> str:
        where = "the drive" if self.node is None else f"node {self.node}"
        return f"0x{self.index:04X}:{self.subindex} on {where}"


@dataclass(slots=True)
class CounterMeter:
    """Turns counter readings into µJ drawn since the previous reading."""

    config: CounterConfig
    last_raw: int | None = None
    last_us: int | None = None
    metered_uj: int = 0
    readings: int = 0
    ambiguous: int = 0
    """Readings whose difference the counter's range could not tell (charged at the most)."""

    def sample(self, now: int, raw: int, envelope_fw: int) -> int:
        """A reading at ``now`` (µs, host time); ``envelope_fw``: the most the drive could draw
        since the previous one. Returns the µJ drawn in between."""
        c = self.config
        raw &= (1 << c.bits) - 1
        self.readings += 1
        drawn = 0
        if self.last_raw is not None and self.last_us is not None:
            drawn = ((raw - self.last_raw) % (1 << c.bits)) * c.unit_uj
            most = -(-envelope_fw * max(0, now - self.last_us) // FW_US_PER_UJ)
            if most >= c.range_uj:  # whole turns of the counter may hide between readings
                self.ambiguous += 1
                drawn += (most - drawn) // c.range_uj * c.range_uj
        self.last_raw, self.last_us = raw, now
        self.metered_uj += drawn
        return drawn
