"""MIT-mode motors in line between two interfaces, for an application in another process or
language: ``canergy inline``. The application's bus (``app``) carries its frames; the motors'
bus (``motors``, with the supervisor on it) is opened through ``MitBus``, so every frame the
application sends to a guarded motor is judged by that motor's gate exactly as in process, and
every other frame crosses unchanged. Both ways: the motors' replies and the rest of the motors'
bus reach the application; canergy's own frames (29-bit, the proxies' business) cross neither
way: from the application they are refused and counted (``canergy_frames_refused``), so the
application's bus gives nobody a way to speak for a node on the supervisor's bus (as the
supervisor's ``--mit`` refuses them).

The forwarder keeps no queue of its own: each frame it takes from the application's bus is
judged at once (``MitBus.send``), so what waits is in that bus's receive buffer (SocketCAN: the
socket's, which the kernel bounds and drops from). It takes at most ``POLL_MAX`` of them before
it carries the motors' side back, so a flood does not hold the replies up. Every frame taken is
counted (``app_taken`` = the gates' forwarded + clamped + refused + ``app_passed`` +
``canergy_frames_refused`` + ``app_error_frames``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can

from canergy.live.devices.mit_bus import MitBus

POLL_MAX = 256
"""The application's frames taken in one poll, at most."""


class MitForwarder:
    """Frames from ``app`` to ``motors`` (a ``MitBus``) and back, one poll at a time."""

    def __init__(self, app: can.BusABC, motors: MitBus) -> None:
        self.app = app
        self.motors = motors
        self.to_motors = 0
        self.to_app = 0
        self.error_frames = 0
        self.canergy_refused = 0
        """Frames in canergy's identifier block from the application: not put on the bus."""
        self.send_failures = 0

    def poll(self, timeout: float = 0.001) -> None:
        """Carry what is waiting on either side (at most ``timeout`` s for the first frame)."""
        frame = self.app.recv(timeout=timeout)
        taken = 0
        while frame is not None:
            taken += 1
            if frame.is_error_frame:
                self.error_frames += 1
            elif frame.is_extended_id and self.motors.codec.is_canergy_id(frame.arbitration_id):
                self.canergy_refused += 1
            else:
                self.to_motors += 1
                self._send(self.motors, frame)
            frame = self.app.recv(timeout=0) if taken < POLL_MAX else None
        while (back := self.motors.recv(timeout=0)) is not None:
            canergy = back.is_extended_id and self.motors.codec.is_canergy_id(back.arbitration_id)
            if not canergy and not back.is_error_frame:
                self.to_app += 1
                self._send(self.app, back)

    def _send(self, bus: can.BusABC, frame: can.Message) -> None:
        try:
            bus.send(frame)
        except can.CanError:
            self.send_failures += 1

    def run(self, stopping: Callable[[], bool], report: Callable[[], None]) -> None:
        while not stopping():
            self.poll()
            report()

    def status(self) -> dict[str, Any]:
        motors = {str(m): self.motors.status(m) for m in self.motors.gates}
        route = self.motors.route
        return {
            "to_motors": self.to_motors,
            "to_app": self.to_app,
            "to_app_dropped": self.motors.dropped,
            "app_taken": self.to_motors + self.error_frames + self.canergy_refused,
            "app_passed": route.passed,
            "canergy_frames_refused": self.canergy_refused,
            "app_error_frames": self.error_frames,
            "send_failures": self.send_failures + self.motors.send_failures,
            "motors": motors,
        }
