"""Emulated nodes on a CAN bus: a python-canopen ``LocalNode`` in front of a ``NodeModel``.

``NodeFace`` serves any ``NodeModel``; ``DriveFace`` is the drive's (``DriveModel``), and
``power_meter.PowerMeterFace`` the power meter's. Several faces may share one network.

- NMT slave and heartbeat producer (0x1017) are the ``LocalNode``'s: ``boot()`` sends the boot-up
  message and enters PRE-OPERATIONAL; NMT reset node / reset communication reset the model
  (``NodeModel.reset``) and boot again. NMT changes reach the model (``set_nmt``).
- SDO server: reads are live (read callback, after advancing the model), writes go through
  ``NodeModel.write``; a refused write is an SDO abort and is counted (``bad_writes``), including
  the ones python-canopen refuses itself (read-only, wrong length, no such object).
- Every other frame (the drive's heartbeats for its 0x1016 consumer, SYNC, RPDOs) goes to
  ``NodeModel.receive`` through a listener on the network's Notifier; TPDOs (SYNC-triggered
  and event-timer ones) are sent as the model makes them due; EMCYs through the node's producer.
- ``run`` (or ``start``, in a thread) advances the model every 1 ms of monotonic time.

One lock guards the model: python-canopen's callbacks run in the Notifier's thread.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import can
import canopen
from canopen import SdoAbortedError

from canergy.live.runtime import monotonic_us
from firmware_model.drive.model import DriveAbort, DriveModel, Frame, NodeModel

__all__ = ["TICK_US", "DriveFace", "NodeFace", "drive_network"]

TICK_US = 1000
"""The model is advanced and due TPDOs are sent every this many µs of monotonic time."""
_ABORT_NOT_WRITABLE = 0x06010002
M = TypeVar("M", bound=NodeModel)


def drive_network(bus: can.BusABC) -> canopen.Network:
    """A canopen ``Network`` on ``bus`` with its own Notifier (stop it with
    ``network.notifier.stop()`` before shutting the bus down)."""
    network = canopen.Network(bus)
    network.notifier = can.Notifier(bus, list(network.listeners), 0.1)
    return network


class _LocalNode(canopen.LocalNode):
    """A ``LocalNode`` that counts every refused SDO write."""

    def __init__(self, model: NodeModel, refused: Callable[[], None]) -> None:
        super().__init__(model.node_id, model.od)
        self.refused = refused

    def set_data(
        self, index: int, subindex: int, data: bytes, check_writable: bool = False
    ) -> None:
        try:
            super().set_data(index, subindex, data, check_writable)
        except SdoAbortedError as exc:
            if not isinstance(exc.__cause__, DriveAbort):  # the model counted its own
                self.refused()
            raise


class _Frames(can.Listener):
    """Raw frames for the model (python-canopen's own listener serves SDO and NMT)."""

    def __init__(self, face: NodeFace[Any]) -> None:
        self.face = face
        self.errors = 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        self.face.received(msg.arbitration_id, bytes(msg.data))

    def on_error(self, exc: Exception) -> None:
        self.errors += 1


class NodeFace(Generic[M]):
    """One emulated node's CANopen side; ``network`` must have its Notifier (see
    ``drive_network``)."""

    kind = "node"
    """Names the thread ``start`` runs in."""

    def __init__(
        self,
        model: M,
        network: canopen.Network,
        clock: Callable[[], int] = monotonic_us,
    ) -> None:
        if network.notifier is None:
            raise ValueError("the network needs its Notifier: use drive_network(bus)")
        self.model, self.network, self.clock = model, network, clock
        self.lock = threading.RLock()
        self.send_errors = 0
        self.local = _LocalNode(model, self._refused)
        self.local.add_read_callback(self._read)
        self.local.add_write_callback(self._write)
        network.add_node(self.local)
        network.subscribe(0, self._nmt_command)  # after the node's NMT slave
        self.frames = _Frames(self)
        network.notifier.add_listener(self.frames)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- NMT ----------------------------------------------------------------------------------

    def boot(self) -> None:
        """Boot-up message, then PRE-OPERATIONAL with the heartbeat running (started here in any
        case: a master may answer the boot-up with NMT start before the second step runs)."""
        nmt = self.local.nmt
        nmt.send_command(0x81)  # reset node: INITIALISING, boot-up message
        nmt.send_command(0x80)  # PRE-OPERATIONAL
        with self.lock:
            period = self.model.read(0x1017)
            self.model.set_nmt(nmt.state, self.clock())
        nmt.start_heartbeat(period)

    def _nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != 2 or data[1] not in (0, self.model.node_id):
            return
        if data[0] in (0x81, 0x82):  # reset node, reset communication
            with self.lock:
                self.model.reset(application=data[0] == 0x81, now_us=self.clock())
            self.boot()
        else:
            self._sync_nmt()

    def _sync_nmt(self) -> None:
        with self.lock:
            if self.local.nmt.state != self.model.nmt:
                self.model.set_nmt(self.local.nmt.state, self.clock())
        self._flush([])

    # -- SDO ----------------------------------------------------------------------------------

    def _refused(self) -> None:
        with self.lock:
            self.model.bad_writes += 1

    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        with self.lock:
            try:
                if not self.model.serves(index, subindex):
                    return None  # strings: the EDS's value
            except DriveAbort as exc:
                raise SdoAbortedError(exc.code) from exc
            self.model.advance(self.clock())
            return self.model.read(index, subindex)

    def _write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        value = od.decode_raw(data)
        if not isinstance(value, int):
            self._refused()
            raise SdoAbortedError(_ABORT_NOT_WRITABLE)
        with self.lock:
            try:
                self.model.write(index, subindex, value, self.clock())
            except DriveAbort as exc:
                raise SdoAbortedError(exc.code) from exc
        self._flush([])

    # -- frames -------------------------------------------------------------------------------

    def received(self, cob_id: int, data: bytes) -> None:
        """A frame from the bus (the Notifier's thread)."""
        with self.lock:
            frames = self.model.receive(cob_id, data, self.clock())
        self._flush(frames)

    def tick(self, now_us: int | None = None) -> None:
        """Advance to now; send the TPDOs and EMCYs that are due."""
        with self.lock:
            if self.local.nmt.state != self.model.nmt:
                self.model.set_nmt(self.local.nmt.state, self.clock())
            frames = self.model.due_tpdos(self.clock() if now_us is None else now_us)
        self._flush(frames)

    def _flush(self, frames: list[Frame]) -> None:
        with self.lock:
            emcys = self.model.take_emcys()
            stopped = self.model.nmt == "STOPPED"
        try:
            for cob_id, data in frames:
                self.network.send_message(cob_id, data)
            for code, register in [] if stopped else emcys:
                self.local.emcy.send(code, register)
        except can.CanError:
            self.send_errors += 1

    # -- running ------------------------------------------------------------------------------

    def run(self, stop: Callable[[], bool], every: Callable[[int], None] | None = None) -> None:
        """Tick every ``TICK_US`` of monotonic time until ``stop()``; ``every(now_us)`` after
        each tick. Never sleeps past a due tick; after a stall the model catches up in its fixed
        substeps at the next tick."""
        next_us = self.clock()
        while not stop():
            now = self.clock()
            if now < next_us:
                time.sleep((next_us - now) / 1e6)
                continue
            self.tick(now)
            if every is not None:
                every(now)
            next_us += TICK_US
            if next_us <= now:
                next_us = now + TICK_US

    def start(self) -> None:
        """Run in a daemon thread until ``close()``."""
        self._thread = threading.Thread(
            target=self.run, args=(self._stop.is_set,), name=f"{self.kind}-{self.model.node_id}"
        )
        self._thread.daemon = True
        self._thread.start()

    def close(self) -> None:
        """Stop the thread and the heartbeat (the caller stops the Notifier and the bus)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        self.local.nmt.stop_heartbeat()
        if self.network.notifier is not None:
            self.network.notifier.remove_listener(self.frames)

    def status(self, advance: bool = True) -> dict[str, Any]:
        """The model's figures, advanced to now; ``advance=False``: as the model stands (a
        reader holding ``lock`` has just advanced it: its figures and these are of one
        instant)."""
        with self.lock:
            if advance:
                self.model.advance(self.clock())
            return {
                **self.model.status(),
                "send_errors": self.send_errors,
                "listener_errors": self.frames.errors,
            }


class DriveFace(NodeFace[DriveModel]):
    """One drive's CANopen side."""

    kind = "drive"
