"""The rule sets by name: ``hardened`` (default, H1), ``paper`` (literal Figs. 3-4) and
``witnessed`` (H1 with node records the supervisor witnesses: older copies found out)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from canergy.core import hardened, paper, witnessed
from canergy.core.table import ClientTable, SupervisorTable


@dataclass(frozen=True, slots=True)
class Variant:
    """A supervisor's and a client's transition table that work together."""

    name: str
    supervisor: SupervisorTable
    client: ClientTable
    lifts_tx: bool = False
    """A start lifts transaction numbers by ``Timing.window`` (witnessed)."""


VARIANTS: dict[str, Variant] = {
    "hardened": Variant("hardened", hardened.SUPERVISOR, hardened.CLIENT),
    "paper": Variant("paper", paper.SUPERVISOR, paper.CLIENT),
    "witnessed": Variant("witnessed", witnessed.SUPERVISOR, witnessed.CLIENT, lifts_tx=True),
}
RUNNABLE: dict[str, Variant] = {name: VARIANTS[name] for name in ("hardened", "paper")}
"""What the demo and the simulator run. ``witnessed`` (its actuator spends in acknowledged
whole-millijoule draws) runs in the checker, the live supervisor and emulator (``--variant``)
and the C port, not in the demo or the simulator."""


def get_variant(
    name: str, registry: Mapping[str, Variant] = VARIANTS, kind: str = "variant"
) -> Variant:
    """The rule set called ``name`` in ``registry``; ``ValueError`` naming the choices."""
    try:
        return registry[name]
    except KeyError:
        raise ValueError(f"unknown {kind} {name!r}; choose from {', '.join(registry)}") from None
