"""The ODrive profile: CAN Simple frames (firmware 0.5 and 0.6) and the envelope of Set_Limits.

CAN Simple: 11-bit identifier ``node << 5 | command`` (node 0-63), data little-endian. The guard
uses Set_Limits (0x00F: velocity limit rev/s, current limit A, two float32), Estop (0x002),
Set_Axis_State (0x007: 1 = IDLE), and reads the heartbeat (0x001: axis error, axis state), the
encoder estimates (0x009), bus voltage and current (0x017) and, on 0.6, the powers (0x01D) and
endpoint reads (RxSdo 0x004 opcode 0, answered by TxSdo 0x005): on 0.6 ``vel_limit`` and
``current_soft_max`` are read back through their endpoint ids (from the firmware's
``flat_endpoints.json``); 0.5 has no way to read a limit back over CAN.

The envelope of limits ``(v_lim, i_lim)`` (docs/guide/drives.md, "ODrive axes")::

    P = min(k_t·i_lim·ω_max + 3/2·R·i_lim², V_bus·i_lim),   ω_max = 2π·tol·v_lim

``k_t`` the motor's torque constant (N·m/A, ODrive's 8.27/KV), ``R`` its phase resistance,
``tol`` the firmware's ``vel_limit_tolerance`` (1.2 by default: it faults only past tol·v_lim),
``V_bus`` the highest bus voltage given or measured. The first term is mechanical power plus the
copper losses of the q-axis current in ODrive's amplitude-invariant frame; the second holds
because phase power is 3/2·|v|·|i| with |v| at most V_bus/√3.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from fractions import Fraction

from canergy.devices.profile import Envelope, Foreign, LimitsWritten, Unbounded

FW_PER_W = 10**15
TWO_PI_UP = Fraction(710, 113)
"""2π rounded up (6.28318584 > 6.28318531): the envelope never comes out below the true one."""
NODE_MAX = 0x3F


class Cmd(IntEnum):
    """CAN Simple command ids (the low 5 bits of the identifier)."""

    HEARTBEAT = 0x001
    ESTOP = 0x002
    RX_SDO = 0x004
    TX_SDO = 0x005
    SET_AXIS_STATE = 0x007
    ENCODER_ESTIMATES = 0x009
    SET_CONTROLLER_MODE = 0x00B
    SET_INPUT_POS = 0x00C
    SET_INPUT_VEL = 0x00D
    SET_INPUT_TORQUE = 0x00E
    SET_LIMITS = 0x00F
    GET_IQ = 0x014
    BUS_VOLTAGE_CURRENT = 0x017
    CLEAR_ERRORS = 0x018
    POWERS = 0x01D
    """0.6 only (0.5 uses 0x01D for Get_Controller_Error)."""


class AxisState(IntEnum):
    UNDEFINED = 0
    IDLE = 1
    CLOSED_LOOP_CONTROL = 8


SDO_READ, SDO_WRITE = 0, 1
FIRMWARES = ("0.5", "0.6")


UNBOUNDED = {
    Cmd.RX_SDO: "RxSdo write",
    0x006: "Set_Axis_Node_ID/Address",
    0x016: "Reboot",
    0x01F: "Enter_DFU_Mode",
}
"""Frames from others whose effect on the limits the guard cannot bound."""


def can_id(node: int, cmd: int) -> int:
    return (node & NODE_MAX) << 5 | (cmd & 0x1F)


def split_id(arbitration_id: int) -> tuple[int, int]:
    """``(node, command)`` of an 11-bit CAN Simple identifier."""
    return arbitration_id >> 5 & NODE_MAX, arbitration_id & 0x1F


def f32(value: float) -> float:
    """``value`` as the float32 on the wire."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def two_floats(data: bytes | bytearray) -> tuple[float, float]:
    """Two little-endian float32 (``ValueError`` if not 8 bytes)."""
    if len(data) != 8:
        raise ValueError(f"{len(data)} bytes, 8 expected")
    a, b = struct.unpack("<ff", bytes(data))
    return float(a), float(b)


def set_limits(velocity: float, current: float) -> bytes:
    return struct.pack("<ff", velocity, current)


def set_axis_state(state: int) -> bytes:
    """Set_Axis_State's data: the state in 4 bytes, padded to the DBC's 8 (decoders that check
    the length against the DBC, as cantools does, refuse 4)."""
    return struct.pack("<I4x", state)


def heartbeat(data: bytes | bytearray) -> tuple[int, int]:
    """``(axis_error, axis_state)`` of a heartbeat (0.5 and 0.6 agree on these two)."""
    if len(data) < 5:
        raise ValueError(f"heartbeat of {len(data)} bytes")
    error, state = struct.unpack_from("<IB", bytes(data))
    return int(error), int(state)


def sdo_read(endpoint: int) -> bytes:
    """RxSdo: read ``endpoint`` (0.6)."""
    return struct.pack("<BHBI", SDO_READ, endpoint, 0, 0)


def sdo_fields(data: bytes | bytearray) -> tuple[int, int, bytes]:
    """``(opcode or reserved byte, endpoint id, value bytes)`` of RxSdo or TxSdo."""
    if len(data) != 8:
        raise ValueError(f"SDO frame of {len(data)} bytes")
    first, endpoint, _ = struct.unpack_from("<BHB", bytes(data))
    return int(first), int(endpoint), bytes(data[4:8])


@dataclass(frozen=True, slots=True)
class OdriveLimits:
    """What Set_Limits writes: ``controller.config.vel_limit`` and the current limit (0.5
    ``motor.config.current_lim``, 0.6 ``config.motor.current_soft_max``), as float32."""

    velocity: float
    """rev/s."""
    current: float
    """A."""

    def wire(self) -> OdriveLimits:
        """The same limits as the device holds them (float32)."""
        return OdriveLimits(f32(self.velocity), f32(self.current))

    def describe(self) -> str:
        return f"velocity limit {self.velocity:g} rev/s, current limit {self.current:g} A"


@dataclass(frozen=True, slots=True)
class MotorConstants:
    """What turns an ODrive's limits into watts (given on the command line)."""

    torque_constant: Fraction
    """N·m/A (ODrive: 8.27 / KV)."""
    resistance: Fraction = Fraction(0)
    """Phase resistance, Ω (hot)."""
    vel_tolerance: Fraction = Fraction(6, 5)
    """The firmware's ``vel_limit_tolerance``: speed reaches tol × vel_limit before it faults."""
    bus_voltage: Fraction = Fraction(0)
    """The supply's highest voltage, V (0: the V_bus term is left out until one is measured)."""


def ceil_fraction(x: Fraction) -> int:
    return -(-x.numerator // x.denominator)


def watch(cmd: int, data: bytes) -> Foreign[OdriveLimits]:
    """A frame someone else sent the axis (not a remote request): Set_Limits carries its
    values; RxSdo writes, Reboot, Set_Axis_Node_ID and Enter_DFU_Mode are not bounded
    (``ValueError``: a Set_Limits or RxSdo frame not 8 bytes long)."""
    if cmd == Cmd.SET_LIMITS:
        return LimitsWritten(OdriveLimits(*two_floats(data)))
    if cmd in UNBOUNDED and not (cmd == Cmd.RX_SDO and sdo_fields(data)[0] != SDO_WRITE):
        return Unbounded(f"{UNBOUNDED[cmd]} ({data.hex() or 'no data'})")
    return None


class OdriveProfile:
    """``canergy.devices.profile.Profile`` for an ODrive axis."""

    name = "odrive"
    watch = staticmethod(watch)

    def __init__(self, motor: MotorConstants) -> None:
        self.motor = motor
        self.bus_voltage = motor.bus_voltage
        """Raised to the highest voltage measured (0x017), never lowered."""

    def observe(self, measured: dict[str, float]) -> None:
        volts = measured.get("bus_voltage_v")
        if volts is not None and math.isfinite(volts) and volts > 0:
            self.bus_voltage = max(self.bus_voltage, Fraction(volts))

    def envelope(self, limits: OdriveLimits) -> Envelope:
        m = self.motor
        i = Fraction(abs(limits.current)) if math.isfinite(limits.current) else None
        v = Fraction(abs(limits.velocity)) if math.isfinite(limits.velocity) else None
        omega = None if v is None else TWO_PI_UP * m.vel_tolerance * v
        motor_w = None
        if i is not None and omega is not None:
            motor_w = m.torque_constant * i * omega + Fraction(3, 2) * m.resistance * i * i
        supply_w = self.bus_voltage * i if i is not None and self.bus_voltage > 0 else None
        watts = [w for w in (motor_w, supply_w) if w is not None]
        fw = ceil_fraction(min(watts) * FW_PER_W) if watts else 2**62
        parts = {
            "torque_constant_nm_per_a": float(m.torque_constant),
            "resistance_ohm": float(m.resistance),
            "vel_tolerance": float(m.vel_tolerance),
            "current_limit_a": float(limits.current),
            "omega_max_rad_s": -1.0 if omega is None else float(omega),
            "bus_voltage_v": float(self.bus_voltage),
            "motor_term_w": -1.0 if motor_w is None else float(motor_w),
            "supply_term_w": -1.0 if supply_w is None else float(supply_w),
        }
        formula = "min(kt·i_lim·2π·tol·v_lim + 3/2·R·i_lim², V_bus·i_lim)"
        return Envelope(fw, formula, parts)

    def closed(self, limits: OdriveLimits) -> OdriveLimits:
        return OdriveLimits(limits.velocity, 0.0)

    def mismatch(self, wrote: OdriveLimits, read: OdriveLimits) -> str | None:
        w = wrote.wire()
        if read.velocity != w.velocity:
            return f"velocity limit reads {read.velocity:g} rev/s, written {w.velocity:g}"
        if read.current != w.current:
            return f"current limit reads {read.current:g} A, written {w.current:g}"
        return None

    def stop_fw_us(self, limits: OdriveLimits, stop_us: int) -> int:
        return 0  # Estop and IDLE turn the power stage off: the motor coasts, draws nothing

    def fields(self, limits: OdriveLimits) -> dict[str, float]:
        return {"velocity_rev_s": limits.velocity, "current_a": limits.current}
