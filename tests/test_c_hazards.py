"""The paper's hazards (tests/test_hazards.py) replayed with the C client in the harness.

The supervisor stays Python's; node 1 is the C client, fed through the C decoder, its power
losses real restarts from the NV bytes it asked to have written. Each scenario must stay exactly
passive, and must unfold frame for frame, persist for persist, as it does with Python's client.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
from support.c_binding import CClient, c_view
from support.harness import Harness
from support.hazards import HAZARDS

from canergy.core import Action, Persist, Send


class TracedHarness(Harness):
    """Records every frame sent and every persist, in order, by either side."""

    def __init__(self, c_client: bool) -> None:
        super().__init__("hardened")
        self.trace: list[object] = []
        if c_client:
            self.clients[1] = CClient(1, timing=self.timing)  # type: ignore[assignment]

    def _take(self, actions: list[Action]) -> list[Action]:
        self.trace += [
            a.message if isinstance(a, Send) else a
            for a in actions
            if isinstance(a, Send | Persist)
        ]
        return super()._take(actions)


def replay(hazard: Callable[[Harness], None], c_client: bool) -> TracedHarness:
    h = TracedHarness(c_client)
    hazard(h)
    return h


@pytest.mark.parametrize("hazard", sorted(HAZARDS))
def test_c_client_stays_passive(hazard: str) -> None:
    h = replay(HAZARDS[hazard], c_client=True)
    assert h.ledger.dissipated == 0, f"hazard ({hazard}) with the C client"


@pytest.mark.parametrize("hazard", sorted(HAZARDS))
def test_c_client_replays_like_python(hazard: str) -> None:
    c = replay(HAZARDS[hazard], c_client=True)
    p = replay(HAZARDS[hazard], c_client=False)
    assert c.trace == p.trace
    assert c.ledger == p.ledger
    assert c.sup.state == p.sup.state
    assert c_view(c.client().state) == c_view(p.client().state)
    assert c.to_client == p.to_client and c.to_sup == p.to_sup
