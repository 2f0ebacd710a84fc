"""The paper's hazards (a)-(e), each replayed as one scenario on both variants.

The same abstract steps drive both rule sets: ``paper`` ends with energy generated (negative
dissipation), ``hardened`` never goes below zero.
"""

from __future__ import annotations

import pytest
from support.harness import Harness
from support.hazards import HAZARDS


@pytest.mark.parametrize("hazard", sorted(HAZARDS))
def test_paper_generates_energy(hazard: str) -> None:
    h = Harness("paper")
    HAZARDS[hazard](h)
    assert h.ledger.dissipated < 0, f"hazard ({hazard}) should generate energy under paper rules"


@pytest.mark.parametrize("hazard", sorted(HAZARDS))
def test_hardened_stays_passive(hazard: str) -> None:
    h = Harness("hardened")
    HAZARDS[hazard](h)
    assert h.ledger.dissipated >= 0
    assert h.ledger.dissipated == 0, "no fault here loses energy for good under hardened rules"
