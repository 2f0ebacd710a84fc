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
CAN Timeout (RID 9: ``can_timeout``, in 50 µs units, 0 off; held, not enforced) from the master
id.

Quirk for tests: ``ignores_exit`` (exit motor mode does nothing: a motor that does not obey).
``MitFace`` runs a model on a python-can bus in a thread, advancing it every 1 ms.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import can

from canergy.devices.mit import (
    ENTER,
    EXIT,
    PARAMETER_ID,
    READ_REGISTER,
    TIMEOUT_RID,
    ZERO,
    Command,
    MitModel,
    Values,
    decode,
    pack_reply,
)
from firmware_model.drive.motor import LoadTorque, Motor, MotorParams

__all__ = ["MitFace", "MitMotorModel"]


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
    """Damiao's CAN Timeout register, 50 µs units (0: off)."""

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
        if data == ENTER:
            self.enabled = True
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
        state = 1 if self.enabled else 0
        p, v, t = codes
        return pack_reply(self.model, self.motor_id, p, v, t, state=state)

    def advance(self, now_us: int) -> None:
        while self.now_us < now_us:
            dt_us = min(1000, now_us - self.now_us)
            self._step(dt_us / 1e6)
            self.now_us += dt_us

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
