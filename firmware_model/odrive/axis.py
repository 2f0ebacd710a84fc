"""An emulated ODrive axis: CAN Simple (firmware 0.5 or 0.6) in front of the CiA 402 drive's
motor physics (``firmware_model.drive.motor``), knowing the energy it draws.

``AxisModel`` is pure (time passed in): ``receive`` takes one frame addressed to the axis and
returns the answers, ``advance`` moves the motor on. What it does, as the firmware documents it:

- Set_Axis_State: CLOSED_LOOP_CONTROL (8) when no error is latched, IDLE (1); Estop latches
  ESTOP_REQUESTED and goes IDLE; Clear_Errors clears it;
- Set_Limits: ``vel_limit`` and the current limit, as float32; Set_Input_Torque and
  Set_Input_Vel (torque control and velocity control, ``vel_gain``);
- the torque is clamped to ``kt`` × the current limit; in torque control the motor does no
  motoring past the velocity limit (``enable_torque_mode_vel_limit``); past ``vel_tolerance`` ×
  the limit the axis faults and goes IDLE (overspeed);
- heartbeat every 100 ms, encoder estimates every 10 ms; remote requests for 0x017 (bus voltage
  and current) and, on 0.6, 0x01D (electrical and mechanical power); RxSdo reads of the four
  endpoints it knows (``VEL_LIMIT_EP``, ``CURRENT_LIMIT_EP``, ``ENABLE_WATCHDOG_EP`` a bool in
  byte 4, ``WATCHDOG_TIMEOUT_EP`` float32 s) on 0.6;
- the watchdog (``enable_watchdog``, ``watchdog_timeout``, off by default as on a new ODrive):
  armed with a timeout above 0, an axis in closed loop not fed for the timeout latches
  WATCHDOG_TIMER_EXPIRED and goes IDLE; it is fed by the setpoints (Set_Input_Torque,
  Set_Input_Vel) and by entering closed loop, as ODrive's CAN examples describe it.

Quirks for tests: ``current_cap`` (the current limit is clamped to it: a limit that does not read
back as written), ``ignores_stop`` (Estop and IDLE do nothing: a device that does not obey),
``answers_reads`` (False: RxSdo reads go unanswered, set at any time: a read-back that fails).

``AxisFace`` runs a model on a python-can bus in a thread, advancing it every 1 ms and, for a
frame, to the frame's arrival (its timestamp, at most 1 s back) before taking it in: a thread
held off on a loaded host does not run the motor on at the old state past frames that had
arrived (a real axis takes them in within its control cycle).
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass, field

import can

from canergy.devices.odrive import AxisState, Cmd, can_id, f32, split_id
from firmware_model.drive.motor import LoadTorque, Motor, MotorParams

__all__ = [
    "CURRENT_LIMIT_EP",
    "ENABLE_WATCHDOG_EP",
    "VEL_LIMIT_EP",
    "WATCHDOG_TIMEOUT_EP",
    "AxisFace",
    "AxisModel",
]

VEL_LIMIT_EP, CURRENT_LIMIT_EP = 401, 178
ENABLE_WATCHDOG_EP, WATCHDOG_TIMEOUT_EP = 215, 216
"""The emulator's endpoint ids (a real firmware's come from its flat_endpoints.json)."""
WATCHDOG_EXPIRED = {"0.5": 0x800, "0.6": 0x1000000}
ESTOP_REQUESTED = 0x4000
OVERSPEED = 0x1000
HEARTBEAT_US, ESTIMATES_US = 100_000, 10_000
CONTROL_TORQUE, CONTROL_VELOCITY = 1, 2
Frame = tuple[int, bytes]


@dataclass
class AxisModel:
    node: int
    now_us: int
    firmware: str = "0.6"
    params: MotorParams = field(default_factory=lambda: MotorParams(kt=0.05, resistance=0.5))
    load: LoadTorque = field(default_factory=LoadTorque)
    vel_limit: float = 2.0
    current_limit: float = 10.0
    vel_tolerance: float = 1.2
    vel_gain: float = 0.02
    """N·m per rev/s (velocity control)."""
    current_cap: float | None = None
    ignores_stop: bool = False
    answers_reads: bool = True
    enable_watchdog: bool = False
    watchdog_timeout: float = 0.0
    """s (0: off even when enabled)."""

    def __post_init__(self) -> None:
        self.motor = Motor(self.params, self.load)
        self.state = AxisState.IDLE
        self.error = 0
        self.control_mode = CONTROL_TORQUE
        self.input_torque = 0.0
        self.input_vel = 0.0
        self.started_us = self.now_us
        self.fed_us = self.now_us
        self.next_heartbeat = self.now_us
        self.next_estimates = self.now_us
        self.history: list[tuple[int, str]] = [(self.now_us, self.state.name)]

    @property
    def drawn_uj(self) -> int:
        return self.motor.energy.drawn.uj

    def _set_state(self, state: AxisState) -> None:
        if state is not self.state:
            self.state = state
            self.history.append((self.now_us, state.name))

    def receive(self, cmd: int, data: bytes, remote: bool) -> list[Frame]:
        """One frame for this axis; the frames it answers with."""
        if remote:
            return self._answer(cmd)
        if cmd == Cmd.ESTOP and not self.ignores_stop:
            self.error |= ESTOP_REQUESTED
            self._set_state(AxisState.IDLE)
        elif cmd == Cmd.SET_AXIS_STATE and len(data) >= 4:
            (want,) = struct.unpack_from("<I", data)
            if want == AxisState.IDLE and not self.ignores_stop:
                self._set_state(AxisState.IDLE)
            elif want == AxisState.CLOSED_LOOP_CONTROL and not self.error:
                self.fed_us = self.now_us
                self._set_state(AxisState.CLOSED_LOOP_CONTROL)
        elif cmd == Cmd.CLEAR_ERRORS:
            self.error = 0
        elif cmd == Cmd.SET_LIMITS and len(data) == 8:
            velocity, current = struct.unpack("<ff", data)
            self.vel_limit = velocity
            cap = self.current_cap
            self.current_limit = current if cap is None else min(current, f32(cap))
        elif cmd == Cmd.SET_INPUT_TORQUE and len(data) >= 4:
            (self.input_torque,) = struct.unpack_from("<f", data)
            self.control_mode = CONTROL_TORQUE
            self.fed_us = self.now_us
        elif cmd == Cmd.SET_INPUT_VEL and len(data) == 8:
            self.input_vel, _ = struct.unpack("<ff", data)
            self.control_mode = CONTROL_VELOCITY
            self.fed_us = self.now_us
        elif cmd == Cmd.RX_SDO and len(data) == 8 and self.firmware == "0.6":
            opcode, endpoint = struct.unpack_from("<BH", data)
            values = {
                VEL_LIMIT_EP: struct.pack("<f", self.vel_limit),
                CURRENT_LIMIT_EP: struct.pack("<f", self.current_limit),
                ENABLE_WATCHDOG_EP: struct.pack("<?3x", self.enable_watchdog),
                WATCHDOG_TIMEOUT_EP: struct.pack("<f", self.watchdog_timeout),
            }
            if opcode == 0 and endpoint in values and self.answers_reads:
                body = struct.pack("<BHB", 0, endpoint, 0) + values[endpoint]
                return [(Cmd.TX_SDO, body)]
        return []

    def _answer(self, cmd: int) -> list[Frame]:
        m = self.motor
        volts = self.params.dc_voltage
        if cmd == Cmd.BUS_VOLTAGE_CURRENT:
            return [(cmd, struct.pack("<ff", volts, m.power_w / volts))]
        if cmd == Cmd.POWERS and self.firmware == "0.6":
            return [(cmd, struct.pack("<ff", m.power_w, m.torque * m.omega))]
        if cmd == Cmd.HEARTBEAT:
            return [self._heartbeat()]
        return []

    def _heartbeat(self) -> Frame:
        return (Cmd.HEARTBEAT, struct.pack("<IBBBB", self.error, self.state, 0, 0, 0))

    def advance(self, now_us: int) -> list[Frame]:
        """Move the motor on to ``now_us`` (1 ms steps); the cyclic frames due."""
        out: list[Frame] = []
        while self.now_us < now_us:
            dt_us = min(1000, now_us - self.now_us)
            self._step(dt_us / 1e6)
            self.now_us += dt_us
        if self.now_us >= self.next_heartbeat:
            self.next_heartbeat = self.now_us + HEARTBEAT_US
            out.append(self._heartbeat())
        if self.now_us >= self.next_estimates:
            self.next_estimates = self.now_us + ESTIMATES_US
            m = self.motor
            est = struct.pack("<ff", m.theta / (2 * math.pi), m.omega / (2 * math.pi))
            out.append((Cmd.ENCODER_ESTIMATES, est))
        return out

    def _step(self, dt: float) -> None:
        m, p = self.motor, self.params
        t = (self.now_us - self.started_us) / 1e6
        tau = 0.0
        w_limit = 2 * math.pi * abs(self.vel_limit)
        if abs(m.omega) > self.vel_tolerance * w_limit:
            self.error |= OVERSPEED
            self._set_state(AxisState.IDLE)
        armed = self.enable_watchdog and self.watchdog_timeout > 0
        starved = self.now_us - self.fed_us > self.watchdog_timeout * 1e6
        if armed and starved and self.state is AxisState.CLOSED_LOOP_CONTROL:
            self.error |= WATCHDOG_EXPIRED[self.firmware]
            self._set_state(AxisState.IDLE)
        if self.state is AxisState.CLOSED_LOOP_CONTROL:
            if self.control_mode == CONTROL_VELOCITY:
                target = max(-self.vel_limit, min(self.vel_limit, self.input_vel))
                tau = self.vel_gain * (target - m.omega / (2 * math.pi))
            else:
                tau = self.input_torque
            tau_max = p.kt * abs(self.current_limit)
            tau = max(-tau_max, min(tau_max, tau))
            tau = m.speed_limited(tau, dt, t, w_limit)
        m.step(dt, tau / p.kt, t)


class AxisFace:
    """An ``AxisModel`` on ``bus``: frames for its node in, answers and cyclic frames out."""

    def __init__(self, model: AxisModel, bus: can.BusABC) -> None:
        self.model = model
        self.bus = bus
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="odrive-axis")

    def start(self) -> None:
        self.thread.start()

    def _send(self, frames: list[Frame]) -> None:
        for cmd, data in frames:
            frame = can.Message(
                arbitration_id=can_id(self.model.node, cmd), data=data, is_extended_id=False
            )
            self.bus.send(frame)

    def _run(self) -> None:
        while not self.stopping.is_set():
            frame = self.bus.recv(timeout=0.001)
            now = time.monotonic_ns() // 1000
            if frame is not None and frame.timestamp > 0:
                # a frame takes effect when it arrived (a drive's controller is not held off
                # as this thread may be): the motor runs on at the state it found until then
                waited = round((time.time() - frame.timestamp) * 1e6)
                now -= max(0, min(waited, 1_000_000))
            with self.lock:
                out = self.model.advance(now)
                if frame is not None and not frame.is_extended_id:
                    node, cmd = split_id(frame.arbitration_id)
                    if node == self.model.node:
                        out += self.model.receive(cmd, bytes(frame.data), frame.is_remote_frame)
            self._send(out)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(timeout=5)
        self.bus.shutdown()
