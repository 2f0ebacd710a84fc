"""What a drive can draw at most: its limits as an energy envelope, and the overshoot bound.

A drive that honours its limits (0x6072 max torque, 0x6073 max current, 0x6080 max motor speed)
draws at most ``τ_max·ω_max + R·i_max²`` from its DC link, whatever its application commands:
that is the envelope. The guard writes the limits, reads them back, and charges the envelope by
the host's clock, so no motion between two TPDOs can exceed what is charged.

What a drive may draw past the moment its budget runs out is bounded by the envelope over the
longest time the guard can take to notice and the drive to act (the worst TPDO gap allowed, the
host's reaction, the drive's own latency), plus what the stop itself can draw. Integers only:
power in fW (1e-15 W), time in µs, energy in µJ (1 µJ = 1e15 fW·µs).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from fractions import Fraction

from canergy.cia402.meter import FW_US_PER_UJ
from canergy.devices.profile import Profile

MAX_TORQUE = 0x6072
MAX_CURRENT = 0x6073
MAX_SPEED = 0x6080
QUICK_STOP_DECELERATION = 0x6085
LIMIT_OBJECTS = (MAX_TORQUE, MAX_CURRENT, MAX_SPEED)
LEVELS = 4
"""Torque and current limits taper in halves as the budget falls: 1, 1/2, 1/4, 1/8."""


def ceil_div(a: int, b: int) -> int:
    return -(-a // b)


class StopKind(Enum):
    QUICK = "quick"
    """Quick stop (controlword), then disable voltage once standing or after the stop timeout."""
    DISABLE = "disable"
    """Disable voltage at once: the drive coasts and draws nothing more."""


@dataclass(frozen=True, slots=True)
class Limits:
    """The three limit objects as the drive holds them."""

    torque_permille: int
    """0x6072, ‰ of the rated torque 0x6076."""
    current_permille: int
    """0x6073, ‰ of the rated current 0x6075."""
    speed: int
    """0x6080, in the drive's velocity unit."""

    def as_objects(self) -> dict[int, int]:
        return {
            MAX_TORQUE: self.torque_permille,
            MAX_CURRENT: self.current_permille,
            MAX_SPEED: self.speed,
        }

    def tapered(self, level: int) -> Limits:
        """Torque and current halved ``level`` times (rounded down: never above the full)."""
        return Limits(self.torque_permille >> level, self.current_permille >> level, self.speed)

    def closed(self) -> Limits:
        """No torque and no current: the drive can draw nothing."""
        return Limits(0, 0, self.speed)

    def describe(self) -> str:
        return (
            f"0x6072 = {self.torque_permille}, 0x6073 = {self.current_permille}, "
            f"0x6080 = {self.speed}"
        )


@dataclass(frozen=True, slots=True)
class Ratings:
    """What turns the limit objects into SI figures: read from the drive, or given."""

    rated_torque_mnm: int
    """0x6076."""
    rated_current_ma: int
    """0x6075."""
    velocity_unit_rad_s: Fraction = Fraction(1, 1000)
    """One unit of 0x606C/0x6080 in rad/s (and of 0x6085 in rad/s²)."""
    resistance_mohm: int = 0
    """The hottest winding resistance, mΩ."""

    def envelope_fw(self, limits: Limits) -> int:
        """τ_max·ω_max + R·i_max², fW, rounded up."""
        # N·m = ‰/1000 × mN·m/1000 and W = N·m × rad/s: fW = ‰ × mN·m × rad/s × 1e9
        mech = (
            Fraction(limits.torque_permille * self.rated_torque_mnm * limits.speed * 10**9)
            * self.velocity_unit_rad_s
        )
        # A = ‰/1000 × mA/1000 and W = A² × mΩ/1000: fW = (‰ × mA)² × mΩ
        amps = limits.current_permille * self.rated_current_ma
        total = mech + amps * amps * self.resistance_mohm
        return ceil_div(total.numerator, total.denominator)

    def stop_fw_us(self, limits: Limits, deceleration: int, stop_us: int) -> int:
        """What a quick stop of at most ``stop_us`` can draw, fW·µs: copper losses R·i_max² for
        all of it, and motoring τ_max·ω only while the ramp (``deceleration``, velocity units
        per s) still asks for speed: τ_max·ω_max²/(2a). Kinetic energy flows back, not in;
        never more than the envelope for the whole stop."""
        whole = self.envelope_fw(limits) * stop_us
        if deceleration <= 0:
            return whole
        amps = limits.current_permille * self.rated_current_ma
        copper = amps * amps * self.resistance_mohm * stop_us
        # τ·ω_max²/(2a) in J: (‰·mN·m/1e6) × (speed·u)² / (2·dec·u) = ‰·mN·m·speed²·u/(2e6·dec)
        motoring = (
            Fraction(limits.torque_permille * self.rated_torque_mnm * limits.speed**2 * 10**9)
            * self.velocity_unit_rad_s
            / (2 * deceleration)
            * 10**6
        )
        motoring_fw_us = ceil_div(motoring.numerator, motoring.denominator)
        return min(whole, copper + motoring_fw_us)


@dataclass(frozen=True, slots=True)
class Timings:
    """The times a bound is made of, µs: configured allowances, raised to what was seen."""

    gap_us: int
    """The longest time between TPDOs before the guard stops the drive (its PDO timeout)."""
    reaction_us: int
    """From a TPDO's arrival to the controlword leaving the host."""
    latency_us: int
    """From a controlword write to the drive acting on it."""
    stop_timeout_us: int
    """Quick stop: disable voltage this long after, at the latest."""
    age_us: int = 0
    """The oldest a TPDO was when the host took it in: drawn before it arrived, not in it."""

    @property
    def notice_us(self) -> int:
        return self.age_us + self.gap_us + self.reaction_us + self.latency_us

    @property
    def stop_us(self) -> int:
        return self.stop_timeout_us + self.reaction_us + self.latency_us


@dataclass(frozen=True, slots=True)
class Bound:
    """What a drive may draw past the moment its budget is gone, µJ, and its parts."""

    envelope_fw: int
    notice_uj: int
    stop_uj: int
    resolution_uj: int = 0
    """A counter's unit: what it may not have shown yet."""

    @property
    def total_uj(self) -> int:
        return self.notice_uj + self.stop_uj + self.resolution_uj


def bound(
    profile: Profile[Limits], limits: Limits, timings: Timings, resolution_uj: int = 0
) -> Bound:
    """Envelope × (gap + reaction + latency) + the stop: what a drive running at ``limits`` may
    draw after the last TPDO that showed budget left (``profile``: the drive's ratings and stop,
    ``canergy.cia402.profile``)."""
    power = profile.envelope(limits).fw
    notice = ceil_div(power * timings.notice_us, FW_US_PER_UJ)
    stop_uj = ceil_div(profile.stop_fw_us(limits, timings.stop_us), FW_US_PER_UJ)
    return Bound(power, notice, stop_uj, resolution_uj)
