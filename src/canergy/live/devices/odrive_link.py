"""One ODrive axis over CAN Simple: set-up, feedback in, limits and stops out.

A ``can.Listener`` on the supervisor's Notifier takes the axis's frames and the frames others
send it, stamped with the host's clock at the driver's receive time (at most 1 s back); a worker
thread carries out the guard's commands, so a device that does not answer never blocks the
supervisor's loop:

- ``WriteLimits``: Set_Limits, then on firmware 0.6 with the endpoint ids given, RxSdo reads of
  ``vel_limit`` and ``current_soft_max`` answered by TxSdo (the round trip is the latency
  measured); on 0.5 nothing can be read back (the answer says so: None);
- ``ReadLimits`` (the periodic read-back): the two endpoint reads alone (None on 0.5), and
  the watchdog's two (``axis.config.enable_watchdog``, ``watchdog_timeout``) where their ids
  are given: unanswered, the whole read-back is;
- ``Stop``: Estop, then Set_Axis_State IDLE.

Set-up writes the guard's full limits and reads them back, then the closed ones (current 0),
then reads the watchdog (``canergy.devices.watchdog``: the guard judges it).
Frames from others are read by the profile (``canergy.devices.odrive.watch``: Set_Limits is
charged as written, then written over; RxSdo writes, Reboot, Address/Set_Axis_Node_ID and
Enter_DFU_Mode stop the axis for good). The link polls bus voltage and current (0x017) and, on
0.6, the powers (0x01D) by remote request.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import struct
from collections.abc import Callable
from dataclasses import dataclass

import can

from canergy.devices.odrive import (
    AxisState,
    Cmd,
    OdriveLimits,
    can_id,
    heartbeat,
    sdo_fields,
    sdo_read,
    set_axis_state,
    set_limits,
    split_id,
    two_floats,
    watch,
)
from canergy.devices.profile import ReadLimits, Stop
from canergy.devices.watchdog import WatchdogReading
from canergy.live.devices.device_link import GuardLink
from canergy.live.devices.device_link import limits_event as _limits
from canergy.live.devices.device_link import read_event as _read
from canergy.live.devices.device_link import ready_event as _ready

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class OdriveLinkConfig:
    firmware: str = "0.6"
    endpoints: tuple[int, int] | None = None
    """0.6: the endpoint ids of ``axis.controller.config.vel_limit`` and
    ``axis.config.motor.current_soft_max`` (the firmware's ``flat_endpoints.json``)."""
    watchdog_endpoints: tuple[int, int] | None = None
    """0.6: the endpoint ids of ``axis.config.enable_watchdog`` (bool) and
    ``axis.config.watchdog_timeout`` (float32, s): read at set-up and with each periodic
    read-back (None: not read)."""
    sdo_timeout_s: float = 0.2
    poll_s: float = 0.1
    """Remote requests for bus voltage and current (and 0.6 powers) this often."""
    sampled: bool = False


class OdriveLink(GuardLink[OdriveLimits]):
    """The axis ``node`` on ``bus`` (see the module doc); ``clock`` gives host µs."""

    def __init__(
        self,
        bus: can.BusABC,
        node: int,
        config: OdriveLinkConfig,
        limits: OdriveLimits | None,
        clock: Callable[[], int],
    ) -> None:
        super().__init__(bus, node, limits, clock, "odrive")
        self.config = config
        self.replies: queue.Queue[tuple[int, bytes]] = queue.Queue()

    # -- the listener (Notifier thread) ---------------------------------------------------
    def on_message_received(self, frame: can.Message) -> None:
        if frame.is_extended_id or frame.is_error_frame:
            return
        node, cmd = split_id(frame.arbitration_id)
        if node != self.node:
            return
        at = self.received_at(frame)
        data = bytes(frame.data)
        try:
            self._take(cmd, data, at, frame.is_remote_frame)
        except (ValueError, struct.error):
            with self.lock:
                self.bad_frames += 1

    def on_error(self, exc: Exception) -> None:
        with self.lock:
            self.bad_frames += 1

    def _take(self, cmd: int, data: bytes, at: int, remote: bool) -> None:
        if remote:
            return  # someone's request: the answer is the axis's
        if cmd == Cmd.HEARTBEAT:
            _, state = heartbeat(data)
            known = state in AxisState.__members__.values()
            name = AxisState(state).name if known else f"state {state}"
            powered = state != AxisState.IDLE
            self._event(lambda g, now: g.on_feedback(now, at, powered, name))
        elif cmd == Cmd.BUS_VOLTAGE_CURRENT:
            volts, amps = two_floats(data)
            self.voltage = volts
            power = volts * amps if self.config.firmware == "0.5" else None
            measured = {"bus_voltage_v": volts}
            self._event(lambda g, now: g.on_feedback(now, at, None, None, power, measured))
        elif cmd == Cmd.POWERS and self.config.firmware == "0.6":
            electrical, _ = two_floats(data)
            self._event(lambda g, now: g.on_feedback(now, at, None, None, electrical))
        elif cmd == Cmd.ENCODER_ESTIMATES:
            two_floats(data)
            self._event(lambda g, now: g.on_feedback(now, at, None))
        elif cmd == Cmd.TX_SDO:
            _, endpoint, value = sdo_fields(data)
            self.replies.put((endpoint, value))
        elif (seen := watch(cmd, data)) is not None:  # the profile reads the others' frames
            self._event(lambda g, now: g.on_watched(now, at, seen))

    # -- the loop's side ------------------------------------------------------------------
    def status(self) -> dict[str, object]:
        return {"firmware": self.config.firmware, **super().status()}

    # -- the worker -----------------------------------------------------------------------
    def _send(self, cmd: int, data: bytes = b"", remote: bool = False) -> bool:
        frame = can.Message(
            arbitration_id=can_id(self.node, cmd),
            data=data,
            is_extended_id=False,
            is_remote_frame=remote,
            dlc=8 if remote else len(data),
        )
        try:
            self.bus.send(frame)
            return True
        except can.CanError:
            self.send_failures += 1
            return False

    def _work(self) -> None:
        if self.limits is not None:
            self._setup(self.limits)
        else:  # sampled: nothing to write
            started = self.clock()
            self._watchdog(periodic=False)
            self._event(lambda g, now: _ready(g, now, started, None, None))
        while not self.closing.is_set():
            try:
                cmd = self.work.get(timeout=self.config.poll_s)
            except queue.Empty:
                self._poll()
                continue
            if cmd is None:
                return
            if isinstance(cmd, Stop):
                self._send(Cmd.ESTOP)
                self._send(Cmd.SET_AXIS_STATE, set_axis_state(AxisState.IDLE))
                self.reaction_max_us = max(self.reaction_max_us, self.clock() - cmd.at)
            elif isinstance(cmd, ReadLimits):
                read = self._read_limits()
                if read is not None and not self._watchdog(periodic=True):
                    read = None  # the watchdog unanswered: the read-back is
                self._event(functools.partial(_read, read))
            else:
                read = self._write(cmd.limits)
                self._event(functools.partial(_limits, cmd.limits, read, cmd.at))

    def _poll(self) -> None:
        self._send(Cmd.BUS_VOLTAGE_CURRENT, remote=True)
        if self.config.sampled and self.config.firmware == "0.6":
            self._send(Cmd.POWERS, remote=True)

    def _setup(self, limits: OdriveLimits) -> None:
        started = self.clock()
        full = self._write(limits)
        closed = self._write(OdriveLimits(limits.velocity, 0.0))
        self._watchdog(periodic=False)
        self._event(lambda g, now: _ready(g, now, started, full, closed))

    def _watchdog(self, periodic: bool) -> bool:
        """Read the watchdog's endpoints, where given, for the guard; False: unanswered."""
        endpoints = self.config.watchdog_endpoints
        if self.config.firmware != "0.6" or endpoints is None:
            return True
        enabled, timeout = (self._read(endpoint) for endpoint in endpoints)
        reading = None
        if enabled is not None and timeout is not None:
            reading = WatchdogReading(enabled[0] != 0, struct.unpack("<f", timeout)[0])
        self._event(lambda g, now: g.on_watchdog(now, reading, periodic))
        return reading is not None

    def _write(self, limits: OdriveLimits) -> OdriveLimits | None:
        """Set_Limits and, where the firmware allows, the limits read back (else None)."""
        if not self._send(Cmd.SET_LIMITS, set_limits(limits.velocity, limits.current)):
            return None
        return self._read_limits()

    def _read_limits(self) -> OdriveLimits | None:
        """The limits the axis holds, where the firmware can say (else None)."""
        if self.config.firmware != "0.6" or self.config.endpoints is None:
            return None
        velocity, current = (self._read(endpoint) for endpoint in self.config.endpoints)
        if velocity is None or current is None:
            return None
        return OdriveLimits(*(struct.unpack("<f", v)[0] for v in (velocity, current)))

    def _read(self, endpoint: int) -> bytes | None:
        """The 4 value bytes of ``endpoint`` (None: no answer within the SDO timeout)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self.replies.get_nowait()  # answers to reads given up on
        start = self.clock()
        if not self._send(Cmd.RX_SDO, sdo_read(endpoint)):
            return None
        deadline = start + round(self.config.sdo_timeout_s * 1e6)
        while (left := deadline - self.clock()) > 0:
            try:
                got, value = self.replies.get(timeout=left / 1e6)
            except queue.Empty:
                break
            if got == endpoint:
                self.latency_max_us = max(self.latency_max_us, self.clock() - start)
                return value
        return None
