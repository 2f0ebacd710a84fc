"""CiA 402 as a device profile (``canergy.devices.profile.Profile`` of ``Limits``). Sans-IO.

The limits are the three objects 0x6072 (‰ of the rated torque 0x6076), 0x6073 (‰ of the rated
current 0x6075) and 0x6080 (the drive's velocity unit); their envelope is ``τ_max·ω_max +
R·i_max²`` (``Ratings.envelope_fw``); closed, they allow no torque and no current; a quick stop
draws what ``Ratings.stop_fw_us`` says over its ramp (0x6085), a disable-voltage stop nothing (the
motor coasts). The CiA 402 guard's meter charges and bounds through this profile once the drive
is set up, so the formula and its parts show in the status as a device profile's do.

What the bound depends on beside the limits is declared here too: ``watches`` says which writes
behind the guard matter (``canergy.cia402.watch.Watched``: the PDO configuration, the limit
objects, the ratings, the mode, the heartbeat consumer, the counter object on the drive, the
stop ramps of a quick stop), ``read_back_keys`` which objects are read at set-up and after such
a write, and ``verify`` what a read-back must show; ``mismatch`` names a limit the link wrote
that did not read back. A write's value is known only by reading the drive back, so the guard
charges it at the drive's reach until then.
"""

from __future__ import annotations

from dataclasses import dataclass

from canergy.cia402.envelope import MAX_CURRENT, MAX_SPEED, MAX_TORQUE, Limits, Ratings, StopKind
from canergy.cia402.watch import Key, Watched, Write, check, expected_keys
from canergy.devices.profile import Envelope

FORMULA = "torque_nm * speed_rad_s + resistance_ohm * current_a**2"


@dataclass(frozen=True, slots=True)
class Cia402Profile:
    """One drive's ratings and stop, as the profile interface asks."""

    ratings: Ratings
    stop: StopKind = StopKind.DISABLE
    deceleration: int = 0
    """0x6085, velocity units per s (0: unknown, a quick stop charged at the whole envelope)."""
    name: str = "cia402"
    counter: Key | None = None
    """The counter object on the drive (counter mode), or None: writes to it matter."""

    def envelope(self, limits: Limits) -> Envelope:
        parts = {**self.fields(limits), "resistance_ohm": self.ratings.resistance_mohm / 1e3}
        return Envelope(self.ratings.envelope_fw(limits), FORMULA, parts)

    def closed(self, limits: Limits) -> Limits:
        return limits.closed()

    def mismatch(self, wrote: Limits, read: Limits) -> str | None:
        """The first object that did not read back as written, named with both values."""
        written, seen = wrote.as_objects(), read.as_objects()
        for index in (MAX_TORQUE, MAX_CURRENT, MAX_SPEED):
            if written[index] != seen[index]:
                return f"0x{index:04X} read back {seen[index]}, written {written[index]}"
        return None

    def stop_fw_us(self, limits: Limits, stop_us: int) -> int:
        if self.stop is StopKind.DISABLE:
            return 0
        return self.ratings.stop_fw_us(limits, self.deceleration, stop_us)

    def fields(self, limits: Limits) -> dict[str, float]:
        r = self.ratings
        return {
            "torque_nm": limits.torque_permille * r.rated_torque_mnm / 1e6,
            "current_a": limits.current_permille * r.rated_current_ma / 1e6,
            "speed_rad_s": float(limits.speed * r.velocity_unit_rad_s),
        }

    def observe(self, measured: dict[str, float]) -> None:
        """A CiA 402 drive's ratings come from its objects at set-up; nothing raises them."""

    def watches(self, write: Write) -> bool:
        """A write behind the guard the bound depends on (the controlword is the guard's)."""
        return Watched(self.stop, self.counter).matters(write)

    def read_back_keys(self) -> tuple[Key, ...]:
        """Beside the PDO configuration and the limits: the objects read at set-up that must
        hold what they held then (``verify``)."""
        return expected_keys(self.stop)

    def verify(
        self, setup: dict[Key, int], read: dict[Key, int | None], limits: Limits | None
    ) -> str | None:
        """What a read-back shows that the guard does not expect (``setup`` as read then, a
        stop ramp steeper; ``limits`` as written), every object named; None: all holds."""
        return check(setup, read, limits)
