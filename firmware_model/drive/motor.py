"""The drive's physics: a DC motor with inertia, viscous friction and a load, and its energy.

Pure (no CAN, no clock). SI units inside: A, N·m, rad, rad/s, s, J, W.

- torque ``τ = kt·i``; the inverter is ideal (a current source without voltage limit), so the
  electrical power drawn from the DC link is ``P = τ·ω + R·i²`` and the DC link current ``P/V_dc``;
- ``J·dω/dt = τ − b·ω − τ_load``.

``Motor.step(dt, current, t)`` holds the current and the load torque over the step and solves the
linear equation exactly (exponential), so the energy integrals are exact for that piecewise-constant
input, including a sign change of ``P`` inside the step. The accounts (``Energy``) keep whole µJ
as integers and the sub-µJ remainder as a float below 1 µJ, so nothing is rounded away however long
a run is: ``drawn_uj`` is ``floor`` of the exact figure (off by less than 1 µJ plus float error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from firmware_model.profile_csv import read_rows

__all__ = ["Account", "Energy", "LoadTorque", "Motor", "MotorParams"]


@dataclass(frozen=True)
class MotorParams:
    """Motor and supply constants (SI)."""

    kt: float = 0.1
    """Torque constant, N·m/A."""
    resistance: float = 1.0
    """Winding resistance, Ω."""
    inertia: float = 1e-4
    """Rotor and load inertia, kg·m²."""
    damping: float = 1e-4
    """Viscous friction, N·m·s/rad."""
    rated_current: float = 5.0
    """A; 0x6073 and 0x6078 are per mille of it."""
    dc_voltage: float = 24.0
    """DC link voltage, V (constant supply)."""

    @property
    def rated_torque(self) -> float:
        """N·m; 0x6071, 0x6072 and 0x6077 are per mille of it."""
        return self.kt * self.rated_current


@dataclass(frozen=True)
class LoadTorque:
    """Load torque in N·m: ``rows`` of ``(start_s, torque)``, each held until the next row (the
    last one for ever). With ``opposing`` it acts like friction: magnitude of the row, sign of ω
    (none at standstill); otherwise a positive torque brakes positive rotation."""

    rows: tuple[tuple[float, float], ...] = ((0.0, 0.0),)
    opposing: bool = False

    @classmethod
    def constant(cls, nm: float, opposing: bool = False) -> LoadTorque:
        return cls(((0.0, nm),), opposing)

    @classmethod
    def from_csv(cls, path: Path, opposing: bool = False) -> LoadTorque:
        """Rows ``time_s,newton_metres`` (a header row is allowed); times from 0, increasing."""
        rows = read_rows(path, "newton_metres", -1e3, 1e3)
        return cls(tuple(rows), opposing)

    def at(self, t_s: float, omega: float) -> float:
        """The load torque at time ``t_s`` for velocity ``omega``."""
        nm = self.rows[0][1]
        for start, value in self.rows:
            if start > t_s:
                break
            nm = value
        if self.opposing:
            return math.copysign(abs(nm), omega) if omega != 0.0 else 0.0
        return nm


class Account:
    """An energy total: whole µJ as an int plus the remainder (0 <= rest < 1 µJ) as a float."""

    __slots__ = ("_rest", "uj")

    def __init__(self) -> None:
        self.uj = 0
        self._rest = 0.0

    def add(self, joules: float) -> None:
        self._rest += joules * 1e6
        whole = math.floor(self._rest)
        self.uj += whole
        self._rest -= whole

    @property
    def joules(self) -> float:
        return (self.uj + self._rest) / 1e6


@dataclass
class Energy:
    """Energy accounts since start (each >= 0, in µJ as ``.uj``)."""

    drawn: Account = field(default_factory=Account)
    """∫max(P, 0) dt: electrical energy taken from the DC link."""
    regenerated: Account = field(default_factory=Account)
    """∫max(−P, 0) dt: electrical energy fed back into the DC link."""
    copper_loss: Account = field(default_factory=Account)
    """∫R·i² dt."""
    motoring: Account = field(default_factory=Account)
    """∫max(τ·ω, 0) dt: mechanical work done by the motor."""
    braking: Account = field(default_factory=Account)
    """∫max(−τ·ω, 0) dt: mechanical work taken back by the motor."""
    friction: Account = field(default_factory=Account)
    """∫b·ω² dt."""
    load_in: Account = field(default_factory=Account)
    """∫max(τ_load·ω, 0) dt: work done against the load."""
    load_out: Account = field(default_factory=Account)
    """∫max(−τ_load·ω, 0) dt: work the load did on the rotor."""

    @property
    def mechanical_work_j(self) -> float:
        """∫τ·ω dt (signed)."""
        return self.motoring.joules - self.braking.joules

    @property
    def load_work_j(self) -> float:
        """∫τ_load·ω dt (signed)."""
        return self.load_in.joules - self.load_out.joules


def _signed(value: float, plus: Account, minus: Account) -> None:
    if value >= 0:
        plus.add(value)
    else:
        minus.add(-value)


@dataclass
class Motor:
    """State (``omega`` rad/s, ``theta`` rad, ``current`` A, ``torque`` N·m, ``load`` N·m) and the
    energy accounts; ``peak_power_w`` is the largest electrical power drawn so far."""

    params: MotorParams = field(default_factory=MotorParams)
    load_torque: LoadTorque = field(default_factory=LoadTorque)
    omega: float = 0.0
    theta: float = 0.0
    current: float = 0.0
    torque: float = 0.0
    load: float = 0.0
    peak_power_w: float = 0.0
    energy: Energy = field(default_factory=Energy)

    @property
    def power_w(self) -> float:
        """Electrical power now (negative when regenerating)."""
        return self.torque * self.omega + self.params.resistance * self.current**2

    @property
    def kinetic_j(self) -> float:
        return 0.5 * self.params.inertia * self.omega**2

    def speed_limited(self, tau: float, dt: float, t_s: float, w_max: float) -> float:
        """``tau`` (N·m) cut so that a ``step(dt, tau / kt, t_s)`` from now does no motoring
        (τ·ω > 0) beyond ``w_max`` rad/s: none in ω's direction once |ω| is past it, else at most
        the torque that ends the step at ±``w_max`` (within a step ω moves monotonically toward
        (τ − load)/b, so |ω| stays within its ends). Braking torque is left as it is."""
        if tau == 0.0:
            return tau
        sign = 1.0 if tau > 0 else -1.0
        w0 = sign * self.omega  # mirrored: the torque is positive
        if w0 > w_max:
            return 0.0
        p = self.params
        load = sign * self.load_torque.at(t_s, self.omega)
        rate = p.damping / p.inertia
        decay = math.exp(-rate * dt)
        bound = load + p.damping * (w_max - w0 * decay) / -math.expm1(-rate * dt)
        return sign * min(sign * tau, max(0.0, bound))

    def step(self, dt: float, current: float, t_s: float) -> None:
        """Advance ``dt`` seconds with ``current`` (A) held; ``t_s`` is the step's start time."""
        p = self.params
        self.current = current
        self.torque = tau = p.kt * current
        self.load = load = self.load_torque.at(t_s, self.omega)
        rate = p.damping / p.inertia  # 1/s
        w0 = self.omega
        w_end = (tau - load) / p.damping  # where ω would settle
        decay = math.exp(-rate * dt)
        w1 = w_end + (w0 - w_end) * decay

        def integrals(t: float) -> tuple[float, float]:
            """∫ω dt and ∫ω² dt from the step's start over ``t`` seconds."""
            a, c = w_end, w0 - w_end
            e1 = -math.expm1(-rate * t) / rate
            e2 = -math.expm1(-2 * rate * t) / (2 * rate)
            return a * t + c * e1, a * a * t + 2 * a * c * e1 + c * c * e2

        int_w, int_w2 = integrals(dt)
        copper = p.resistance * current**2
        self.energy.copper_loss.add(copper * dt)
        _signed(tau * int_w, self.energy.motoring, self.energy.braking)
        _signed(load * int_w, self.energy.load_in, self.energy.load_out)
        self.energy.friction.add(p.damping * int_w2)
        # P(t) = τ·ω(t) + R·i² is monotonic over the step: split at its zero, if any.
        p0, p1 = tau * w0 + copper, tau * w1 + copper
        electrical = tau * int_w + copper * dt
        if p0 >= 0 and p1 >= 0:
            self.energy.drawn.add(electrical)
        elif p0 <= 0 and p1 <= 0:
            self.energy.regenerated.add(-electrical)
        else:
            w_zero = -copper / tau  # τ != 0 here, else P = copper >= 0
            t_zero = -math.log((w_zero - w_end) / (w0 - w_end)) / rate
            first = tau * integrals(t_zero)[0] + copper * t_zero
            second = electrical - first
            (self.energy.drawn if p0 > 0 else self.energy.regenerated).add(abs(first))
            (self.energy.drawn if p1 > 0 else self.energy.regenerated).add(abs(second))
        self.peak_power_w = max(self.peak_power_w, p0, p1)
        self.omega = w1
        self.theta += int_w
