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

Why the proxy lives here rather than in the supervisor: the application's commands then take one
function call to reach the clamp (no second process in their path), and the supervisor needs
nothing new (the proxy is an ordinary client to it). What it costs: if this process dies the
motor keeps its last command (clamped under the cap, but no longer re-clamped nor stopped) until
its own timeout (Damiao: ``CAN Timeout``; CubeMars AK: none), and the supervisor sees its proxy
go silent; docs/guide/drives.md says what to arm.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import can

from canergy.codec import Codec, DecodeError
from canergy.core import Timing
from canergy.devices.guard import DeviceConfig
from canergy.devices.mit import (
    EXIT,
    FW_PER_W,
    MODELS,
    UNM_PER_NM,
    MitLimits,
    cap_for_power,
    default_master,
    side_channel,
)
from canergy.devices.mit_gate import MitCounts, MitGate
from canergy.live.runtime import monotonic_us
from canergy.messages import Direction, Message, ToClient

log = logging.getLogger(__name__)

INCOMING_MAX = 10_000
"""Frames kept for an application that does not read them (a socket's buffer drops too)."""


class MitRefused(can.CanOperationError):
    """A frame to a guarded motor was not sent (``on_refused="raise"``)."""


@dataclass(frozen=True, slots=True)
class MitMotor:
    """One guarded motor: its CAN id, its proxy's canergy node id, its model, and the cap."""

    motor_id: int
    node: int
    model: str = "DM4310"
    max_torque: float | None = None
    """N·m: the cap while the budget lasts (default: the model's torque range)."""
    max_power: float | None = None
    """W: instead of ``max_torque``, the largest cap whose envelope stays within it."""
    max_speed: float | None = None
    """rad/s: the velocity set point's cap (default: the model's range)."""
    resistance: float | None = None
    """Ω: the phase resistance where the table has none (CubeMars AK)."""
    master_id: int | None = None
    """The replies' identifier (default: 0 for CubeMars, motor_id + 0x10 for Damiao)."""
    hold_us: int = 20_000


def gate_for(
    motor: MitMotor, now: int, timing: Timing, config: dict[str, Any] | None = None
) -> MitGate:
    """The gate of ``motor`` (``ValueError`` for an unknown model or a missing figure)."""
    if motor.model not in MODELS:
        raise ValueError(f"unknown MIT model {motor.model!r}: one of {', '.join(sorted(MODELS))}")
    model = MODELS[motor.model]
    r = Fraction(motor.resistance) if motor.resistance is not None else model.resistance
    if r is None:
        raise ValueError(f"{model.name}: no phase resistance in the table; give it (ohms)")
    if motor.max_power is not None:
        torque = cap_for_power(model, round(motor.max_power * FW_PER_W), r)
    elif motor.max_torque is not None:
        torque = min(round(motor.max_torque * UNM_PER_NM), int(model.t_max * UNM_PER_NM))
    else:
        torque = int(model.t_max * UNM_PER_NM)
    speed = motor.max_speed if motor.max_speed is not None else float(model.v_max)
    limits = MitLimits(torque, min(round(speed * UNM_PER_NM), int(model.v_max * UNM_PER_NM)))
    device = DeviceConfig(limits=limits, timing=timing, **(config or {}))
    nonce = secrets.randbits(16)
    return MitGate(
        motor.motor_id, motor.node, model, device, now, nonce, resistance=r, hold_us=motor.hold_us
    )


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
        **kwargs: Any,
    ) -> None:
        if on_refused not in ("count", "raise"):
            raise ValueError("on_refused: 'count' or 'raise'")
        self.inner = bus
        self.codec = codec or Codec()
        self.clock = clock
        self.on_refused = on_refused
        self.lock = threading.Lock()
        now = clock()
        self.gates: dict[int, MitGate] = {}
        self.masters: dict[int, list[MitGate]] = {}
        for m in motors:
            gate = gate_for(m, now, timing or Timing(), guard_config)
            if m.motor_id in self.gates or m.node in {g.guard.node for g in self.gates.values()}:
                raise ValueError(f"motor {m.motor_id} or node {m.node} given twice")
            self.gates[m.motor_id] = gate
            master = m.master_id
            if master is None:
                master = default_master(gate.model, m.motor_id)
            self.masters.setdefault(master, []).append(gate)
        self.by_node = {g.guard.node: g for g in self.gates.values()}
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
    def _side(self, frame: can.Message) -> tuple[MitGate, str] | None:
        """The motor a frame reaches outside MIT mode, and how (``mit.side_channel``)."""
        for gate in self.gates.values():
            why = side_channel(
                gate.model, gate.motor_id, frame.arbitration_id, frame.is_extended_id
            )
            if why is not None:
                return gate, why
        return None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not msg.is_error_frame and (side := self._side(msg)) is not None:
            with self.lock:
                side[0].refuse(side[1])
            self._refused(side[0], side[1])
            return
        gate = None if msg.is_extended_id else self.gates.get(msg.arbitration_id)
        if gate is None or msg.is_error_frame:
            self.inner.send(msg, timeout)
            return
        if msg.is_remote_frame:  # what a firmware makes of one is not documented: not sent
            with self.lock:
                gate.refuse("remote frame")
            self._refused(gate, "remote frame")
            return
        if self.reader_waiting:  # the reader has replies to take in: let it have the lock first
            time.sleep(0)
        with self.lock:
            verdict = gate.from_app(bytes(msg.data), self.clock())
            self._to_motor(gate)
        if verdict.frame is None:
            self._refused(gate, verdict.why or "refused")
            return
        out = can.Message(
            arbitration_id=msg.arbitration_id, data=verdict.frame, is_extended_id=False
        )
        self.inner.send(out, timeout)

    def _refused(self, gate: MitGate, why: str) -> None:
        n = gate.counts.refused
        if n == 1 or n % 100 == 0:
            log.warning(
                "MIT motor %d: command refused (%s); %d refused so far", gate.motor_id, why, n
            )
        if self.on_refused == "raise":
            raise MitRefused(f"MIT motor {gate.motor_id}: command refused ({why})")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self.incoming.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def counts(self, motor_id: int) -> MitCounts:
        return self.gates[motor_id].counts

    def status(self, motor_id: int) -> dict[str, Any]:
        with self.lock:
            return self.gates[motor_id].status(self.clock())

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
                    self._to_motor(gate)

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
            if isinstance(msg, ToClient) and msg.node in self.by_node:
                self._up(self.by_node[msg.node].on_message(msg, now))
                return
        if not frame.is_error_frame and (side := self._side(frame)) is not None:
            self._up(side[0].on_foreign(bytes(frame.data), now))
        if not frame.is_extended_id and not frame.is_error_frame:
            at = now
            if frame.timestamp > 0:
                at -= max(0, min(round((time.time() - frame.timestamp) * 1e6), 1_000_000))
            for gate in self.masters.get(frame.arbitration_id, ()):
                self._up(gate.from_motor(bytes(frame.data), at, now))
            if (target := self.gates.get(frame.arbitration_id)) is not None:
                self._up(target.on_foreign(bytes(frame.data), now))
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

    def _to_motor(self, gate: MitGate) -> None:
        for data in gate.take_frames():
            frame = can.Message(arbitration_id=gate.motor_id, data=data, is_extended_id=False)
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
                self._to_motor(gate)
                self._inner_send(
                    can.Message(arbitration_id=gate.motor_id, data=EXIT, is_extended_id=False)
                )
        self.stopping.set()
        self.thread.join(timeout=5)
        super().shutdown()
        self.inner.shutdown()
