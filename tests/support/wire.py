"""An in-memory bus end for driving one bus loop from a test, pass by pass."""

from __future__ import annotations

import can


class Wire(can.BusABC):
    """What is sent is kept (identifier and bytes), what is queued in ``inbox`` is received."""

    def __init__(self) -> None:
        super().__init__(channel="wire")
        self.inbox: list[can.Message] = []
        self.sent: list[tuple[int, bytes]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data)))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.pop(0) if self.inbox else None), False
