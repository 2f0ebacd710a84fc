"""What the supervisor's loop needs of a guarded device's link (``OdriveLink``, ``MoteusLink``):
feed what arrived to the guard, take its commands, report, close."""

from __future__ import annotations

from typing import Any, Protocol

from canergy.devices.guard import DeviceGuard
from canergy.messages import Message


class DeviceLink(Protocol):
    """Also a ``can.Listener`` (the builder adds it to the bus's Notifier)."""

    def start(self) -> None: ...

    def on_message_received(self, msg: Any) -> None: ...

    def pump(self, guard: Any, now: int) -> list[Message]: ...

    def command(self, cmd: Any) -> None: ...

    def pending(self) -> bool: ...

    def status(self) -> dict[str, object]: ...

    def close(self) -> None: ...


Device = tuple[DeviceGuard[Any], DeviceLink]
"""A guarded device and its link."""
