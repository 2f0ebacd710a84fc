"""Metering modes, and the *sampled* meters: power from the values TPDOs carry. Integers only.

The sound modes are ``counter`` (``canergy.cia402.counter``) and ``envelope``
(``canergy.cia402.envelope``). The two sampled modes below only see power at the instants TPDOs
are sampled: motion timed between two samples is invisible to them (aliasing), so they guarantee
nothing and exist for drives that have neither a counter nor limits the guard can write.

- **sampled-mechanical**: torque actual (0x6077, ‰ of the rated torque 0x6076) × velocity actual
  (0x606C, in the drive's velocity unit), plus copper losses R·i² from current actual (0x6078,
  ‰ of the rated current 0x6075) and the winding resistance the installer gives. Without R the
  meter misses what the windings turn into heat: give the largest R the motor can have (hot).
- **sampled-electrical**: DC link voltage (0x6079, mV) × a DC link current object (mA), for
  drives that have one (manufacturer-specific; the emulator's is 0x2010).

Power is known only at samples. Over each interval the meter charges the larger of the power at
its two ends, which is an upper bound *only* where power is monotone between two samples: a
pulse that starts after one sample and ends before the next is not seen at all. Power that flows
back (negative) is not credited unless ``credit_regen``; then it only offsets energy drawn later,
never the books.

Power is in fW (1e-15 W) and time in µs, so energy is exact in fW·µs; 1 µJ = 1e15 fW·µs.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from fractions import Fraction

from canergy.devices.profile import Metering

FW_US_PER_UJ = 10**15

TORQUE_ACTUAL = 0x6077
VELOCITY_ACTUAL = 0x606C
CURRENT_ACTUAL = 0x6078
DC_LINK_VOLTAGE = 0x6079
RATED_CURRENT = 0x6075
RATED_TORQUE = 0x6076


class MeterKind(Enum):
    COUNTER = "counter"
    """A cumulative energy object: tight, sound."""
    ENVELOPE = "envelope"
    """The drive's limits written by the guard, charged at their largest power: sound."""
    SAMPLED_MECHANICAL = "sampled-mechanical"
    SAMPLED_ELECTRICAL = "sampled-electrical"

    @property
    def sampled(self) -> bool:
        """Power read at TPDO instants only: can be fooled, no bound claimed."""
        return self in (MeterKind.SAMPLED_MECHANICAL, MeterKind.SAMPLED_ELECTRICAL)

    @property
    def metering(self) -> Metering:
        """The device-profile metering mode this is (both sampled modes are ``sampled``)."""
        return Metering.SAMPLED if self.sampled else Metering(self.value)


@dataclass(frozen=True, slots=True)
class MeterConfig:
    """How to turn one set of PDO values into power. Scales are exact fractions."""

    kind: MeterKind = MeterKind.SAMPLED_MECHANICAL
    rated_torque_mnm: int = 0
    """0x6076, read from the drive at set-up."""
    rated_current_ma: int = 0
    """0x6075, read from the drive at set-up."""
    velocity_unit_rad_s: Fraction = Fraction(1, 1000)
    """What one unit of 0x606C is, in rad/s."""
    resistance_mohm: int = 0
    """Winding resistance for copper losses (mechanical metering), mΩ."""
    bus_current_index: int | None = None
    """Object holding the DC link current in mA (electrical metering)."""
    credit_regen: bool = False

    def needs(self) -> tuple[int, ...]:
        """The objects the TPDOs must carry for sampled power (none in the sound modes)."""
        if not self.kind.sampled:
            return ()
        if self.kind is MeterKind.SAMPLED_ELECTRICAL:
            assert self.bus_current_index is not None
            return (DC_LINK_VOLTAGE, self.bus_current_index)
        needed = (TORQUE_ACTUAL, VELOCITY_ACTUAL)
        return (*needed, CURRENT_ACTUAL) if self.resistance_mohm else needed

    def power_fw(self, values: dict[int, int]) -> int | None:
        """Power in fW from the latest values, or None while one of them was never seen."""
        if any(index not in values for index in self.needs()):
            return None
        if self.kind is MeterKind.SAMPLED_ELECTRICAL:
            assert self.bus_current_index is not None
            mv, ma = values[DC_LINK_VOLTAGE], values[self.bus_current_index]
            return max(v * a for v in (mv - 1, mv + 1) for a in (ma - 1, ma + 1)) * 10**9
        # Each value is rounded by the drive (by up to one unit, whichever way it rounds): take
        # the largest power the rounding allows. N·m = ‰/1000 × mN·m/1000 and W = N·m × rad/s,
        # so fW = ‰ × mN·m × rad/s × 1e9.
        torque, velocity = values[TORQUE_ACTUAL], values[VELOCITY_ACTUAL]
        mech = max(t * v for t in (torque - 1, torque + 1) for v in (velocity - 1, velocity + 1))
        mech_fw = Fraction(mech * self.rated_torque_mnm) * self.velocity_unit_rad_s * 10**9
        copper_fw = 0
        if self.resistance_mohm:
            # A = ‰/1000 × mA/1000 and W = A² × mΩ/1000, so fW = (‰ × mA)² × mΩ
            amps = (abs(values[CURRENT_ACTUAL]) + 1) * self.rated_current_ma
            copper_fw = amps * amps * self.resistance_mohm
        total = mech_fw + copper_fw
        return -((-total.numerator) // total.denominator)  # rounded up: never under-metered


@dataclass(slots=True)
class EnergyMeter:
    """Integrates sampled power into whole µJ drawn, carrying the remainder."""

    config: MeterConfig
    last_us: int | None = None
    last_fw: int | None = None
    remainder: int = 0
    """Energy below 1 µJ not yet charged, fW·µs (after any regeneration credit)."""
    metered_uj: int = 0
    regen_uj: int = 0
    """Energy that flowed back, whole µJ (credited only with ``credit_regen``)."""
    peak_fw: int = 0
    samples: int = 0

    def sample(self, now: int, values: dict[int, int], *, charge: bool = True) -> int:
        """A new set of values at ``now`` (µs); returns the µJ drawn since the last sample.
        ``charge=False``: the drive had its power stage off for the whole interval (nothing is
        charged, not even the allowance for rounded values)."""
        power = self.config.power_fw(values)
        if power is None:
            return 0
        self.samples += 1
        self.peak_fw = max(self.peak_fw, power)
        drawn = 0
        if charge and self.last_us is not None and self.last_fw is not None and now > self.last_us:
            energy = max(self.last_fw, power) * (now - self.last_us)
            if energy < 0:
                self.regen_uj += -energy // FW_US_PER_UJ
                energy = energy if self.config.credit_regen else 0
            self.remainder += energy
            if self.remainder > 0:
                drawn, self.remainder = divmod(self.remainder, FW_US_PER_UJ)
        if self.last_us is None or now >= self.last_us:
            self.last_us, self.last_fw = now, power
        self.metered_uj += drawn
        return drawn
