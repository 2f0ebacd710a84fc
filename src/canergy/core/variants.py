"""The rule sets by name: ``hardened`` (default, H1) and ``paper`` (literal Figs. 3-4)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from canergy.core.common import Actions, ClientStep, SessionStep
from canergy.core.hardened import HardenedClient, HardenedSupervisor
from canergy.core.paper import PaperClient, PaperSupervisor
from canergy.core.state import ClientState, Decision, Session
from canergy.core.timing import Timing
from canergy.messages import ToClient, ToSupervisor


class SupervisorRules(Protocol):
    def begin(self, t: Timing, s: Session, amount: int, now: int) -> tuple[Session, Actions]: ...
    def decide(self, t: Timing, s: Session, decision: Decision, now: int) -> SessionStep: ...
    def receive(self, t: Timing, s: Session, msg: ToSupervisor, now: int) -> SessionStep: ...
    def timer(self, t: Timing, s: Session, now: int) -> SessionStep: ...
    def power_loss(self, s: Session, now: int) -> Session: ...
    def persistent(self, s: Session) -> tuple[object, ...]: ...


class ClientRules(Protocol):
    def receive(self, t: Timing, c: ClientState, msg: ToClient, now: int) -> ClientStep: ...
    def command_timer(self, t: Timing, c: ClientState, now: int) -> ClientStep: ...
    def return_timer(self, t: Timing, c: ClientState, now: int) -> ClientStep: ...
    def give_back(self, t: Timing, c: ClientState, amount: int, now: int) -> ClientStep: ...
    def can_give_back(self, c: ClientState) -> bool: ...
    def power_loss(self, c: ClientState, now: int) -> ClientState: ...
    def persistent(self, c: ClientState) -> tuple[object, ...]: ...


@dataclass(frozen=True, slots=True)
class Variant:
    name: str
    supervisor: SupervisorRules
    client: ClientRules


VARIANTS: dict[str, Variant] = {
    "hardened": Variant("hardened", HardenedSupervisor(), HardenedClient()),
    "paper": Variant("paper", PaperSupervisor(), PaperClient()),
}


def get_variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}") from None
