"""MIT-mode motors (CubeMars AK, Damiao DM): their frames, a table of models, and the clamp that
keeps every command forwarded inside a torque cap. Sans-IO, exact (``Fraction``) arithmetic.

**Frames** (11-bit identifier = the motor's id, 8 data bytes, big-endian bit fields):

- command: position ``p`` 16 bits, velocity ``v`` 12, ``kp`` 12, ``kd`` 12, feed-forward torque
  ``t_ff`` 12; each an unsigned integer mapped linearly over its range, ``x = lo + n·(hi −
  lo)/(2^bits − 1)`` (how the firmwares decode it). The motor applies
  ``τ = kp·(p − θ) + kd·(v − ω) + t_ff`` until the next command;
- special frames: ``FF×7 FC`` enter motor mode, ``FF×7 FD`` exit motor mode (power stage off),
  ``FF×7 FE`` set the current position to zero (Damiao also ``FB``: clear error);
- reply, one per frame received: ``data[0]`` the motor's id (Damiao: id in the low nibble, state
  in the high one), then position 16 bits, velocity 12, torque 12 over the same ranges (CubeMars
  manual V1.0.8 §5.3; Damiao's reply has MOSFET and rotor temperatures in bytes 6-7).

**The clamp.** Over the time ``horizon`` a command may stay in force (until the guard sends the
next one, re-clamped from a newer reply, or the stop), the motor's position moves at most
``Ω·horizon`` from the last reply's (older by ``age``) and its speed is at most ``Ω`` (the
model's velocity range, which covers the no-load speed at the rated supply). So the torque the
command can ask for is at most::

    W = kp·(|p − θ₀| + Ω·(age + horizon)) + kd·(|v| + Ω) + |t_ff|

A command with ``W`` above the cap ``T`` is clamped: ``v`` to the velocity cap, then ``kp``,
``kd`` and ``t_ff`` scaled by the same factor and rounded toward zero on the wire, so that the
decoded command's ``W`` is at most ``T``. ``t_ff`` cannot be 0 on the wire (12 bits over a range
symmetric about 0): a cap below its smallest step refuses the command. The power the cap allows
(the envelope): ``T·Ω + 3/2·R·(T/k_t)²``, mechanical power plus the q-axis copper losses
(``k_t`` per peak phase ampere at the output, as the MIT firmwares define it).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction

from canergy.devices.profile import Envelope

FW_PER_W = 10**15
UNM_PER_NM = 10**6
ENTER = bytes([0xFF] * 7 + [0xFC])
EXIT = bytes([0xFF] * 7 + [0xFD])
ZERO = bytes([0xFF] * 7 + [0xFE])
CLEAR_ERROR = bytes([0xFF] * 7 + [0xFB])
SPECIAL = {ENTER: "enter", EXIT: "exit", ZERO: "zero", CLEAR_ERROR: "clear"}


@dataclass(frozen=True, slots=True)
class Field:
    """A value coded as an unsigned ``bits``-bit integer over ``[-span, span]`` (or ``[0,
    span]`` for gains)."""

    span: Fraction
    bits: int
    signed: bool = True

    @property
    def top(self) -> int:
        return (1 << self.bits) - 1

    @property
    def lo(self) -> Fraction:
        return -self.span if self.signed else Fraction(0)

    def value(self, n: int) -> Fraction:
        """``lo + n·width/top``, built as one fraction (this is on every command's path)."""
        a, b = self.span.numerator, self.span.denominator
        top = (1 << self.bits) - 1
        if self.signed:  # -a/b + n·2a/(b·top)
            return Fraction(a * (2 * n - top), b * top)
        return Fraction(a * n, b * top)

    def code_toward_zero(self, x: Fraction) -> int:
        """The code whose value is nearest ``x`` without exceeding ``|x|`` in magnitude on the
        same side of 0 (or the smallest magnitude on that side, if none)."""
        width = 2 * self.span if self.signed else self.span
        exact = (x - self.lo) * self.top / width
        n = math.floor(exact) if x >= 0 else math.ceil(exact)
        n = min(max(n, 0), self.top)
        if self.signed and x >= 0 and self.value(n) < 0:
            n += 1  # the smallest positive step (0 is not on the wire)
        if self.signed and x < 0 and self.value(n) > 0:
            n -= 1
        return n


@dataclass(frozen=True, slots=True)
class MitModel:
    """A motor's coding ranges and the figures its envelope needs (SI, at the output)."""

    name: str
    p_max: Fraction
    """rad (position range ±p_max)."""
    v_max: Fraction
    """rad/s (velocity range; also Ω, the fastest the output turns at the rated supply)."""
    t_max: Fraction
    """N·m (torque range; the rated peak torque)."""
    torque_constant: Fraction
    """N·m per peak phase A at the output (the smallest credible figure: more current per
    N·m, more copper losses)."""
    resistance: Fraction | None
    """Phase resistance, Ω (None: no published figure; give it on the command line)."""
    kp_max: Fraction = Fraction(500)
    kd_max: Fraction = Fraction(5)
    damiao: bool = False
    """Reply's first byte: id in the low nibble, state in the high one."""

    def fields(self) -> tuple[Field, Field, Field, Field, Field]:
        return _fields(self)


@functools.cache
def _fields(model: MitModel) -> tuple[Field, Field, Field, Field, Field]:
    return (
        Field(model.p_max, 16),
        Field(model.v_max, 12),
        Field(model.kp_max, 12, signed=False),
        Field(model.kd_max, 12, signed=False),
        Field(model.t_max, 12),
    )


MODELS: dict[str, MitModel] = {
    # CubeMars AK Series Driver Manual V1.0.8, §5.3 (ranges: P ±12.5 rad, V ±50 rad/s, T ±18
    # N·m; kp 0-500, kd 0-5); torque constant 0.091 N·m/A at the motor × gear 9 (CubeMars's
    # figure, as listed by TMotorCANControl's MIT_Params; they measured 0.115, larger: the
    # smaller one is kept). CubeMars publishes no phase resistance found here.
    "AK80-9": MitModel(
        "AK80-9", Fraction(25, 2), Fraction(50), Fraction(18), Fraction(819, 1000), None
    ),
    # same manual: V ±50 rad/s, T ±25 N·m; 0.095 N·m/A × gear 10 (measured 0.122).
    "AK70-10": MitModel(
        "AK70-10", Fraction(25, 2), Fraction(50), Fraction(25), Fraction(95, 100), None
    ),
    # Damiao DM-J4310-2EC V1.1 (its specification table, as Seeed's wiki lists it): default
    # PMAX 12.5 rad, VMAX 30 rad/s, TMAX 10 N·m; torque constant 0.945 N·m/A at the output,
    # phase resistance 0.85 Ω; no-load speed 200 rpm (21 rad/s) at 24 V.
    "DM4310": MitModel(
        "DM4310", Fraction(25, 2), Fraction(30), Fraction(10), Fraction(945, 1000),
        Fraction(85, 100), damiao=True,
    ),
}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Command:
    """A command as the wire codes it (the five unsigned integers)."""

    p: int
    v: int
    kp: int
    kd: int
    t: int

    def pack(self) -> bytes:
        return bytes(
            (
                self.p >> 8,
                self.p & 0xFF,
                self.v >> 4,
                (self.v & 0xF) << 4 | self.kp >> 8,
                self.kp & 0xFF,
                self.kd >> 4,
                (self.kd & 0xF) << 4 | self.t >> 8,
                self.t & 0xFF,
            )
        )

    @classmethod
    def unpack(cls, data: bytes | bytearray) -> Command:
        """``ValueError`` if not 8 bytes or a special frame."""
        d = bytes(data)
        if len(d) != 8:
            raise ValueError(f"MIT command of {len(d)} bytes, 8 expected")
        if d in SPECIAL:
            raise ValueError(f"a special frame ({SPECIAL[d]}), not a command")
        return cls(
            d[0] << 8 | d[1],
            d[2] << 4 | d[3] >> 4,
            (d[3] & 0xF) << 8 | d[4],
            d[5] << 4 | d[6] >> 4,
            (d[6] & 0xF) << 8 | d[7],
        )


@dataclass(frozen=True, slots=True)
class Values:
    """A command decoded (SI, exact)."""

    p: Fraction
    v: Fraction
    kp: Fraction
    kd: Fraction
    t: Fraction


def decode(model: MitModel, cmd: Command) -> Values:
    fp, fv, fkp, fkd, ft = model.fields()
    return Values(
        fp.value(cmd.p), fv.value(cmd.v), fkp.value(cmd.kp), fkd.value(cmd.kd), ft.value(cmd.t)
    )


def encode(model: MitModel, p: float, v: float, kp: float, kd: float, t: float) -> Command:
    """A command from SI values (nearest codes, saturated): for applications and tests."""
    out = []
    for f, x in zip(model.fields(), (p, v, kp, kd, t), strict=True):
        width = 2 * f.span if f.signed else f.span
        n = round((Fraction(x) - f.lo) * f.top / width)
        out.append(min(max(n, 0), f.top))
    return Command(*out)


@dataclass(frozen=True, slots=True)
class Reply:
    node: int
    p: Fraction
    v: Fraction
    torque: Fraction
    state: int | None = None
    """Damiao: the high nibble of byte 0 (0 disabled, 1 enabled, others faults)."""


def pack_reply(model: MitModel, node: int, p: int, v: int, t: int, state: int = 0) -> bytes:
    first = (state & 0xF) << 4 | node & 0xF if model.damiao else node & 0xFF
    return bytes((first, p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF, 0, 0))


def default_master(model: MitModel, motor_id: int) -> int:
    """The replies' identifier unless the motor is configured otherwise: 0 for CubeMars,
    ``motor_id + 0x10`` for Damiao."""
    return motor_id + 0x10 if model.damiao else 0


def reply_collision(replies: dict[int, int]) -> str | None:
    """Why motors whose replies go out on ``replies[motor id]`` cannot share a bus (None: they
    can): a motor's replies on another's (or its own) command identifier would reach that motor
    as a command no gate clamped."""
    for motor_id, reply in sorted(replies.items()):
        if reply in replies:
            whose = "its own" if reply == motor_id else f"motor {reply}'s"
            return (
                f"MIT motor {motor_id}'s replies go out on 0x{reply:03X}, {whose} command "
                "identifier: it would take them as commands no gate clamped (give the motors "
                "ids whose replies land on no motor's id)"
            )
    return None


def unpack_reply(model: MitModel, data: bytes | bytearray) -> Reply:
    """``ValueError`` if shorter than 6 bytes."""
    d = bytes(data)
    if len(d) < 6:
        raise ValueError(f"MIT reply of {len(d)} bytes, at least 6 expected")
    fp, fv, _, _, ft = model.fields()
    node, state = (d[0] & 0xF, d[0] >> 4) if model.damiao else (d[0], None)
    v = d[3] << 4 | d[4] >> 4
    t = (d[4] & 0xF) << 8 | d[5]
    return Reply(node, fp.value(d[1] << 8 | d[2]), fv.value(v), ft.value(t), state)


def side_channel(model: MitModel, motor_id: int, arbitration_id: int, extended: bool) -> str | None:
    """Why a frame to ``arbitration_id`` reaches motor ``motor_id`` outside MIT mode, whose
    effect the clamp cannot bound (None: it does not). Damiao: position-velocity ``0x100 + id``,
    velocity ``0x200 + id``, force-position ``0x300 + id``, and the parameter frame ``0x7FF``
    (control mode, limits; whichever motor it names); CubeMars: servo-mode extended frames
    ``mode << 8 | id`` (modes 0-7: duty, current, brake, velocity, position, origin, ...)."""
    if model.damiao and not extended:
        if arbitration_id in (0x100 + motor_id, 0x200 + motor_id, 0x300 + motor_id):
            return f"Damiao mode frame 0x{arbitration_id:03X} (not MIT)"
        if arbitration_id == 0x7FF:
            return "Damiao parameter frame 0x7FF"
    servo = extended and arbitration_id & 0xFF == motor_id and arbitration_id >> 8 <= 7
    if not model.damiao and servo:
        return f"CubeMars servo-mode frame 0x{arbitration_id:X} (not MIT)"
    return None


PARAMETER_ID = 0x7FF
"""Damiao's parameter frames: ``[id low, id high, op, RID, value (4 bytes, little-endian)]``,
op 0x33 read, 0x55 write, 0xAA save to flash; answered from the motor's master id with the
same layout (Damiao's register table, as the open Damiao drivers list it)."""
READ_REGISTER = 0x33
TIMEOUT_RID = 9
"""``TIMEOUT``, the CAN Timeout: uint32 in units of 50 µs (0: off); a motor that receives no
frame for that long disables itself."""
TIMEOUT_UNIT_US = 50


def read_register(motor_id: int, rid: int) -> bytes:
    """The 0x7FF frame that asks Damiao motor ``motor_id`` for register ``rid``."""
    return bytes([motor_id & 0xFF, motor_id >> 8 & 0x07, READ_REGISTER, rid, 0, 0, 0, 0])


def register_reply(motor_id: int, rid: int, data: bytes | bytearray) -> int | None:
    """The value of register ``rid`` if ``data`` is motor ``motor_id``'s answer to its read
    (None: it is not; an MIT reply of the same motor may look like one only with byte 1, its
    position's high byte, equal to the id's high byte and bytes 2-3 equal to 0x33, ``rid``)."""
    d = bytes(data)
    head = bytes([motor_id & 0xFF, motor_id >> 8 & 0x07, READ_REGISTER, rid])
    if len(d) != 8 or d[:4] != head:
        return None
    return int.from_bytes(d[4:8], "little")


# -- the envelope and the clamp -------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class MitLimits:
    """What the guard lets through: a torque cap (µN·m) and a velocity cap (µrad/s)."""

    torque_unm: int
    velocity_urad_s: int

    def describe(self) -> str:
        t, v = self.torque_unm / 1e6, self.velocity_urad_s / 1e6
        return f"torque cap {t:g} N·m, velocity cap {v:g} rad/s"


def power(model: MitModel, torque: Fraction, resistance: Fraction) -> Fraction:
    """W at torque ``torque`` (N·m) and full speed: ``T·Ω + 3/2·R·(T/k_t)²``."""
    i = torque / model.torque_constant
    return torque * model.v_max + Fraction(3, 2) * resistance * i * i


def cap_for_power(model: MitModel, fw: int, resistance: Fraction) -> int:
    """The largest torque cap (µN·m) whose envelope is at most ``fw``."""
    target = Fraction(fw, FW_PER_W)
    a = Fraction(3, 2) * resistance / model.torque_constant**2
    b = model.v_max
    if a == 0:
        t = target / b
    else:  # (-b + sqrt(b² + 4·a·P)) / (2a), rounded down at 1 µN·m, then checked
        disc = b * b + 4 * a * target
        root = Fraction(math.isqrt(math.floor(disc * 10**24)), 10**12)
        t = (root - b) / (2 * a)
    unm = max(0, math.floor(t * UNM_PER_NM))
    while unm > 0 and power(model, Fraction(unm, UNM_PER_NM), resistance) > target:
        unm -= 1
    return min(unm, math.floor(model.t_max * UNM_PER_NM))


def worst_torque(
    model: MitModel, v: Values, theta: Fraction, age_us: int, horizon_us: int
) -> Fraction:
    """The most torque ``v`` can ask for over ``horizon_us`` (module doc), from a position
    ``theta`` read ``age_us`` ago."""
    drift = model.v_max * Fraction(age_us + horizon_us, 10**6)
    return v.kp * (abs(v.p - theta) + drift) + v.kd * (abs(v.v) + model.v_max) + abs(v.t)


@dataclass(frozen=True, slots=True)
class Clamped:
    command: Command | None
    """What to send (None: refused)."""
    clamped: bool
    worst: Fraction
    """The sent command's worst-case torque (N·m)."""
    why: str | None = None


def clamp(
    model: MitModel,
    cmd: Command,
    limits: MitLimits,
    theta: Fraction,
    age_us: int,
    horizon_us: int,
) -> Clamped:
    """``cmd`` as it may go to the motor under ``limits`` (module doc)."""
    _, fv, fkp, fkd, ft = model.fields()
    cap = Fraction(limits.torque_unm, UNM_PER_NM)
    vals = decode(model, cmd)
    out = cmd
    vcap = Fraction(limits.velocity_urad_s, UNM_PER_NM)
    if abs(vals.v) > vcap:
        out = Command(
            cmd.p, fv.code_toward_zero(vcap if vals.v > 0 else -vcap), cmd.kp, cmd.kd, cmd.t
        )
        if abs(fv.value(out.v)) > vcap:
            return Clamped(None, True, Fraction(0), "velocity cap below the smallest step")
    vals = decode(model, out)
    worst = worst_torque(model, vals, theta, age_us, horizon_us)
    if worst <= cap:
        return Clamped(out, out != cmd, worst)
    scale = cap / worst
    t = ft.code_toward_zero(vals.t * scale)  # may be one step above: 0 is not on the wire
    room = cap - abs(ft.value(t))
    gains = worst - abs(vals.t)
    if room < 0:
        return Clamped(None, True, worst, f"torque cap {float(cap):g} N·m below the smallest step")
    share = min(Fraction(1), room / gains) if gains > 0 else Fraction(0)
    out = Command(
        out.p,
        out.v,
        fkp.code_toward_zero(vals.kp * share),
        fkd.code_toward_zero(vals.kd * share),
        t,
    )
    worst = worst_torque(model, decode(model, out), theta, age_us, horizon_us)
    assert worst <= cap, (worst, cap)  # each gain rounded down, t_ff within room
    return Clamped(out, True, worst)


class MitProfile:
    """``canergy.devices.profile.Profile`` for an MIT-mode motor guarded in line."""

    name = "mit"

    def __init__(self, model: MitModel, resistance: Fraction | None = None) -> None:
        r = resistance if resistance is not None else model.resistance
        if r is None:
            raise ValueError(f"{model.name}: no phase resistance in the table; give it")
        self.model = model
        self.resistance = r

    def observe(self, measured: dict[str, float]) -> None:
        return None

    def envelope(self, limits: MitLimits) -> Envelope:
        t = Fraction(limits.torque_unm, UNM_PER_NM)
        w = power(self.model, t, self.resistance)
        parts = {
            "torque_cap_nm": float(t),
            "omega_max_rad_s": float(self.model.v_max),
            "torque_constant_nm_per_a": float(self.model.torque_constant),
            "resistance_ohm": float(self.resistance),
        }
        fw = math.ceil(w * FW_PER_W)
        return Envelope(fw, "T_cap·Ω + 3/2·R·(T_cap/kt)²", parts)

    def closed(self, limits: MitLimits) -> MitLimits:
        return MitLimits(0, 0)

    def mismatch(self, wrote: MitLimits, read: MitLimits) -> str | None:
        return None if wrote == read else f"{read.describe()}, written {wrote.describe()}"

    def stop_fw_us(self, limits: MitLimits, stop_us: int) -> int:
        return 0  # exit motor mode turns the power stage off: the motor coasts

    def fields(self, limits: MitLimits) -> dict[str, float]:
        return {
            "torque_nm": limits.torque_unm / 1e6,
            "velocity_rad_s": limits.velocity_urad_s / 1e6,
        }
