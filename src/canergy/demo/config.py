"""Settings of one demo run, checked when they are made."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from canergy.core import Timing
from canergy.faults import FaultProfile
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ
from canergy.units import UJ_PER_J, US_PER_S, format_energy

MAX_AMOUNT_UJ = AMOUNT_MAX_MJ * QUANTUM_UJ


@dataclass(frozen=True, slots=True)
class DemoConfig:
    """One run's settings; refused when a drawn grant could exceed one transaction's amount."""

    nodes: tuple[int, ...] = (1, 2, 3, 4, 5)
    transactions: int = 200
    duration_us: int = 300 * US_PER_S
    """Virtual-time limit."""
    initial: int = 10 * UJ_PER_J
    variant: str = "hardened"
    faults: FaultProfile = field(default_factory=FaultProfile)
    seed: int = 0
    resets: int = 2
    commit_ratio: float = 0.8
    log: Path | None = None
    timing: Timing = field(default_factory=Timing)

    def __post_init__(self) -> None:
        if self.largest_grant_uj > MAX_AMOUNT_UJ:
            raise ValueError(
                f"--initial {format_energy(self.initial)} over --transactions "
                f"{self.transactions} draws grants of up to {format_energy(self.largest_grant_uj)}"
                f", but one transaction carries at most {format_energy(MAX_AMOUNT_UJ)}: "
                "lower --initial or raise --transactions"
            )

    @property
    def grant_range_uj(self) -> tuple[int, int]:
        """Bounds of a grant drawn by the workload: 0.5-1.5 times half the initial budget spread
        over all transactions (rounded down to whole mJ when drawn)."""
        mean = max(2 * QUANTUM_UJ, self.initial // (2 * max(self.transactions, 1)))
        return mean // 2, mean * 3 // 2

    @property
    def largest_grant_uj(self) -> int:
        high = self.grant_range_uj[1]
        return high - high % QUANTUM_UJ
