"""MIT-mode motors in line, in the application's process: a python-can bus to open instead of
one's own. Existing python-can code changes one line::

    bus = MitBus(can.Bus(interface="socketcan", channel="can0"), [MitMotor(1, node=11)])

``MitBus`` wraps the real bus. What the application sends to a guarded motor's identifier goes
through that motor's ``MitGate`` (``canergy.devices.mit_gate``): forwarded, clamped, or refused;
everything else passes untouched, both ways. The budget comes from a ``canergy supervisor`` on
the same bus: each motor's gate holds a proxy client (canergy node ``node``, which the supervisor
lists in ``--nodes``), whose frames this bus exchanges with the supervisor itself. A thread reads
the real bus: the supervisor's frames to the proxies go to the gates, the motors' replies to the
gates and to the application, the rest to the application; it also runs the gates' timers (the
re-clamp every hold, the stop when the budget is gone).

A refused or clamped command is never silent: ``counts(motor)`` gives the gate's counters
(forwarded, clamped, refused and why), ``status(motor)`` the guard's whole status; each refusal
is logged (warning, the first and then every 100th of a motor, with its reason); with
``on_refused="raise"`` a refused ``send`` raises ``MitRefused`` (a ``can.CanOperationError``).
``shutdown`` exits motor mode on every guarded motor before it closes the real bus.

A motor that does not obey (still showing torque ``stop_timeout_us`` after its stop, or not heard
since) is STUCK: its gate repeats exit motor mode every 100 ms, ``status(motor)`` says so
(``guard: stuck``, ``stuck``), ``report`` (default: logged, a warning) gets
``mit motor 1: STUCK (...)`` within one pass of the reader (5 ms, the host willing), ``on_stuck``
(a command, as ``canergy supervisor --on-stuck``) runs once, and what the motor may draw from the
stop's notice on is booked as ``uncontained_uj`` at its model's whole envelope.

Why the proxy lives here: the application's commands then take one function call to reach the
clamp (no second process in their path), and the supervisor needs nothing new (the proxy is an
ordinary client to it). What it costs: if this process dies the motor keeps its last command
(clamped under the cap, but no longer re-clamped nor stopped) until its own timeout (Damiao:
``CAN Timeout``; CubeMars AK: none), and the supervisor sees its proxy go silent;
docs/guide/drives.md says what to arm. The other way, ``canergy supervisor --mit``, hosts the
same gates (``MitGates``) in the supervisor's process, between the application's bus and its own
(``canergy.live.devices.mit_host``): the proxies are then its guarded devices, shown under
``mit`` in its status, and the application needs a bus of its own.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import can

from canergy.codec import Codec, DecodeError
from canergy.core import Timing
from canergy.devices.mit import EXIT
from canergy.devices.mit_gate import MitCounts
from canergy.live.devices.mit_gates import MitGates
from canergy.live.devices.mit_motor import MitMotor, gate_for
from canergy.live.devices.on_stuck import DeviceNews, OnStuck
from canergy.live.runtime import monotonic_us
from canergy.messages import Direction, Message, ToClient

__all__ = ["INCOMING_MAX", "MitBus", "MitMotor", "MitRefused", "gate_for"]

log = logging.getLogger("canergy.live.devices.mit_bus")

INCOMING_MAX = 10_000
"""Frames kept for an application that does not read them (a socket's buffer drops too)."""


def _logged(line: str) -> None:
    """A motor STUCK and ``on_stuck``'s runs as warnings; its stops and releases as info."""
    stuck = "STUCK" in line or "--on-stuck" in line
    log.log(logging.WARNING if stuck else logging.INFO, "%s", line)


class MitRefused(can.CanOperationError):
    """A frame to a guarded motor was not sent (``on_refused="raise"``)."""


class MitBus(can.BusABC):
    """See the module doc."""

    def __init__(
        self,
        bus: can.BusABC,
        motors: Sequence[MitMotor],
        *,
        codec: Codec | None = None,
        timing: Timing | None = None,
        guard_config: dict[str, Any] | None = None,
        on_refused: str = "count",
        clock: Callable[[], int] = monotonic_us,
        on_stuck: str | None = None,
        report: Callable[[str], None] | None = None,
        **kwargs: Any,
    ) -> None:
        """``on_stuck``: a command run once each time a motor becomes STUCK (``{node}`` is the
        motor's CAN id); ``report``: told a line when a motor stops, is released or is STUCK
        (default: logged, STUCK as a warning, the rest as info)."""
        if on_refused not in ("count", "raise"):
            raise ValueError("on_refused: 'count' or 'raise'")
        said = report or _logged
        self.on_stuck = None if on_stuck is None else OnStuck(on_stuck, said)
        self.news = DeviceNews(said, self.on_stuck, lambda g: self.route.by_node[g.node].motor_id)
        self.inner = bus
        self.codec = codec or Codec()
        self.clock = clock
        self.on_refused = on_refused
        self.lock = threading.Lock()
        self.route = MitGates(motors, clock(), timing, guard_config)
        self.gates = self.route.gates
        self.incoming: queue.Queue[can.Message] = queue.Queue(maxsize=INCOMING_MAX)
        self.dropped = 0
        """Frames for the application dropped, oldest first, while it read none (as a socket's
        receive buffer drops them)."""
        self.stopping = threading.Event()
        self.send_failures = 0
        self.reader_waiting = False
        self.channel_info = f"canergy MIT in line over {bus.channel_info}"
        super().__init__(channel=getattr(bus, "channel", None) or "mit", **kwargs)
        self.thread = threading.Thread(target=self._run, daemon=True, name="canergy-mit-bus")
        self.thread.start()

    # -- the application's side ------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.reader_waiting:  # the reader has replies to take in: let it have the lock first
            time.sleep(0)
        with self.lock:
            out, refused = self.route.from_app(msg, self.clock())
            self._to_motors()
        if out is None:
            if refused is not None and self.on_refused == "raise":
                raise MitRefused(refused)
            return
        self.inner.send(out, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self.incoming.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def counts(self, motor_id: int) -> MitCounts:
        return self.gates[motor_id].counts

    def status(self, motor_id: int) -> dict[str, Any]:
        with self.lock:
            gate = self.gates[motor_id]
            status = gate.status(self.clock())
        if self.on_stuck is not None:
            status["on_stuck"] = self.on_stuck.status(motor_id)
        return status

    # -- the reader ------------------------------------------------------------------------
    def _run(self) -> None:
        while not self.stopping.is_set():
            with self.lock:
                wakeup = min(g.next_wakeup() for g in self.gates.values())
            wait = max(0.0, min((wakeup - self.clock()) / 1e6, 0.005))
            frames = self._drain(wait)
            self.reader_waiting = True
            with self.lock:
                self.reader_waiting = False
                for frame in frames:
                    self._take(frame)
                now = self.clock()
                for gate in self.gates.values():
                    if gate.next_wakeup() <= now:
                        self._up(gate.on_wakeup(now))
                self._to_motors()
                for gate in self.gates.values():
                    self.news(gate.guard)

    def _drain(self, wait: float) -> list[can.Message]:
        """What the real bus holds: the first frame within ``wait`` s, then all that is there
        (at most 256), so that replies are never taken in later than they could be."""
        frames: list[can.Message] = []
        try:
            frame = self.inner.recv(timeout=wait)
            while frame is not None:
                frames.append(frame)
                frame = self.inner.recv(timeout=0) if len(frames) < 256 else None
        except can.CanError:
            pass
        return frames

    def _take(self, frame: can.Message) -> None:
        now = self.clock()
        if frame.is_extended_id and self.codec.is_canergy_id(frame.arbitration_id):
            try:
                msg = self.codec.decode(
                    frame.arbitration_id, bytes(frame.data), direction=Direction.TO_CLIENT
                )
            except DecodeError:
                msg = None
            if isinstance(msg, ToClient) and msg.node in self.route.by_node:
                self._up(self.route.by_node[msg.node].on_message(msg, now))
                return
        self._up(self.route.from_bus(frame, now))
        while True:
            try:
                self.incoming.put_nowait(frame)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self.incoming.get_nowait()
                    self.dropped += 1

    def _up(self, messages: list[Message]) -> None:
        for msg in messages:
            arbitration_id, data = self.codec.encode(msg)
            self._inner_send(can.Message(arbitration_id=arbitration_id, data=data))

    def _to_motors(self) -> None:
        for frame in self.route.outgoing():
            self._inner_send(frame)

    def _inner_send(self, frame: can.Message) -> None:
        try:
            self.inner.send(frame)
        except can.CanError:
            self.send_failures += 1

    def shutdown(self) -> None:
        """Exit motor mode on every guarded motor, stop the reader, close the real bus."""
        if self._is_shutdown:
            return
        with self.lock:
            now = self.clock()
            for gate in self.gates.values():
                self._up(gate.halt(now))
                gate.from_app(EXIT, now)
            self._to_motors()
            for gate in self.gates.values():
                self._inner_send(
                    can.Message(arbitration_id=gate.motor_id, data=EXIT, is_extended_id=False)
                )
        self.stopping.set()
        self.thread.join(timeout=5)
        super().shutdown()
        self.inner.shutdown()
