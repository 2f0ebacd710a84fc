"""What a rule returns: the new state, the actions to carry out and, for the supervisor, energy."""

from __future__ import annotations

from typing import NamedTuple

from canergy.core.actions import Action
from canergy.core.state import ClientState, Session

Actions = tuple[Action, ...]
NO_ACTIONS: Actions = ()


class SessionStep(NamedTuple):
    """A supervisor rule's result for one node's session."""

    session: Session
    actions: Actions = NO_ACTIONS
    credit: int = 0
    """µJ to add to the supervisor's usable budget Us (negative: a reservation's debit)."""


class ClientStep(NamedTuple):
    """A client rule's result; the client's energy moves inside its state."""

    client: ClientState
    actions: Actions = NO_ACTIONS
