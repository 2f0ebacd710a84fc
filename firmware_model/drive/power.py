"""The CiA 402 power state machine and the operation modes, pure (time is integer µs).

``PowerStateMachine`` decodes controlwords (CiA 402 transitions 2-12, 15, 16), runs the quick stop
and fault reactions, and computes the statusword. ``demand(...)`` says, each substep, which torque
the drive asks of the motor: profiled velocity (3: ``ramp`` toward 0x60FF then ``VelocityPI``),
cyclic synchronous torque (10: 0x6071), a stopping reaction (reference ramped to 0 on 0x6084 or
0x6085 whatever the mode) or nothing (coast: no torque outside OPERATION ENABLED, QUICK STOP ACTIVE
and FAULT REACTION ACTIVE). State names are python-canopen's ``State402.SW_MASK`` keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "CW_FAULT_RESET",
    "MODES",
    "NOT_READY",
    "OPERATION_ENABLED",
    "Limits",
    "PowerStateMachine",
    "VelocityPI",
    "ramp",
]

NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP = "QUICK STOP ACTIVE"
FAULT_REACTION = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

STATUS_BITS = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY: 0x0031,  # bit 4 voltage enabled, bit 5 quick stop off, bit 0 ready
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP: 0x0017,
    FAULT_REACTION: 0x001F,
    FAULT: 0x0008,
}
"""Statusword bits 0-6 per state (they match canopen's ``State402.SW_MASK``)."""
SW_REMOTE, SW_TARGET_REACHED, SW_INTERNAL_LIMIT = 0x0200, 0x0400, 0x0800

CW_SWITCH_ON, CW_ENABLE_VOLTAGE, CW_QUICK_STOP, CW_ENABLE_OPERATION = 0x01, 0x02, 0x04, 0x08
CW_FAULT_RESET = 0x80

MODES = {0: "NO MODE", 3: "PROFILED VELOCITY", 10: "CYCLIC SYNCHRONOUS TORQUE"}
"""Modes of operation accepted by 0x6060 (0x6502 advertises 3 and 10)."""
PV, CST = 3, 10

TORQUE_STATES = (OPERATION_ENABLED, QUICK_STOP, FAULT_REACTION)
STOPPED_RAD_S = 0.01
"""A stopping reaction is over when its reference is 0 and |ω| is below this."""
MAX_STOP_US = 10_000_000
"""... or after this long in any case."""


def ramp(reference: float, target: float, accel: float, decel: float, dt: float) -> float:
    """``reference`` moved toward ``target`` by one step: at ``accel`` while its magnitude grows,
    at ``decel`` while it shrinks (rad/s, rad/s², s)."""
    if reference == target:
        return reference
    growing = (reference >= 0 and target > reference) or (reference <= 0 and target < reference)
    step = (accel if growing else decel) * dt
    if target > reference:
        return min(target, reference + step)
    return max(target, reference - step)


@dataclass
class VelocityPI:
    """PI velocity controller, torque out (N·m), with a back-calculation anti-windup: when the
    output is clipped the integral is set so that the unclipped output equals the limit.

    Defaults: a crossover near 300 rad/s for the default 1e-4 kg·m², stable at 100 µs steps."""

    kp: float = 0.03
    """N·m per rad/s."""
    ki: float = 2.0
    """N·m per rad."""
    integral: float = 0.0

    def update(self, error: float, limit: float, dt: float) -> tuple[float, bool]:
        """Torque for velocity ``error`` within ±``limit``, and whether it was clipped."""
        self.integral += self.ki * error * dt
        self.integral = max(-limit, min(limit, self.integral))
        out = self.kp * error + self.integral
        if abs(out) <= limit:
            return out, False
        clipped = limit if out > 0 else -limit
        self.integral = max(-limit, min(limit, clipped - self.kp * error))
        return clipped, True


@dataclass
class Limits:
    """What ``demand`` needs from the object dictionary, in SI units."""

    mode: int = 0
    target_velocity: float = 0.0
    target_torque: float = 0.0
    accel: float = 100.0
    decel: float = 100.0
    quick_stop_decel: float = 500.0
    max_torque: float = 1.5
    """The tighter of 0x6072 and 0x6073 (as kt·i), N·m."""
    max_speed: float = 10_000.0
    """0x6080, rad/s: no motoring torque past it (the drive model enforces it)."""
    quick_stop_option: int = 2
    fault_reaction_option: int = 2


@dataclass
class PowerStateMachine:
    """State, stopping reactions and the velocity loop. ``history`` holds ``(time_us, state)``."""

    state: str = NOT_READY
    changed_us: int = 0
    reference: float = 0.0
    """Velocity reference, rad/s (PV mode and stopping reactions)."""
    pi: VelocityPI = field(default_factory=VelocityPI)
    limited: bool = False
    """The last demand was clipped (statusword bit 11)."""
    stopping_since_us: int | None = None
    stopped: bool = False
    """The current quick stop has reached standstill (option codes 5 and 6 stay there)."""
    stopped_at_us: int | None = None
    quick_stops: int = 0
    history: list[tuple[int, str]] = field(default_factory=list)
    last_controlword: int = 0

    def go(self, state: str, now_us: int) -> None:
        if state != self.state:
            self.state, self.changed_us = state, now_us
            self.history.append((now_us, state))
            del self.history[:-50]

    def start(self, now_us: int) -> None:
        """Transition 1: NOT READY TO SWITCH ON → SWITCH ON DISABLED once initialised."""
        if self.state == NOT_READY:
            self.go(SWITCH_ON_DISABLED, now_us)

    def controlword(self, cw: int, omega: float, lim: Limits, now_us: int) -> None:
        """Apply a controlword written at ``now_us`` (``omega``: actual velocity, rad/s)."""
        rising_reset = bool(cw & CW_FAULT_RESET and not self.last_controlword & CW_FAULT_RESET)
        self.last_controlword = cw
        s = self.state
        if s == FAULT:
            if rising_reset:
                self.go(SWITCH_ON_DISABLED, now_us)  # 15
            return
        if s in (NOT_READY, FAULT_REACTION):
            return
        low = cw & 0x0F
        if not cw & CW_ENABLE_VOLTAGE:  # disable voltage: 7, 9, 10, 12
            if s != SWITCH_ON_DISABLED:
                self.go(SWITCH_ON_DISABLED, now_us)
        elif not cw & CW_QUICK_STOP:  # quick stop: 7, 10, 11
            if s in (READY, SWITCHED_ON):
                self.go(SWITCH_ON_DISABLED, now_us)
            elif s == OPERATION_ENABLED:
                self.begin_stop(QUICK_STOP, omega, now_us)
        elif low & 0x7 == 0x6:  # shutdown: 2, 6, 8
            if s in (SWITCH_ON_DISABLED, SWITCHED_ON, OPERATION_ENABLED):
                self.go(READY, now_us)
        elif low == 0x7:  # switch on: 3; disable operation: 5
            if s in (READY, OPERATION_ENABLED):
                self.go(SWITCHED_ON, now_us)
        elif low == 0xF:  # enable operation: 4 (via 3 from READY), 16
            if s == READY:
                self.go(SWITCHED_ON, now_us)
            resumable = s == QUICK_STOP and lim.quick_stop_option in (5, 6)
            if self.state == SWITCHED_ON or resumable:
                self.enable(omega, now_us)

    def enable(self, omega: float, now_us: int) -> None:
        """Into OPERATION ENABLED: the reference starts at the actual velocity (bumpless)."""
        self.reference, self.pi.integral = omega, 0.0
        self.stopping_since_us = None
        self.go(OPERATION_ENABLED, now_us)

    def begin_stop(self, state: str, omega: float, now_us: int) -> None:
        """Enter QUICK STOP ACTIVE or FAULT REACTION ACTIVE: ramp from the actual velocity."""
        if self.state not in TORQUE_STATES:
            self.reference, self.pi.integral = 0.0, 0.0
        elif self.state == OPERATION_ENABLED:
            self.reference = omega
        if state == QUICK_STOP:
            self.quick_stops += 1
        self.stopping_since_us, self.stopped = now_us, False
        self.go(state, now_us)

    def fault(self, omega: float, now_us: int) -> None:
        """A fault: FAULT REACTION ACTIVE (then FAULT once stopped); none while already faulted."""
        if self.state not in (FAULT_REACTION, FAULT):
            self.begin_stop(FAULT_REACTION, omega, now_us)

    def demand(self, omega: float, lim: Limits, dt: float, now_us: int) -> float:
        """Torque demand (N·m) for the substep starting at ``now_us``; ends finished reactions."""
        self.limited = False
        s = self.state
        if s not in TORQUE_STATES:
            return 0.0
        if s == OPERATION_ENABLED:
            if lim.mode == CST:
                tau = lim.target_torque
                self.limited = abs(tau) > lim.max_torque
                self.reference = omega
                self.pi.integral = max(-lim.max_torque, min(lim.max_torque, tau))
                return max(-lim.max_torque, min(lim.max_torque, tau))
            if lim.mode != PV:
                self.reference, self.pi.integral = omega, 0.0
                return 0.0
            self.reference = ramp(self.reference, lim.target_velocity, lim.accel, lim.decel, dt)
            return self._track(omega, lim, dt)
        option = lim.quick_stop_option if s == QUICK_STOP else lim.fault_reaction_option
        if option == 0:  # coast: the reaction is over at once
            self._stopped(now_us, lim)
            return 0.0
        decel = lim.decel if option in (1, 5) else lim.quick_stop_decel
        self.reference = ramp(self.reference, 0.0, decel, decel, dt)
        tau = self._track(omega, lim, dt)
        elapsed = now_us - (self.stopping_since_us or now_us)
        if not self.stopped and (
            (self.reference == 0.0 and abs(omega) < STOPPED_RAD_S) or elapsed >= MAX_STOP_US
        ):
            self._stopped(now_us, lim)
            if self.state not in TORQUE_STATES:
                return 0.0
        return tau

    def _track(self, omega: float, lim: Limits, dt: float) -> float:
        tau, self.limited = self.pi.update(self.reference - omega, lim.max_torque, dt)
        return tau

    def _stopped(self, now_us: int, lim: Limits) -> None:
        self.stopped, self.stopped_at_us = True, now_us
        if self.state == FAULT_REACTION:
            self.go(FAULT, now_us)  # 14
        elif lim.quick_stop_option in (5, 6):
            self.reference = 0.0  # stay in QUICK STOP ACTIVE, holding zero velocity
        else:
            self.go(SWITCH_ON_DISABLED, now_us)  # 12

    def statusword(self, target_reached: bool) -> int:
        sw = STATUS_BITS[self.state] | SW_REMOTE
        if target_reached:
            sw |= SW_TARGET_REACHED
        if self.limited:
            sw |= SW_INTERNAL_LIMIT
        return sw
