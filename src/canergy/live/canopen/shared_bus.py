"""What canergy and CANopen share on one bus: the node EDS, an 11-bit filter, one Notifier.

Both ends use these: the supervisor (``canergy supervisor --canopen``) and emulated client nodes.
``canergy_node.eds`` ships inside this package, so an installed canergy has it.
"""

from __future__ import annotations

import queue
from pathlib import Path

import can
import canopen

EDS = Path(__file__).with_name("canergy_node.eds")
"""The canergy node's electronic data sheet (energy 0x2000-0x2007, parameters 0x2100-0x2102)."""

STANDARD_FRAMES: dict[str, int | bool] = {"can_id": 0, "can_mask": 0, "extended": False}
"""Acceptance filter passing every 11-bit frame (NMT, SDO, heartbeat, ...)."""


_WAKE = can.Message(arbitration_id=0)
"""Put in the reader's queue by ``wake``: read as no frame."""


class SharedReader(can.BufferedReader):
    """canergy's end of a shared Notifier; a receive error is counted, not fatal (without a
    listener that handles it the Notifier's thread would stop and every node look lost).
    ``wake``: the loop waiting on it returns at once, with no frame (work from elsewhere:
    frames of the application's bus for supervisor-hosted MIT gates).

    Frames wait in a ``queue.Queue``, not in ``can.BufferedReader``'s ``SimpleQueue``: the
    lock-based ``SimpleQueue`` of CPython 3.11 (3.13 has another) waits without end, until the
    next ``put``, once ``get(timeout=t)`` goes round its loop after ``t`` ran out (a signal
    handler that outlasts ``t`` in its wait; or a tiny ``t`` spent before its first check,
    as where reading the clock is a system call, in user-mode Linux). A supervisor whose loop
    waited here for a frame of its bus, where the guarded motor answers only what that loop
    sends, then never ended, not even on SIGTERM (``test_vcan_mit_hosted``: faulthandler
    showed its main thread in ``get_message``). ``queue.Queue`` waits on a
    ``threading.Condition``, whose lock gives up once the time is over."""

    def __init__(self) -> None:
        super().__init__()
        self.errors = 0
        self.frames: queue.Queue[can.Message] = queue.Queue()

    def on_message_received(self, msg: can.Message) -> None:
        if self.is_stopped:
            raise RuntimeError("reader has already been stopped")
        self.frames.put(msg)

    def on_error(self, exc: Exception) -> None:
        self.errors += 1

    def wake(self) -> None:
        self.frames.put(_WAKE)

    def get_message(self, timeout: float = 0.5) -> can.Message | None:
        """The oldest frame, waiting at most ``timeout`` s (not at all once stopped); None
        when none came, or a ``wake``."""
        try:
            msg = self.frames.get(block=not self.is_stopped and timeout > 0, timeout=timeout)
        except queue.Empty:
            return None
        return None if msg is _WAKE else msg


def shared_network(bus: can.BusABC) -> tuple[canopen.Network, SharedReader]:
    """A canopen ``Network`` on ``bus`` and a reader for canergy, behind one Notifier
    (python-canopen's "re-using a bus": assign the bus and the notifier yourself). Stop it with
    ``network.notifier.stop()`` before shutting the bus down."""
    network = canopen.Network(bus)
    reader = SharedReader()
    network.notifier = can.Notifier(bus, [*network.listeners, reader], 0.1)
    return network, reader
