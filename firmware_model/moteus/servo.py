"""An emulated moteus controller: the CAN-FD register protocol in front of the CiA 402 drive's
motor physics (``firmware_model.drive.motor``), knowing the energy it draws.

``ServoModel`` is pure (time passed in): ``receive`` takes one frame's data addressed to it and
returns the reply's data (None: no reply), ``advance`` moves the motor on. What it does, as the
protocol documents it:

- mode 0 stops (power stage off), 10 is position mode: torque = kp·kp_scale·(x_c − x) +
  kd·kd_scale·(v_c − v) + feed-forward, limited to the maximum torque register and k_t times
  ``servo.max_current_A``; modes 9 (current: q current register 0x01c) and 12 (zero velocity);
  writing the mode resets the command registers to their defaults; other modes are taken and do
  nothing (the emulator has no PWM or voltage stage);
- the electrical power is held to ``servo.max_power_W``; motoring torque fades from
  ``servo.max_velocity`` to nothing at max_velocity + ``servo.max_velocity_derate``;
- the watchdog: no command for ``servo.default_timeout_s`` (or register 0x027 when written) and
  position mode becomes mode 11, timeout, with the power stage off (``servo.timeout_mode`` 0);
- reads of any register it knows in any type; the diagnostic stream on channel 1 with ``conf
  get`` and ``conf set`` (answered ``OK`` or ``ERR``), polled with 0x42.

Quirks for tests: ``current_cap`` (``servo.max_current_A`` is clamped to it: a limit that does not
read back as written), ``ignores_stop`` (mode 0 does nothing: a controller that does not obey),
``answers_reads`` (False: ``conf get`` goes unanswered, set at any time: a read-back that fails).

``ServoFace`` runs a model on a python-can bus in a thread, advancing it every 1 ms.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import can

from canergy.devices.moteus import (
    DIAGNOSTIC_CHANNEL,
    Error,
    Mode,
    Poll,
    Read,
    Reg,
    Reply,
    Stream,
    Subframe,
    Write,
    can_id,
    decode,
    encode,
    extended,
    split_id,
    stream_lines,
)
from firmware_model.drive.motor import LoadTorque, Motor, MotorParams

__all__ = ["ServoFace", "ServoModel"]

COMMAND_DEFAULTS = {
    Reg.COMMAND_POSITION: math.nan,
    Reg.COMMAND_VELOCITY: 0.0,
    Reg.FEEDFORWARD_TORQUE: 0.0,
    Reg.KP_SCALE: 1.0,
    Reg.KD_SCALE: 1.0,
    Reg.MAX_TORQUE: math.nan,
    Reg.WATCHDOG_TIMEOUT: 0.0,
    0x01C: 0.0,  # commanded q current
}
TWO_PI = 2 * math.pi


@dataclass
class ServoModel:
    node: int
    now_us: int
    params: MotorParams = field(default_factory=lambda: MotorParams(kt=0.1, resistance=0.5))
    load: LoadTorque = field(default_factory=LoadTorque)
    kp: float = 2.0
    """N·m per revolution (``servo.pid_position.kp``)."""
    kd: float = 0.05
    """N·m per rev/s."""
    current_cap: float | None = None
    ignores_stop: bool = False
    answers_reads: bool = True
    config: dict[str, float] = field(
        default_factory=lambda: {
            "servo.max_power_W": 450.0,
            "servo.max_current_A": 100.0,
            "servo.max_velocity": 100.0,
            "servo.max_velocity_derate": 2.0,
            "servo.default_timeout_s": 0.1,
            "servo.pid_position.kp": 2.0,
        }
    )

    def __post_init__(self) -> None:
        self.motor = Motor(self.params, self.load)
        self.mode = Mode.STOPPED
        self.commands: dict[int, float] = dict(COMMAND_DEFAULTS)
        self.last_command_us = self.now_us
        self.hold = 0.0
        """Position mode's control position, revolutions."""
        self.started_us = self.now_us
        self.diag_in = bytearray()
        self.diag_out = bytearray()
        self.history: list[tuple[int, str]] = [(self.now_us, self.mode.name)]

    @property
    def drawn_uj(self) -> int:
        return self.motor.energy.drawn.uj

    def _set_mode(self, mode: Mode) -> None:
        if mode is not self.mode:
            self.mode = mode
            self.history.append((self.now_us, mode.name))

    # -- frames ---------------------------------------------------------------------------
    def receive(self, data: bytes, reply: bool) -> bytes | None:
        subframes, _ = decode(data)  # a real controller acts on what parsed
        out: list[Subframe] = []
        for s in subframes:
            if isinstance(s, Write):
                self._write(s)
            elif isinstance(s, Read):
                out += self._read(s)
            elif isinstance(s, Stream) and not s.server and s.channel == DIAGNOSTIC_CHANNEL:
                for line in stream_lines(self.diag_in, s.data):
                    answer = self._conf(line)
                    if answer is not None:
                        self.diag_out += answer.encode() + b"\r\n"
                if reply:  # the answer to a 0x40 is a 0x41, data or not
                    out.append(self._stream(48))
            elif isinstance(s, Poll) and s.channel == DIAGNOSTIC_CHANNEL and reply:
                out.append(self._stream(min(s.most, 48)))
        return encode(*out) if reply and out else None

    def _stream(self, most: int) -> Stream:
        data, self.diag_out = bytes(self.diag_out[:most]), self.diag_out[most:]
        return Stream(True, DIAGNOSTIC_CHANNEL, data)

    def _write(self, s: Write) -> None:
        for register, value in enumerate(s.values, start=s.start):
            if register == Reg.MODE:
                self._command_mode(value)
            elif register in COMMAND_DEFAULTS:
                self.commands[register] = value

    def _command_mode(self, value: float) -> None:
        self.commands = dict(COMMAND_DEFAULTS)
        self.last_command_us = self.now_us
        if value == Mode.STOPPED:
            if not self.ignores_stop:
                self._set_mode(Mode.STOPPED)
        elif self.mode in (Mode.TIMEOUT, Mode.FAULT):
            return  # latched: only a stop leaves it
        elif value in Mode.__members__.values():
            self._set_mode(Mode(int(value)))
            if self.mode is Mode.POSITION:
                self.hold = self.motor.theta / TWO_PI

    def _read(self, s: Read) -> list[Subframe]:
        values = [self._register(r) for r in range(s.start, s.start + s.count)]
        if all(v is not None for v in values):
            return [Reply(s.kind, s.start, tuple(v for v in values if v is not None))]
        return [
            Error(True, s.start + i, 1) if v is None else Reply(s.kind, s.start + i, (v,))
            for i, v in enumerate(values)
        ]

    def _register(self, register: int) -> float | None:
        m = self.motor
        values: dict[int, float] = {
            Reg.MODE: float(self.mode),
            Reg.POSITION: m.theta / TWO_PI,
            Reg.VELOCITY: m.omega / TWO_PI,
            Reg.TORQUE: m.torque,
            Reg.Q_CURRENT: m.current,
            Reg.POWER: m.power_w,
            Reg.VOLTAGE: self.params.dc_voltage,
            Reg.TEMPERATURE: 30.0,
            Reg.FAULT: 0.0,
        }
        return values.get(register, self.commands.get(register))

    def _conf(self, line: str) -> str | None:
        words = line.split()
        if words[:2] == ["conf", "get"] and not self.answers_reads:
            return None
        if words[:2] == ["conf", "get"] and len(words) == 3 and words[2] in self.config:
            return f"{self.config[words[2]]:.6f}"
        if words[:2] == ["conf", "set"] and len(words) == 4 and words[2] in self.config:
            try:
                value = float(words[3])
            except ValueError:
                return "ERR bad value"
            if words[2] == "servo.max_current_A" and self.current_cap is not None:
                value = min(value, self.current_cap)
            self.config[words[2]] = value
            return "OK"
        return "ERR unknown command"

    # -- physics --------------------------------------------------------------------------
    def advance(self, now_us: int) -> None:
        while self.now_us < now_us:
            dt_us = min(1000, now_us - self.now_us)
            self._step(dt_us / 1e6)
            self.now_us += dt_us

    def _watchdog(self) -> None:
        timeout = self.commands[Reg.WATCHDOG_TIMEOUT] or self.config["servo.default_timeout_s"]
        late = self.now_us - self.last_command_us > timeout * 1e6
        if self.mode in (Mode.POSITION, Mode.CURRENT, Mode.ZERO_VELOCITY) and late:
            self._set_mode(Mode.TIMEOUT)  # servo.timeout_mode 0: the power stage off

    def _torque(self) -> float:
        m, c = self.motor, self.commands
        x, v = m.theta / TWO_PI, m.omega / TWO_PI
        if self.mode is Mode.POSITION:
            target = self.hold if math.isnan(c[Reg.COMMAND_POSITION]) else c[Reg.COMMAND_POSITION]
            self.hold = target + c[Reg.COMMAND_VELOCITY] * 0.001
            kp = self.config["servo.pid_position.kp"] * c[Reg.KP_SCALE]
            tau = kp * (target - x) + self.kd * c[Reg.KD_SCALE] * (c[Reg.COMMAND_VELOCITY] - v)
            tau += c[Reg.FEEDFORWARD_TORQUE]
            if not math.isnan(c[Reg.MAX_TORQUE]):
                tau = max(-abs(c[Reg.MAX_TORQUE]), min(abs(c[Reg.MAX_TORQUE]), tau))
            return tau
        if self.mode is Mode.CURRENT:
            return float(self.params.kt * c[0x01C])
        if self.mode is Mode.ZERO_VELOCITY:
            return -self.kd * v
        return 0.0

    def _step(self, dt: float) -> None:
        m, p, conf = self.motor, self.params, self.config
        t = (self.now_us - self.started_us) / 1e6
        self._watchdog()
        tau = self._torque()
        tau_max = p.kt * abs(conf["servo.max_current_A"])
        tau = max(-tau_max, min(tau_max, tau))
        v_max, derate = abs(conf["servo.max_velocity"]), abs(conf["servo.max_velocity_derate"])
        speed = abs(m.omega) / TWO_PI
        if tau * m.omega > 0 and speed > v_max:  # motoring past the limit fades out
            tau *= max(0.0, 1 - (speed - v_max) / derate) if derate > 0 else 0.0
        tau = m.speed_limited(tau, dt, t, TWO_PI * (v_max + derate))
        tau = self._power_limited(tau, conf["servo.max_power_W"])
        m.step(dt, tau / p.kt, t)

    def _power_limited(self, tau: float, p_max: float) -> float:
        """The largest |τ| in τ's direction whose τ·ω + R·(τ/k_t)² is at most ``p_max``, at
        the speed now and at the end of the step's worst (taken as 10% faster)."""
        p = self.params
        a = p.resistance / p.kt**2
        s = 1.0 if tau >= 0 else -1.0
        b = s * self.motor.omega * 1.1 if s * self.motor.omega > 0 else s * self.motor.omega
        if a > 0:
            most = (-b + math.sqrt(b * b + 4 * a * max(0.0, p_max))) / (2 * a)
        else:
            most = p_max / b if b > 0 else math.inf
        return s * min(abs(tau), max(0.0, most))


class ServoFace:
    """A ``ServoModel`` on ``bus``: frames for its id in, replies out."""

    def __init__(self, model: ServoModel, bus: can.BusABC) -> None:
        self.model = model
        self.bus = bus
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="moteus-servo")

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        while not self.stopping.is_set():
            frame = self.bus.recv(timeout=0.001)
            now = time.monotonic_ns() // 1000
            reply = None
            with self.lock:
                self.model.advance(now)
                if frame is not None and not frame.is_error_frame:
                    source, destination, wants, _ = split_id(frame.arbitration_id)
                    if destination == self.model.node:
                        data = self.model.receive(bytes(frame.data), wants)
                        reply = None if data is None else (source, data)
            if reply is not None:
                arbitration_id = can_id(self.model.node, reply[0])
                self.bus.send(
                    can.Message(
                        arbitration_id=arbitration_id,
                        data=reply[1],
                        is_extended_id=extended(arbitration_id),
                        is_fd=True,
                        bitrate_switch=True,
                    )
                )

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(timeout=5)
        self.bus.shutdown()
