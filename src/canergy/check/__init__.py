"""Explicit-state model checking of the protocol core (``canergy check``).

The checker explores, breadth first, every interleaving of deliveries, losses, duplications,
timer expiries, decisions, spending, returns and power losses of one supervisor and K clients,
and of an attacker forging or replaying frames when its bounds allow, driving the same rule
functions as the live runtime, and checks the conservation ledger in every state.
"""

from canergy.check.explore import CheckResult, check
from canergy.check.model import Bounds, Step, World, replay

__all__ = ["Bounds", "CheckResult", "Step", "World", "check", "replay"]
