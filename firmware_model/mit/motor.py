"""An emulated MIT-mode motor: the frames of ``canergy.devices.mit`` in front of the CiA 402
drive's motor physics (``firmware_model.drive.motor``), knowing the energy it draws.

``MitMotorModel`` is pure (time passed in): ``receive`` takes one frame addressed to the motor
and returns its reply (every frame is answered, as the firmwares do), ``advance`` moves the motor
on in 1 ms steps. What it does:

- enter motor mode (``FF×7 FC``), exit (``FD``: the power stage off, no current), zero (``FE``:
  the position origin moves to where the motor is);
- a command is held until the next: ``τ = kp·(p − θ) + kd·(v − ω) + t_ff``, limited to the
  model's torque range (the firmware's current limit), then to no motoring past the model's
  velocity range (the back-EMF limit of the supply; ``Motor.speed_limited``);
- the reply: position, velocity and torque over the model's ranges (saturated), from the
  reply's identifier ``master_id``.

Damiao models answer a register read on 0x7FF (``canergy.devices.mit.read_register``) for the
CAN Timeout (RID 9: ``can_timeout``, in 50 µs units, 0 off) from the master id, and enforce it:
an enabled motor that receives no frame for longer than the timeout disables itself with the
fault ``LOST_COMM`` (0xD) in its replies' state, held until clear error (``FF×7 FB``).

What the real firmware does, as modelled here (no text copied): the DM4310 firmware as
reconstructed in the public repository umeow0716/damiao_firmware (``app/src/safety.c``, the
fault monitor; ``app/src/motor_control.c``, the trip) counts the time since the last frame in
its 50 µs control ticks only while the motor is enabled (the count restarts at 0 otherwise),
restarts it on every frame whose identifier's low byte is the motor's id (before the command
family is looked at: a mode frame 0x100 + id counts too, 0x7FF does not), and latches the fault
once the count is above the register (above, not equal), which disarms the power stage (neutral
PWM: the motor coasts); only clear error unlatches it. The status code 0xD (``LOST_COMM``, tied
to register 9 ``TIMEOUT``) is as jia-xie/python-damiao-driver's protocol notes list it. Assumed
here, not found in either: enter motor mode while the fault is latched leaves the motor off. The
model counts in µs, checked every 1 ms step (so it disables within one step of the timeout),
and hears only frames on the motor's own id (``MitFace``).

Quirk for tests: ``ignores_exit`` (exit motor mode does nothing: a motor that does not obey).
``MitFace`` runs a model on a python-can bus in a thread, advancing it every 1 ms.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import can

from canergy.devices.mit import (
    CLEAR_ERROR,
    ENTER,
    EXIT,
    PARAMETER_ID,
    READ_REGISTER,
    TIMEOUT_RID,
    TIMEOUT_UNIT_US,
    ZERO,
    Command,
    MitModel,
    Values,
    decode,
    pack_reply,
)
from firmware_model.drive.motor import LoadTorque, Motor, MotorParams

__all__ = ["LOST_COMM", "MitFace", "MitMotorModel"]

LOST_COMM = 0xD
"""Damiao's reply state for a motor its CAN Timeout disabled."""


@dataclass
class MitMotorModel:
    motor_id: int
    model: MitModel
    now_us: int
    master_id: int = 0
    load: LoadTorque = field(default_factory=LoadTorque)
    inertia: float = 2e-3
    damping: float = 5e-3
    ignores_exit: bool = False
    can_timeout: int = 0
    """Damiao's CAN Timeout register, 50 µs units (0: off; Damiao models only)."""

    def __post_init__(self) -> None:
        r = self.model.resistance if self.model.resistance is not None else 0.2
        params = MotorParams(
            kt=float(self.model.torque_constant),
            resistance=float(r),
            inertia=self.inertia,
            damping=self.damping,
        )
        self.motor = Motor(params, self.load)
        self.enabled = False
        self.fault = 0
        """A latched fault's state code (0: none; ``LOST_COMM``: the CAN Timeout ran out)."""
        self.quiet_since = self.now_us
        """The last frame on the motor's id (or its enabling, if later)."""
        self.timeouts = 0
        """How often the CAN Timeout disabled the motor."""
        self.command: Values | None = None
        self.origin = 0.0
        self.started_us = self.now_us
        self.frames = 0
        self.commands: list[Values] = []
        """Every command received in motor mode (what the motor was asked for)."""
        self.positions: list[float] = []
        """Where the motor was (rad, from its origin) as each of ``commands`` came."""
        self.torque_max_seen = 0.0

    @property
    def drawn_uj(self) -> int:
        return self.motor.energy.drawn.uj

    def receive(self, data: bytes) -> bytes:
        """One frame for this motor; its reply."""
        self.frames += 1
        if not self.fault:
            self.quiet_since = self.now_us
        if data == ENTER:
            self.enabled = self.enabled or not self.fault
        elif data == CLEAR_ERROR:
            self.fault = 0
        elif data == EXIT:
            if not self.ignores_exit:
                self.enabled, self.command = False, None
        elif data == ZERO:
            self.origin = self.motor.theta
        elif len(data) == 8 and self.enabled:
            try:
                self.command = decode(self.model, Command.unpack(data))
            except ValueError:
                pass
            else:
                self.commands.append(self.command)
                self.positions.append(self.motor.theta - self.origin)
        return self.reply()

    def register(self, data: bytes) -> bytes | None:
        """A 0x7FF frame: the answer to a read of the CAN Timeout addressed to this motor
        (Damiao only; None: not one)."""
        m = self.motor_id
        head = bytes([m & 0xFF, m >> 8 & 0x07, READ_REGISTER, TIMEOUT_RID])
        if not self.model.damiao or len(data) != 8 or data[:4] != head:
            return None
        return head + self.can_timeout.to_bytes(4, "little")

    def reply(self) -> bytes:
        fp, fv, _, _, ft = self.model.fields()
        m = self.motor
        codes = []
        for f, x in ((fp, m.theta - self.origin), (fv, m.omega), (ft, m.torque)):
            n = round((x - float(f.lo)) * f.top / float(2 * f.span))
            codes.append(min(max(n, 0), f.top))
        state = self.fault or (1 if self.enabled else 0)
        p, v, t = codes
        return pack_reply(self.model, self.motor_id, p, v, t, state=state)

    def advance(self, now_us: int) -> None:
        while self.now_us < now_us:
            self._watch_timeout()
            dt_us = min(1000, now_us - self.now_us)
            self._step(dt_us / 1e6)
            self.now_us += dt_us
        self._watch_timeout()

    def _watch_timeout(self) -> None:
        """Damiao's CAN Timeout (module doc): counted only while enabled."""
        if not self.enabled:
            self.quiet_since = max(self.quiet_since, self.now_us)
            return
        limit = self.can_timeout * TIMEOUT_UNIT_US
        if self.model.damiao and limit and self.now_us - self.quiet_since > limit:
            self.enabled, self.command, self.fault = False, None, LOST_COMM
            self.timeouts += 1

    def _step(self, dt: float) -> None:
        m = self.motor
        t = (self.now_us - self.started_us) / 1e6
        tau = 0.0
        c = self.command
        if self.enabled and c is not None:
            theta = m.theta - self.origin
            tau = float(c.kp) * (float(c.p) - theta) + float(c.kd) * (float(c.v) - m.omega)
            tau += float(c.t)
            t_max = float(self.model.t_max)
            tau = max(-t_max, min(t_max, tau))
            tau = m.speed_limited(tau, dt, t, float(self.model.v_max))
        self.torque_max_seen = max(self.torque_max_seen, abs(tau))
        m.step(dt, tau / m.params.kt, t)


class MitFace:
    """A ``MitMotorModel`` on ``bus``: frames for its id in, replies out."""

    def __init__(self, model: MitMotorModel, bus: can.BusABC) -> None:
        self.model = model
        self.bus = bus
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="mit-motor")

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        while not self.stopping.is_set():
            frame = self.bus.recv(timeout=0.001)
            now = time.monotonic_ns() // 1000
            reply = None
            with self.lock:
                self.model.advance(now)
                ours = frame is not None and not frame.is_extended_id
                if ours and frame is not None and frame.arbitration_id == self.model.motor_id:
                    reply = self.model.receive(bytes(frame.data))
                elif ours and frame is not None and frame.arbitration_id == PARAMETER_ID:
                    reply = self.model.register(bytes(frame.data))
            if reply is not None:
                out = can.Message(
                    arbitration_id=self.model.master_id, data=reply, is_extended_id=False
                )
                self.bus.send(out)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(timeout=5)
        self.bus.shutdown()
