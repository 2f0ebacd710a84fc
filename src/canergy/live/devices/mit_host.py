"""MIT-mode motors in line, hosted by the supervisor itself (``canergy supervisor --mit``).

The supervisor's bus is the motors' bus; the application has a bus of its own (``app``). The
gates are the ones ``MitBus`` and ``canergy inline`` use (``MitGates``), and each motor's proxy
client (the gate's ``DeviceGuard``) is a guarded device of the supervisor like an ODrive axis:
a local node whose frames never go on the bus. So no canergy frame for the motors crosses any
bus, and no second process stands between the application and the budget.

``MitHost`` holds the application's bus (a thread reads it and wakes the supervisor's loop), the
gates and the frames both ways; ``MitLink`` is one motor's link (``DeviceLink``) in the
supervisor's loop: each pass it carries the application's frames to the gates and out on the
motors' bus (forwarded, clamped or refused), the motors' replies to the gates and on to the
application, its guard's commands to its gate (enter the cap, exit motor mode), and its gate's
re-clamp every hold. Everything runs on the loop's thread but the two readers, which only queue.

The application's frames wait for the loop in a queue of at most ``APP_QUEUE_MAX`` frames: a
frame that finds it full is refused (never sent), counted (``app_overflowed``, and under the
motor it was for as ``commands.overflowed``) and logged (the first and every 100th), so that a
flood costs bounded memory and every frame the reader took is accounted for:
``app_taken`` = the gates' forwarded + clamped + refused + ``app_passed`` (for no guarded motor)
+ ``canergy_frames_refused`` + ``app_for_other_devices`` (frames another guarded group on the bus
reads, not sent) + ``app_error_frames`` + ``app_overflowed``, once the queue is empty.

The motors' bus's frames wait for the loop too, at most ``BUS_QUEUE_MAX``. One dropped there could
be another sender's command to a motor, which the gate must see (it stops that motor for good), so
a frame that finds that queue full is not dropped quietly: it is counted (``bus_overflowed``) and
at the next pass every motor is stopped for good, the reason named, as for a frame from another
sender (a bus flooded faster than the loop reads it cannot be watched).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from canergy.codec import Codec
from canergy.core import Timing
from canergy.devices.guard import DeviceGuard
from canergy.devices.mit import EXIT
from canergy.devices.mit_gate import MitGate
from canergy.live.devices.mit_gates import MitGates
from canergy.live.devices.mit_motor import MitMotor
from canergy.messages import Message

Clock = Callable[[], int]
Others = Callable[[bool, int], str | None]

APP_QUEUE_MAX = 1_000
"""The application's frames waiting for the supervisor's loop, at most (a pass takes them all:
at 1 Mbit/s, 8 frames a ms at most, this is a loop held off for over 100 ms)."""

BUS_QUEUE_MAX = 4_000
"""The motors' bus's frames waiting for the loop, at most (past it: every motor stopped for
good, see the module's doc)."""

log = logging.getLogger("canergy.live.devices.mit_host")


class MitHost:
    """The application's bus and the gates between it and the supervisor's bus (module doc)."""

    def __init__(
        self,
        bus: can.BusABC,
        app: can.BusABC,
        route: MitGates,
        codec: Codec,
        wake: Callable[[], None],
        clock: Clock,
        queue_max: int | None = None,
        others: Others | None = None,
    ) -> None:
        """``others``: how the other guarded groups on the bus read a frame (None: as none of
        theirs); the application's frames they would read are not put on the bus: their guards
        do not hear what this process sends, so a write to their devices would pass unseen."""
        self.others = others
        self.for_others = 0
        self.bus = bus
        self.queue_max = APP_QUEUE_MAX if queue_max is None else queue_max
        self.bus_queue_max = BUS_QUEUE_MAX
        self.clock = clock
        self.app = app
        self.route = route
        self.codec = codec
        self.wake = wake
        self.lock = threading.Lock()
        self.from_app: list[can.Message] = []
        self.from_bus: list[can.Message] = []
        self.to_motors = 0
        self.to_app = 0
        self.taken = 0
        """Frames the reader took from the application's bus."""
        self.overflowed = 0
        """Of those, refused because the queue was full."""
        self.overflowed_by_id: dict[int, int] = {}
        """The same, by the guarded motor each was for."""
        self.queue_peak = 0
        self.bus_overflowed = 0
        """Frames of the motors' bus not kept: the queue was full."""
        self.bus_overflowed_told = 0
        """Of those, what the gates were told of (at a pass)."""
        self.error_frames = 0
        self.canergy_refused = 0
        """Frames in canergy's identifier block from the application: not put on the bus."""
        self.send_failures = 0
        self.receive_failures = 0
        self.closing = threading.Event()
        self.reader = threading.Thread(target=self._read_app, daemon=True, name="canergy-mit-app")
        self.closed = False

    def start(self) -> None:
        if not self.reader.is_alive() and not self.closing.is_set():
            self.reader.start()

    # -- the readers (their own threads) -------------------------------------------------
    def _read_app(self) -> None:
        while not self.closing.is_set():
            try:
                frame = self.app.recv(timeout=0.1)
            except can.CanError:
                self.receive_failures += 1
                self.closing.wait(0.1)
                continue
            if frame is None:
                continue
            with self.lock:
                self.taken += 1
                full = len(self.from_app) >= self.queue_max
                if full:
                    self.overflowed += 1
                    motor = frame.arbitration_id
                    if not frame.is_extended_id and motor in self.route.gates:
                        self.overflowed_by_id[motor] = self.overflowed_by_id.get(motor, 0) + 1
                    n = self.overflowed
                else:
                    self.from_app.append(frame)
                    self.queue_peak = max(self.queue_peak, len(self.from_app))
            if full and (n == 1 or n % 100 == 0):
                log.warning(
                    "MIT: the application's frame to 0x%X refused: %d frames wait already; "
                    "%d refused so far",
                    frame.arbitration_id,
                    self.queue_max,
                    n,
                )
            self.wake()

    def heard(self, frame: can.Message) -> None:
        """A frame of the supervisor's bus (the Notifier's thread)."""
        if frame.is_extended_id and self.codec.is_canergy_id(frame.arbitration_id):
            return
        with self.lock:
            if len(self.from_bus) < self.bus_queue_max:
                self.from_bus.append(frame)
            else:
                self.bus_overflowed += 1

    # -- the loop's side ------------------------------------------------------------------
    def waiting(self) -> bool:
        with self.lock:
            return bool(self.from_app or self.from_bus)

    def pump(self, now: int) -> list[Message]:
        """What both buses brought since the last pass: through the gates, and across."""
        with self.lock:
            app, self.from_app = self.from_app, []
            heard, self.from_bus = self.from_bus, []
            lost = self.bus_overflowed - self.bus_overflowed_told
            self.bus_overflowed_told = self.bus_overflowed
        up: list[Message] = []
        if lost:
            lost_why = (
                f"{lost} frames of the motors' bus lost ({self.bus_queue_max} waiting already): "
                "one may have been another sender's to the motor"
            )
            log.warning("MIT: %s; every motor stopped for good", lost_why)
            up += self.route.unseen(lost_why, now)
        for frame in heard:
            up += self.route.from_bus(frame, now)
            if not frame.is_error_frame and not self.closed:  # closed: the app's bus is shut
                self.to_app += 1
                self._send(self.app, frame)
        for frame in app:
            if frame.is_error_frame:
                self.error_frames += 1
                continue
            if frame.is_extended_id and self.codec.is_canergy_id(frame.arbitration_id):
                self.canergy_refused += 1
                continue
            if self.others is not None:
                why = self.others(frame.is_extended_id, frame.arbitration_id)
                if why is not None:
                    self.for_others += 1
                    if self.for_others == 1 or self.for_others % 100 == 0:
                        log.warning(
                            "MIT: the application's frame 0x%X refused: %s; %d refused so far",
                            frame.arbitration_id,
                            why,
                            self.for_others,
                        )
                    continue
            out, _ = self.route.from_app(frame, now)
            self.send_out()
            if out is not None:
                self.to_motors += 1
                self._send(self.bus, out)
        return up

    def send_out(self, gate: MitGate | None = None) -> None:
        """The gates' own frames (or ``gate``'s) to the motors."""
        for frame in self.route.outgoing(gate):
            self._send(self.bus, frame)

    def _send(self, bus: can.BusABC, frame: can.Message) -> None:
        try:
            bus.send(frame)
        except can.CanError:
            self.send_failures += 1

    def status(self) -> dict[str, int]:
        with self.lock:
            taken, overflowed, peak = self.taken, self.overflowed, self.queue_peak
        return {
            "to_motors": self.to_motors,
            "to_app": self.to_app,
            "app_taken": taken,
            "app_queue_max": self.queue_max,
            "app_queue_peak": peak,
            "app_overflowed": overflowed,
            "bus_overflowed": self.bus_overflowed,
            "app_passed": self.route.passed,
            "app_error_frames": self.error_frames,
            "canergy_frames_refused": self.canergy_refused,
            "app_for_other_devices": self.for_others,
            "forward_send_failures": self.send_failures,
            "app_receive_failures": self.receive_failures,
        }

    def close(self) -> None:
        """Exit motor mode on every motor, stop the reader, shut the application's bus down."""
        if self.closed:
            return
        self.closed = True
        for gate in self.route.gates.values():
            exit_mode = can.Message(arbitration_id=gate.motor_id, data=EXIT, is_extended_id=False)
            self._send(self.bus, exit_mode)
        self.closing.set()
        if self.reader.is_alive():
            self.reader.join(timeout=2)
        self.app.shutdown()


class MitLink:
    """One motor's link in the supervisor's loop (``canergy.live.devices.device_link``); the
    first of a host's links is the one the bus's Notifier feeds (``listens``)."""

    def __init__(self, host: MitHost, gate: MitGate, listens: bool) -> None:
        self.host = host
        self.gate = gate
        self.listens = listens
        self.queued: list[Any] = []

    def start(self) -> None:
        self.host.start()

    def __call__(self, frame: can.Message) -> None:
        self.on_message_received(frame)

    def on_message_received(self, msg: Any) -> None:
        if self.listens:
            self.host.heard(msg)

    def pump(self, guard: Any, now: int) -> list[Message]:
        up = self.host.pump(now)
        queued, self.queued = self.queued, []
        for cmd in queued:
            up += self.gate.execute(cmd, now)
        up += self.gate.carry_out(now)
        if self.gate.next_wakeup() <= now:
            up += self.gate.on_wakeup(now)
        self.host.send_out(self.gate)
        return up

    def command(self, cmd: Any) -> None:
        self.queued.append(cmd)

    def pending(self) -> bool:
        return bool(self.queued or self.gate.guard.commands) or self.host.waiting()

    def next_wakeup(self) -> int | None:
        return self.gate.next_send

    def status(self) -> dict[str, object]:
        details = self.gate.details()
        with self.host.lock:
            overflowed = self.host.overflowed_by_id.get(self.gate.motor_id, 0)
        details["commands"]["overflowed"] = overflowed
        return {**details, **self.host.status()}

    def close(self) -> None:
        """Carry out what is queued (a halt's stop), then close the host (once)."""
        now = self.host.clock()
        for cmd in self.queued:
            self.gate.execute(cmd, now)
        self.queued = []
        if not self.gate.guard.halted:
            self.gate.halt(now)
        self.host.send_out(self.gate)
        self.host.close()


@dataclass(frozen=True, slots=True)
class MitMotors:
    """``--mit``: the motors, their gates' configuration and the application's bus
    (``canergy.live.supervisor.build.DeviceGroup``)."""

    motors: tuple[MitMotor, ...]
    open_app: Callable[[], can.BusABC]
    """Opens the application's bus (the host shuts it down when it closes)."""
    timing: Timing
    guard_config: dict[str, Any] = field(default_factory=dict)
    codec: Codec = field(default_factory=Codec)
    others: Others | None = None
    """How the other guarded groups on the bus read a frame (``canergy.devices.bus_ids``)."""

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(m.node for m in self.motors)

    def open(
        self, bus: can.BusABC, now: int, clock: Clock, wake: Callable[[], None]
    ) -> dict[int, tuple[DeviceGuard[Any], MitLink]]:
        """A gate (its guard the proxy) and a link per motor, around one host."""
        route = MitGates(self.motors, now, self.timing, self.guard_config)
        host = MitHost(bus, self.open_app(), route, self.codec, wake, clock, others=self.others)
        return {
            gate.guard.node: (gate.guard, MitLink(host, gate, listens=i == 0))
            for i, gate in enumerate(route.gates.values())
        }
