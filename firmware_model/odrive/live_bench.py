"""A guarded ODrive axis on python-can's virtual bus, on the wall clock: ``canergy supervisor
--odrive`` (its real ``main``, in a thread) against the emulated axis (``AxisFace``) and an
application of our own on a third bus object (CAN Simple frames, ``send``).
"""

from __future__ import annotations

import contextlib
import struct
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from canergy.devices.odrive import AxisState, Cmd, can_id, set_axis_state
from firmware_model.drive.live_bench import wait_for
from firmware_model.drive.motor import LoadTorque
from firmware_model.odrive.axis import (
    CURRENT_LIMIT_EP,
    ENABLE_WATCHDOG_EP,
    VEL_LIMIT_EP,
    WATCHDOG_TIMEOUT_EP,
    AxisFace,
    AxisModel,
)
from firmware_model.supervisor_thread import SupervisorThread, supervisor_thread

AXIS = 3
MOTOR = ("--odrive-torque-constant", "0.05", "--odrive-resistance", "0.5")
LIMITS = ("--odrive-max-speed", "5", "--odrive-max-current", "2")
"""With the motor: min(0.05·2·2π·1.2·5 + 3/2·0.5·2², 24·2) = 6.77 W."""
ENDPOINTS = ("--odrive-endpoints", f"{VEL_LIMIT_EP},{CURRENT_LIMIT_EP}")
WATCHDOG = ("--odrive-watchdog-endpoints", f"{ENABLE_WATCHDOG_EP},{WATCHDOG_TIMEOUT_EP}")

__all__ = ["AXIS", "ENDPOINTS", "LIMITS", "WATCHDOG", "AxisBench", "guarded_axis", "wait_for"]


@dataclass
class AxisBench:
    model: AxisModel
    face: AxisFace
    app: can.BusABC
    supervisor: SupervisorThread

    def status(self) -> dict[str, Any] | None:
        return self.supervisor.status()

    def axis_status(self) -> dict[str, Any] | None:
        return self.supervisor.device("odrive", AXIS)

    def stop(self) -> dict[str, Any]:
        return self.supervisor.stop()

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj

    def send(self, cmd: int, data: bytes = b"") -> None:
        """A frame from the application to the axis."""
        frame = can.Message(arbitration_id=can_id(AXIS, cmd), data=data, is_extended_id=False)
        self.app.send(frame)

    def run_closed_loop(self, torque: float) -> None:
        """The application clears errors, enters closed loop and asks for ``torque``."""
        self.send(Cmd.CLEAR_ERRORS, b"\x00")
        self.send(Cmd.SET_AXIS_STATE, set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
        self.send(Cmd.SET_INPUT_TORQUE, struct.pack("<f", torque))


@contextlib.contextmanager
def guarded_axis(
    tmp: Path, *supervisor_args: str, firmware: str = "0.6", **model: Any
) -> Iterator[AxisBench]:
    """The axis (``model`` overrides ``AxisModel``'s fields), the supervisor guarding it with
    ``supervisor_args`` after the defaults, and the application's bus."""
    channel = f"odrive-{uuid.uuid4().hex}"
    from canergy.live.runtime import monotonic_us

    axis = AxisModel(
        AXIS,
        monotonic_us(),
        firmware=firmware,
        load=LoadTorque.constant(0.01, opposing=True),
        **model,
    )
    face = AxisFace(axis, can.Bus(interface="virtual", channel=channel))
    face.start()
    app = can.Bus(interface="virtual", channel=channel)
    args = (
        *("-i", "virtual", "-c", channel),
        *("--odrive", str(AXIS), "--odrive-firmware", firmware),
        *("--max-grant", "500mJ", "--response-timeout", "100ms"),
        *MOTOR,
        # threads on a loaded machine stall for 300 ms: a feedback gap is not what is tested
        *("--odrive-feedback-timeout", "2s", "--odrive-stop-timeout", "2s"),
        *supervisor_args,
    )
    try:
        with supervisor_thread(tmp, *args) as supervisor:
            yield AxisBench(axis, face, app, supervisor)
    finally:
        face.close()
        app.shutdown()
