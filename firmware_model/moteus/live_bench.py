"""A guarded moteus on python-can's virtual bus, on the wall clock: ``canergy supervisor --moteus``
(its real ``main``, in a thread) against the emulated controller (``ServoFace``) and an
application of our own on a third bus object (register frames, ``send``).
"""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from canergy.devices.moteus import (
    DIAGNOSTIC_CHANNEL,
    Kind,
    Mode,
    Reg,
    Stream,
    Write,
    can_id,
    encode,
    extended,
)
from firmware_model.drive.live_bench import wait_for
from firmware_model.drive.motor import LoadTorque
from firmware_model.moteus.servo import ServoFace, ServoModel
from firmware_model.supervisor_thread import SupervisorThread, supervisor_thread

SERVO = 1
APP = 0
"""The application's source id (the moteus library's default)."""
MOTOR = ("--moteus-torque-constant", "0.1", "--moteus-resistance", "0.5")
LIMITS = ("--moteus-max-power", "100", "--moteus-max-current", "2", "--moteus-max-speed", "2")
"""With the motor: min(100, 0.1·2·2π·(2+2) + 3/2·0.5·2², 24·2) = 8.03 W."""

__all__ = ["SERVO", "ServoBench", "guarded_servo", "wait_for"]


@dataclass
class ServoBench:
    model: ServoModel
    face: ServoFace
    app: can.BusABC
    supervisor: SupervisorThread

    def status(self) -> dict[str, Any] | None:
        return self.supervisor.status()

    def servo_status(self) -> dict[str, Any] | None:
        return self.supervisor.device("moteus", SERVO)

    def stop(self) -> dict[str, Any]:
        return self.supervisor.stop()

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj

    def send(
        self, data: bytes, reply: bool = False, source: int = APP, destination: int = SERVO
    ) -> None:
        """A frame from the application (source id ``source``) to the controller."""
        arbitration_id = can_id(source, destination, reply)
        self.app.send(
            can.Message(
                arbitration_id=arbitration_id,
                data=data,
                is_extended_id=extended(arbitration_id),
                is_fd=True,
            )
        )

    def position(self, torque: float, velocity: float = 0.0) -> None:
        """Position mode at the position now, ``velocity``, feed-forward ``torque``."""
        self.send(
            encode(
                Write(Kind.INT8, Reg.MODE, (float(Mode.POSITION),)),
                Write(Kind.FLOAT, Reg.COMMAND_POSITION, (float("nan"), velocity, torque)),
            )
        )

    def conf(self, line: str, source: int = APP) -> None:
        """A diagnostic line (``conf set ...``) from the application."""
        data = encode(Stream(False, DIAGNOSTIC_CHANNEL, line.encode() + b"\n"))
        self.send(data, source=source)

    def send_as_servo(self, data: bytes) -> None:
        """A frame in the controller's name, to the application."""
        arbitration_id = can_id(SERVO, APP)
        frame = can.Message(arbitration_id=arbitration_id, data=data, is_fd=True)
        self.app.send(frame)


@contextlib.contextmanager
def guarded_servo(tmp: Path, *supervisor_args: str, **model: Any) -> Iterator[ServoBench]:
    """The controller (``model`` overrides ``ServoModel``'s fields), the supervisor guarding it
    with ``supervisor_args`` after the defaults, and the application's bus."""
    from canergy.live.runtime import monotonic_us

    channel = f"moteus-{uuid.uuid4().hex}"
    load = LoadTorque.constant(0.01, opposing=True)
    servo = ServoModel(SERVO, monotonic_us(), load=load, **model)
    face = ServoFace(servo, can.Bus(interface="virtual", channel=channel))
    face.start()
    app = can.Bus(interface="virtual", channel=channel)
    args = (
        *("-i", "virtual", "-c", channel, "--fd"),
        *("--moteus", str(SERVO)),
        *("--max-grant", "500mJ", "--response-timeout", "100ms"),
        *MOTOR,
        # threads on a loaded machine stall for 300 ms: a feedback gap is not what is tested
        *("--moteus-feedback-timeout", "2s", "--moteus-stop-timeout", "2s"),
        *supervisor_args,
    )
    try:
        with supervisor_thread(tmp, *args) as supervisor:
            yield ServoBench(servo, face, app, supervisor)
    finally:
        face.close()
        app.shutdown()
