"""The sans-IO protocol core: frozen states, pure transition rules, thin stateful wrappers.

No clock, no sockets, no ``can`` import. Callers pass ``now`` (integer µs), feed messages and
timer expiries in, and carry out the returned actions.
"""

from canergy.core.actions import (
    Acknowledged,
    Action,
    Admitted,
    AheadOfImage,
    ClientAborted,
    ClientCommitted,
    Credited,
    IntentionRefused,
    Persist,
    Resolved,
    ReturnAcknowledged,
    ReturnCredited,
    RolledBack,
    Send,
)
from canergy.core.client import Client
from canergy.core.errors import LocalProtocolError
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session, SupervisorState
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.supervisor import Supervisor
from canergy.core.table import ClientTable, SupervisorTable
from canergy.core.timing import Timing
from canergy.core.variants import VARIANTS

__all__ = [
    "VARIANTS",
    "Acknowledged",
    "Action",
    "Admitted",
    "AheadOfImage",
    "Client",
    "ClientAborted",
    "ClientCommitted",
    "ClientState",
    "ClientStep",
    "ClientTable",
    "Credited",
    "Decision",
    "IntentionRefused",
    "LocalProtocolError",
    "Outcome",
    "Persist",
    "Phase",
    "Resolved",
    "ReturnAcknowledged",
    "ReturnCredited",
    "RolledBack",
    "Send",
    "Session",
    "SessionStep",
    "Supervisor",
    "SupervisorState",
    "SupervisorTable",
    "Timing",
]
