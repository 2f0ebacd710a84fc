"""Inputs that are not messages: local requests and timer expiries, as frozen dataclasses.

Together with the wire messages of ``canergy.messages`` they are the events the rule tables
dispatch on. Timers carry no data: the rules compare ``now`` with the deadline they armed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from canergy.core.state import Decision
from canergy.frozen import fast_init


@fast_init
@dataclass(frozen=True, slots=True)
class Begin:
    """Supervisor: reserve ``amount`` µJ for a new transaction and send its intention."""

    NAME: ClassVar[str] = "begin"
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class Decide:
    """Supervisor: commit or abort the acknowledged intention."""

    NAME: ClassVar[str] = "decide"
    decision: Decision


@fast_init
@dataclass(frozen=True, slots=True)
class ResponseTimeout:
    """Supervisor: the response timer of a session expired."""

    NAME: ClassVar[str] = "response timeout"


@fast_init
@dataclass(frozen=True, slots=True)
class CommandTimeout:
    """Client: no command came for the held intention in time."""

    NAME: ClassVar[str] = "command timeout"


@fast_init
@dataclass(frozen=True, slots=True)
class ReturnTimeout:
    """Client: the pending return was not acknowledged in time."""

    NAME: ClassVar[str] = "return timeout"


@fast_init
@dataclass(frozen=True, slots=True)
class Spend:
    """Client: the actuator used ``amount`` µJ."""

    NAME: ClassVar[str] = "spend"
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class GiveBack:
    """Client: return ``amount`` µJ of unused energy to the supervisor."""

    NAME: ClassVar[str] = "give back"
    amount: int


@fast_init
@dataclass(frozen=True, slots=True)
class PowerLoss:
    """Either side: volatile memory is lost; restart from the persistent record. ``nonce``: a
    fresh random number for a client whose rules confirm every start (witnessed)."""

    NAME: ClassVar[str] = "power loss"
    nonce: int = 0


@fast_init
@dataclass(frozen=True, slots=True)
class BooksLost:
    """Client: started without a valid NV record (new, wiped or corrupted); ``nonce`` is a fresh
    random number that ties the supervisor's answer to this start."""

    NAME: ClassVar[str] = "books lost"
    nonce: int


RESPONSE_TIMEOUT = ResponseTimeout()
COMMAND_TIMEOUT = CommandTimeout()
RETURN_TIMEOUT = ReturnTimeout()
POWER_LOSS = PowerLoss()

LocalInput = Begin | Decide | Spend | GiveBack
"""Requests of the local application: refused (``LocalProtocolError``) where the table says so."""
Input = LocalInput | ResponseTimeout | CommandTimeout | ReturnTimeout | PowerLoss | BooksLost
