"""The moteus profile (mjbots): its CAN-FD register protocol, sans-IO, and the envelope of the
limits the guard writes to its configuration.

**Identifier**: ``prefix << 16 | source << 8 | destination`` (7-bit ids; bit 15 set asks the
controller to reply); a frame whose identifier exceeds 0x7FF is sent extended. A controller's
reply comes from ``id << 8 | asker``.

**Subframes** (one frame holds several; unused bytes are NOP 0x50): write, read and reply of N
registers of one type (int8, int16, int32, float32: type byte ``base | kind << 2 | N``, N in the
two low bits or, when they are 0, a varuint after it; then the first register as a varuint), write
and read errors (0x30, 0x31: register, error), the tunnelled diagnostic stream (0x40 client data,
0x41 server data: channel, length, bytes; 0x42 poll: channel, most bytes wanted). Integers are
scaled per register kind (``SCALES``); the most negative integer stands for "unset" (NaN).

**Limits**: the ones the host can hold across the application's commands are configuration
values, set and read back as text on diagnostic channel 1 (``conf set NAME VALUE`` answered
``OK``, ``conf get NAME`` answered with the value): ``servo.max_power_W``, ``servo.max_current_A``,
``servo.max_velocity`` and the watchdog ``servo.default_timeout_s``. The per-command registers
(0x025 maximum torque, 0x027 watchdog, 0x028 velocity limit) are reset by every command that
writes the mode (register 0x000), so the application's next command replaces them: the guard does
not use them. The envelope (docs/guide/drives.md, "moteus")::

    P = min(P_max, k_t·i_max·ω_max + 3/2·R·i_max², V_bus·i_max),  ω_max = 2π·(v_max + v_derate)

``P_max`` the power limit (the firmware's own limit on the electrical power into the motor),
``i_max`` the phase current limit, ``v_max`` the velocity limit past which the firmware derates
power to nothing at ``v_max + v_derate`` (``servo.max_velocity_derate``, given), ``k_t``, ``R`` the
motor's (given), ``V_bus`` the highest supply voltage given or measured (register 0x00d). The stop
is mode 0 (stopped: the power stage is off).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, replace
from enum import IntEnum
from fractions import Fraction

from canergy.devices.odrive import FW_PER_W, TWO_PI_UP, ceil_fraction, f32
from canergy.devices.profile import Envelope, Foreign, LimitsWritten, Unbounded

ID_MAX = 0x7F
BROADCAST = 0x7F
"""The multiplex protocol's broadcast id: a frame to it is taken as addressed to every
controller."""
PREFIX_MAX = 0x1FFF
REPLY = 0x8000
DIAGNOSTIC_CHANNEL = 1
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
NOP = 0x50
READ_BACK_TOLERANCE = 1e-5
"""``conf get`` answers in text: a value read back within this (relative, or absolute below 1)
of the one written is the one written (six significant digits)."""


class Reg(IntEnum):
    MODE = 0x000
    POSITION = 0x001
    VELOCITY = 0x002
    TORQUE = 0x003
    Q_CURRENT = 0x004
    D_CURRENT = 0x005
    POWER = 0x007
    VOLTAGE = 0x00D
    TEMPERATURE = 0x00E
    FAULT = 0x00F
    COMMAND_POSITION = 0x020
    COMMAND_VELOCITY = 0x021
    FEEDFORWARD_TORQUE = 0x022
    KP_SCALE = 0x023
    KD_SCALE = 0x024
    MAX_TORQUE = 0x025
    WATCHDOG_TIMEOUT = 0x027
    VELOCITY_LIMIT = 0x028
    FIXED_VOLTAGE_OVERRIDE = 0x02A
    FIXED_CURRENT_OVERRIDE = 0x02C


class Mode(IntEnum):
    STOPPED = 0
    FAULT = 1
    PWM = 5
    VOLTAGE = 6
    VOLTAGE_FOC = 7
    VOLTAGE_DQ = 8
    CURRENT = 9
    POSITION = 10
    TIMEOUT = 11
    ZERO_VELOCITY = 12
    STAY_WITHIN = 13
    MEASURE_INDUCTANCE = 14
    BRAKE = 15


BOUNDED_MODES = frozenset(
    {Mode.STOPPED, Mode.CURRENT, Mode.POSITION, Mode.ZERO_VELOCITY, Mode.STAY_WITHIN, Mode.BRAKE}
)
"""Modes an application may write that the current and power limits hold in; the others
(PWM, voltage, voltage FOC, voltage DQ, inductance measurement, and any value not a mode) command
voltage or PWM directly, or mean nothing known."""
UNBOUNDED_REGISTERS = {
    Reg.FIXED_VOLTAGE_OVERRIDE: "fixed voltage override (0x02a)",
    Reg.FIXED_CURRENT_OVERRIDE: "fixed current override (0x02c)",
    0x071: "clock trim (0x071)",
    0x110: "multiplex id (0x110)",
}
"""Registers whose write bypasses the current limit (moteus: "fixed voltage mode")."""
UNPOWERED_MODES = frozenset({Mode.STOPPED, Mode.FAULT})


class Kind(IntEnum):
    INT8 = 0
    INT16 = 1
    INT32 = 2
    FLOAT = 3


_FORMATS = {Kind.INT8: "<b", Kind.INT16: "<h", Kind.INT32: "<i", Kind.FLOAT: "<f"}
_SIZES = {Kind.INT8: 1, Kind.INT16: 2, Kind.INT32: 4, Kind.FLOAT: 4}
_CURRENT = (1.0, 0.1, 0.001)
_TORQUE = (0.5, 0.01, 0.001)
_VOLTAGE = (0.5, 0.1, 0.001)
_POSITION = (0.01, 0.0001, 0.00001)
_VELOCITY = (0.1, 0.00025, 0.00001)
_TIME = (0.01, 0.001, 0.000001)
_SCALE = (1 / 127, 1 / 32767, 1 / 2147483647)
SCALES: dict[int, tuple[float, float, float]] = {
    Reg.POSITION: _POSITION,
    Reg.VELOCITY: _VELOCITY,
    Reg.TORQUE: _TORQUE,
    Reg.Q_CURRENT: _CURRENT,
    Reg.D_CURRENT: _CURRENT,
    Reg.POWER: (10.0, 0.05, 0.0001),
    Reg.VOLTAGE: _VOLTAGE,
    Reg.TEMPERATURE: (1.0, 0.1, 0.001),
    Reg.COMMAND_POSITION: _POSITION,
    Reg.COMMAND_VELOCITY: _VELOCITY,
    Reg.FEEDFORWARD_TORQUE: _TORQUE,
    Reg.KP_SCALE: _SCALE,
    Reg.KD_SCALE: _SCALE,
    Reg.MAX_TORQUE: _TORQUE,
    Reg.WATCHDOG_TIMEOUT: _TIME,
    Reg.VELOCITY_LIMIT: _VELOCITY,
    Reg.FIXED_VOLTAGE_OVERRIDE: _VOLTAGE,
    Reg.FIXED_CURRENT_OVERRIDE: _CURRENT,
}
"""Value of one integer LSB (int8, int16, int32) per register; others are plain integers."""


# -- identifiers ------------------------------------------------------------------------------
def can_id(source: int, destination: int, reply: bool = False, prefix: int = 0) -> int:
    return (
        (prefix & PREFIX_MAX) << 16
        | (REPLY if reply else 0)
        | (source & ID_MAX) << 8
        | (destination & ID_MAX)
    )


def split_id(arbitration_id: int) -> tuple[int, int, bool, int]:
    """``(source, destination, reply requested, prefix)``."""
    return (
        arbitration_id >> 8 & ID_MAX,
        arbitration_id & ID_MAX,
        bool(arbitration_id & REPLY),
        arbitration_id >> 16 & PREFIX_MAX,
    )


def extended(arbitration_id: int) -> bool:
    return arbitration_id > 0x7FF


def padded(data: bytes) -> bytes:
    """``data`` filled with NOPs to the next CAN FD length (``ValueError`` past 64 bytes)."""
    if len(data) > 64:
        raise ValueError(f"{len(data)} bytes: a CAN FD frame holds 64")
    size = next(n for n in FD_LENGTHS if n >= len(data))
    return data + bytes([NOP]) * (size - len(data))


# -- values -----------------------------------------------------------------------------------
def varuint(value: int) -> bytes:
    if not 0 <= value < 2**32:
        raise ValueError(f"varuint {value} out of range")
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def read_varuint(data: bytes, at: int) -> tuple[int, int]:
    """The varuint at ``at`` and the offset after it (``ValueError``: truncated or too long)."""
    value = 0
    for i in range(5):
        if at + i >= len(data):
            raise ValueError("truncated varuint")
        byte = data[at + i]
        value |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return value, at + i + 1
    raise ValueError("varuint longer than 5 bytes")


def to_wire(register: int, kind: Kind, value: float) -> bytes:
    """``value`` as register ``register`` holds it in ``kind`` (NaN: the "unset" integer)."""
    if kind is Kind.FLOAT:
        return struct.pack("<f", value)
    bits = 8 * _SIZES[kind]
    low, high = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    scale = SCALES.get(register, (1.0, 1.0, 1.0))[kind]
    raw = low if math.isnan(value) else max(low + 1, min(high, round(value / scale)))
    return struct.pack(_FORMATS[kind], raw)


def from_wire(register: int, kind: Kind, raw: bytes) -> float:
    (value,) = struct.unpack(_FORMATS[kind], raw)
    if kind is Kind.FLOAT:
        return float(value)
    if value == -(2 ** (8 * _SIZES[kind] - 1)):
        return math.nan
    return float(value) * SCALES.get(register, (1.0, 1.0, 1.0))[kind]


# -- subframes --------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Write:
    """Registers written (``values`` from ``start`` on, scaled)."""

    kind: Kind
    start: int
    values: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Read:
    kind: Kind
    start: int
    count: int


@dataclass(frozen=True, slots=True)
class Reply:
    kind: Kind
    start: int
    values: tuple[float, ...]

    def items(self) -> dict[int, float]:
        return {self.start + i: v for i, v in enumerate(self.values)}


@dataclass(frozen=True, slots=True)
class Error:
    read: bool
    register: int
    code: int


@dataclass(frozen=True, slots=True)
class Stream:
    """Diagnostic stream bytes: from a client (``server`` False, 0x40) or a controller (0x41)."""

    server: bool
    channel: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Poll:
    channel: int
    most: int


Subframe = Write | Read | Reply | Error | Stream | Poll


def encode(*subframes: Subframe) -> bytes:
    """One frame's data, NOP-padded to a CAN FD length."""
    out = bytearray()
    for s in subframes:
        if isinstance(s, Write | Reply | Read):
            base = {Write: 0x00, Read: 0x10, Reply: 0x20}[type(s)]
            count = s.count if isinstance(s, Read) else len(s.values)
            if count < 1:
                raise ValueError("no register")
            head = base | s.kind << 2 | (count if count <= 3 else 0)
            out.append(head)
            if count > 3:
                out += varuint(count)
            out += varuint(s.start)
            if not isinstance(s, Read):
                for i, v in enumerate(s.values):
                    out += to_wire(s.start + i, s.kind, v)
        elif isinstance(s, Error):
            out += bytes([0x31 if s.read else 0x30]) + varuint(s.register) + varuint(s.code)
        elif isinstance(s, Stream):
            out += bytes([0x41 if s.server else 0x40]) + varuint(s.channel)
            out += varuint(len(s.data)) + s.data
        else:
            out += bytes([0x42]) + varuint(s.channel) + varuint(s.most)
    return padded(bytes(out))


def decode(data: bytes) -> tuple[list[Subframe], str | None]:
    """The subframes of one frame, in order, up to the first that does not parse; with the
    reason it did not (None: all parsed). A controller acts on the ones before it."""
    out: list[Subframe] = []
    at = 0
    try:
        while at < len(data):
            head, at = data[at], at + 1
            if head == NOP:
                continue
            if head < 0x30:
                base, kind, count = head & 0xF0, Kind(head >> 2 & 3), head & 3
                if not count:
                    count, at = read_varuint(data, at)
                    if not 0 < count <= 64:
                        raise ValueError(f"{count} registers")
                start, at = read_varuint(data, at)
                if base == 0x10:
                    out.append(Read(kind, start, count))
                    continue
                size = _SIZES[kind]
                if at + size * count > len(data):
                    raise ValueError("values past the frame's end")
                values = tuple(
                    from_wire(start + i, kind, data[at + i * size : at + (i + 1) * size])
                    for i in range(count)
                )
                at += size * count
                out.append(Write(kind, start, values) if base == 0 else Reply(kind, start, values))
            elif head in (0x30, 0x31):
                register, at = read_varuint(data, at)
                code, at = read_varuint(data, at)
                out.append(Error(head == 0x31, register, code))
            elif head in (0x40, 0x41):
                channel, at = read_varuint(data, at)
                size, at = read_varuint(data, at)
                if at + size > len(data):
                    raise ValueError("stream data past the frame's end")
                out.append(Stream(head == 0x41, channel, bytes(data[at : at + size])))
                at += size
            elif head in (0x42, 0x44):  # 0x44: a poll with a packet number (flow control)
                channel, at = read_varuint(data, at)
                at += 1 if head == 0x44 else 0
                most, at = read_varuint(data, at)
                out.append(Poll(channel, most))
            elif head == 0x43:  # controller data with a packet number (flow control)
                channel, at = read_varuint(data, at)
                size, at = read_varuint(data, at + 1)
                if at + size > len(data):
                    raise ValueError("stream data past the frame's end")
                out.append(Stream(True, channel, bytes(data[at : at + size])))
                at += size
            else:
                raise ValueError(f"unknown subframe 0x{head:02x}")
    except ValueError as exc:
        return out, f"{exc} at byte {at}"
    return out, None


def write_mode(mode: int) -> bytes:
    return encode(Write(Kind.INT8, Reg.MODE, (float(mode),)))


FEEDBACK = (
    Read(Kind.FLOAT, Reg.MODE, 5),  # mode, position, velocity, torque, q current
    Read(Kind.FLOAT, Reg.POWER, 1),
    Read(Kind.FLOAT, Reg.VOLTAGE, 3),  # voltage, temperature, fault
)
"""What the guard's query asks for (with the reply bit set)."""


# -- configuration (diagnostic channel) -------------------------------------------------------
CONF = {
    "power_w": "servo.max_power_W",
    "current_a": "servo.max_current_A",
    "velocity": "servo.max_velocity",
    "timeout_s": "servo.default_timeout_s",
}
"""The limits' configuration names."""
UNBOUNDED_CONF = frozenset(
    {
        "servo.max_velocity_derate",
        "servo.override_board_max_power",
        "servo.fixed_voltage_mode",
        "servo.voltage_mode_control",
        "servo.timeout_mode",
        "id.id",
        "can.prefix",
    }
)
"""Configuration the envelope depends on that the guard does not write (as are ``motor.*`` and
``motor_position.*``: the torque constant and gearing)."""
UNBOUNDED_COMMANDS = ("conf load", "conf default", "d raw", "d pwm", "d cal", "d flash")


def whole(value: float) -> int | None:
    """``value`` as an integer, if it is one (a register read or written as a float may not)."""
    return int(value) if math.isfinite(value) and value == int(value) else None


def mode_name(mode: float) -> str:
    n = whole(mode)
    return Mode(n).name if n is not None and n in Mode.__members__.values() else f"mode {mode:g}"


def watch_register(register: int, value: float) -> Unbounded | None:
    """A register someone else wrote: a mode the limits do not hold in, or a register that
    bypasses them, is not bounded."""
    if register == Reg.MODE and whole(value) not in BOUNDED_MODES:
        return Unbounded(f"mode {value:g} ({mode_name(value)})")
    if register in UNBOUNDED_REGISTERS:
        return Unbounded(UNBOUNDED_REGISTERS[register])
    return None


def watch_line(line: str, held: MoteusLimits | None) -> list[Foreign[MoteusLimits]]:
    """A diagnostic line someone else sent: ``conf set`` of a limit sets ``held`` (what the
    controller holds as far as the bus shows) with its value; ``conf load``, ``conf default``,
    ``d raw``/``pwm``/``cal``/``flash`` and ``conf set`` of what the envelope rests on are not
    bounded."""
    words = line.split()
    out: list[Foreign[MoteusLimits]] = []
    if " ".join(words).startswith(UNBOUNDED_COMMANDS):
        out.append(Unbounded(f"'{line[:60]}'"))
    if words[:2] != ["conf", "set"] or len(words) < 4:
        return out  # with no value, nothing is set
    name = words[2]
    if name in CONF.values() and held is not None:
        try:
            value = float(words[3])
        except ValueError:  # a lenient parser may take its start as a number
            return [*out, Unbounded(f"'{line[:60]}'")]
        out.append(LimitsWritten(held.with_conf(name, value)))
    elif name in UNBOUNDED_CONF or name.startswith(("motor.", "motor_position.")):
        out.append(Unbounded(f"'{line[:60]}'"))
    return out


def conf_set(name: str, value: float) -> bytes:
    return f"conf set {name} {value:.9g}\n".encode()


def conf_get(name: str) -> bytes:
    return f"conf get {name}\n".encode()


def stream_lines(buffer: bytearray, data: bytes) -> list[str]:
    """Append ``data`` to ``buffer``; the complete lines taken out of it (``\\r`` dropped,
    undecodable bytes replaced)."""
    buffer += data
    lines = []
    while (end := buffer.find(b"\n")) >= 0:
        line = bytes(buffer[:end]).replace(b"\r", b"")
        del buffer[: end + 1]
        lines.append(line.decode("latin-1").strip())
    if len(buffer) > 4096:  # a line that never ends: what it says is lost
        del buffer[:]
    return lines


# -- limits and envelope ----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class MoteusLimits:
    """The configuration values the guard writes and reads back."""

    power_w: float
    """``servo.max_power_W``."""
    current_a: float
    """``servo.max_current_A`` (phase current; the torque limit is k_t times it)."""
    velocity: float
    """``servo.max_velocity``, rev/s at the output."""
    timeout_s: float
    """``servo.default_timeout_s``: the watchdog after the application's last command."""

    def wire(self) -> MoteusLimits:
        return MoteusLimits(*(f32(v) for v in self.values()))

    def values(self) -> tuple[float, float, float, float]:
        return (self.power_w, self.current_a, self.velocity, self.timeout_s)

    def items(self) -> list[tuple[str, str, float]]:
        """``(field, configuration name, value)`` in writing order."""
        return [(f, name, getattr(self, f)) for f, name in CONF.items()]

    def with_conf(self, name: str, value: float) -> MoteusLimits:
        """These limits with the configuration value ``name`` set to ``value``."""
        field = next(f for f, n in CONF.items() if n == name)
        return replace(self, **{field: value})


@dataclass(frozen=True, slots=True)
class MoteusMotor:
    torque_constant: Fraction
    """N·m/A at the output."""
    resistance: Fraction = Fraction(0)
    velocity_derate: Fraction = Fraction(2)
    """``servo.max_velocity_derate``, rev/s: power reaches 0 at max_velocity plus it."""
    bus_voltage: Fraction = Fraction(0)


def _fraction(value: float) -> Fraction | None:
    return Fraction(abs(value)) if math.isfinite(value) else None


class MoteusProfile:
    """``canergy.devices.profile.Profile`` for a moteus controller."""

    name = "moteus"
    watch_register = staticmethod(watch_register)
    watch_line = staticmethod(watch_line)

    def __init__(self, motor: MoteusMotor) -> None:
        self.motor = motor
        self.bus_voltage = motor.bus_voltage

    def observe(self, measured: dict[str, float]) -> None:
        volts = measured.get("bus_voltage_v")
        if volts is not None and math.isfinite(volts) and volts > 0:
            self.bus_voltage = max(self.bus_voltage, Fraction(volts))

    def envelope(self, limits: MoteusLimits) -> Envelope:
        m = self.motor
        p_max = _fraction(limits.power_w)
        i = _fraction(limits.current_a)
        v = _fraction(limits.velocity)
        omega = None if v is None else TWO_PI_UP * (v + m.velocity_derate)
        motor_w = None
        if i is not None and omega is not None:
            motor_w = m.torque_constant * i * omega + Fraction(3, 2) * m.resistance * i * i
        supply_w = self.bus_voltage * i if i is not None and self.bus_voltage > 0 else None
        watts = [w for w in (p_max, motor_w, supply_w) if w is not None]
        fw = ceil_fraction(min(watts) * FW_PER_W) if watts else 2**62
        parts = {
            "power_limit_w": float(limits.power_w),
            "current_limit_a": float(limits.current_a),
            "torque_constant_nm_per_a": float(m.torque_constant),
            "resistance_ohm": float(m.resistance),
            "velocity_derate_rev_s": float(m.velocity_derate),
            "omega_max_rad_s": -1.0 if omega is None else float(omega),
            "bus_voltage_v": float(self.bus_voltage),
            "motor_term_w": -1.0 if motor_w is None else float(motor_w),
            "supply_term_w": -1.0 if supply_w is None else float(supply_w),
            "watchdog_s": float(limits.timeout_s),
        }
        formula = "min(P_max, kt·i_max·2π·(v_max+v_derate) + 3/2·R·i_max², V_bus·i_max)"
        return Envelope(fw, formula, parts)

    def closed(self, limits: MoteusLimits) -> MoteusLimits:
        return replace(limits, power_w=0.0, current_a=0.0)

    def mismatch(self, wrote: MoteusLimits, read: MoteusLimits) -> str | None:
        w = wrote.wire()
        for (_, name, value), got in zip(w.items(), read.values(), strict=True):
            same = got == value or (math.isnan(got) and math.isnan(value))
            close = math.isfinite(got) and abs(got - value) <= READ_BACK_TOLERANCE * max(
                1.0, abs(value)
            )
            if not (same or close):
                return f"{name} reads {got:g}, written {value:g}"
        return None

    def stop_fw_us(self, limits: MoteusLimits, stop_us: int) -> int:
        return 0  # mode 0: the power stage is off, the motor coasts

    def fields(self, limits: MoteusLimits) -> dict[str, float]:
        return {
            "power_w": limits.power_w,
            "current_a": limits.current_a,
            "velocity_rev_s": limits.velocity,
            "timeout_s": limits.timeout_s,
        }
