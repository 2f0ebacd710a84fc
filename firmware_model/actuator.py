"""An energy-aware actuator: draws power from the usable budget and halts exactly at zero.

Power is constant or a profile of ``(time_s, watts)`` rows from a CSV file, held until the
next row and repeated after the last. Energy is counted in µJ with the sub-µJ remainder
carried, so nothing is rounded away or invented.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from firmware_model.profile_csv import read_rows


@dataclass(frozen=True, slots=True)
class PowerProfile:
    """Piecewise-constant power in µW: ``steps`` of ``(start_us, power_uw)``, repeating."""

    steps: tuple[tuple[int, int], ...]
    period_us: int

    @classmethod
    def constant(cls, watts: float) -> PowerProfile:
        if watts < 0:
            raise ValueError("power must be >= 0 W")
        return cls(((0, round(watts * 1e6)),), 1)

    @classmethod
    def from_csv(cls, path: Path) -> PowerProfile:
        """Rows ``time_s,watts`` (a header row is allowed); times increasing from 0."""
        rows = read_rows(path, "watts", 0, 1e9)
        steps = [(round(t * 1e6), round(w * 1e6)) for t, w in rows]
        if len({t for t, _ in steps}) < len(steps):
            raise ValueError(f"{path}: two rows less than 1 µs apart")
        last = steps[-1][0]
        period = last + (last - steps[-2][0] if len(steps) > 1 else 1_000_000)
        return cls(tuple(steps), period)

    def power_uw(self, t_us: int) -> int:
        t = t_us % self.period_us
        power = self.steps[0][1]
        for start, p in self.steps:
            if start > t:
                break
            power = p
        return power


@dataclass(slots=True)
class Actuator:
    """Integrates power over time into the energy it needs from the budget."""

    profile: PowerProfile
    started_us: int
    last_us: int
    remainder: int = 0
    """Energy owed below 1 µJ, in µW·µs (pJ)."""
    halted: bool = False
    drawn_uj: int = 0

    def need(self, now_us: int) -> int:
        """µJ the actuator wants for the time since the last call (power sampled at its start)."""
        dt = max(0, now_us - self.last_us)
        power = self.profile.power_uw(self.last_us - self.started_us)
        self.last_us = now_us
        total = power * dt + self.remainder
        self.remainder = total % 1_000_000
        return total // 1_000_000

    def run(self, granted_uj: int, wanted_uj: int) -> None:
        """Run on what the budget gave; halt (this tick) when it gave less than wanted."""
        self.drawn_uj += granted_uj
        self.halted = granted_uj < wanted_uj
        if self.halted:
            self.remainder = 0  # a halted actuator does not keep a debt
