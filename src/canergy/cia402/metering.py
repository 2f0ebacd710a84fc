"""What one guarded drive is charged, in each metering mode, and the bound that goes with it.

``DriveMeter`` holds what the guard knows of the drive's energy: the limits in force (written by
the guard, confirmed by read-back), the figures its bound is made of (configured allowances raised
to what was seen), and the mode's meter:

- ``envelope``: every µs of host time is charged at the largest envelope in force during it. A
  raised limit is in force from the moment the guard decides it; a lowered one only once the
  drive has confirmed it and had its latency to act on it.
- ``counter``: each reading is charged its difference from the previous one (``CounterMeter``);
  the limits bound only what may be drawn after the last reading.
- ``sampled-*``: power at TPDO instants (``EnergyMeter``); no limits, no bound.

Sans-IO: times are integer µs from the caller.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from canergy.cia402.counter import COUNTER_KEY, CounterConfig, CounterMeter
from canergy.cia402.envelope import (
    Bound,
    Limits,
    Ratings,
    StopKind,
    Timings,
    bound,
)
from canergy.cia402.meter import EnergyMeter, MeterConfig, MeterKind
from canergy.cia402.profile import Cia402Profile
from canergy.devices.clock import ClockCharge


@dataclass(frozen=True, slots=True)
class Allowances:
    """The configured figures a bound starts from, µs (raised to what is seen, never lowered)."""

    gap_us: int = 200_000
    reaction_us: int = 10_000
    latency_us: int = 5_000
    stop_timeout_us: int = 1_000_000


@dataclass(frozen=True, slots=True)
class DriveSetup:
    """What the link read from the drive at set-up."""

    ratings: Ratings
    deceleration: int = 0
    """0x6085 quick stop deceleration, velocity units per s (0: unknown)."""
    latency_us: int = 0
    """The controlword write measured at set-up."""
    limits: Limits | None = None
    """The limits the link wrote and read back at set-up."""
    reach: Limits | None = None
    """The most the drive can be set to (its EDS maxima, the objects' ranges, or flags): what a
    write the guard has not verified yet is charged at."""
    config: dict[tuple[int, int], int] = field(default_factory=dict)
    """What the guard's bound depends on beside the limits, as read at set-up (PDO
    configuration, heartbeat consumer, ratings, quick stop objects): read back after a write."""


class DriveMeter:
    """Charges and bounds for one drive (see the module doc)."""

    def __init__(
        self,
        kind: MeterKind,
        sampled: MeterConfig,
        limits: Limits | None,
        counter: CounterConfig | None,
        stop: StopKind,
        allowances: Allowances,
    ) -> None:
        if not kind.sampled and limits is None:
            raise ValueError(f"{kind.value} metering needs the drive's limits")
        if kind is MeterKind.COUNTER and counter is None:
            raise ValueError("counter metering needs a counter object")
        self.kind = kind
        self.full = None if kind.sampled else limits
        """The full limits (the sampled modes write none)."""
        self.stop = stop
        self.allowances = allowances
        self.sampled = EnergyMeter(sampled)
        self.counter = CounterMeter(counter) if counter is not None else None
        self.setup: DriveSetup | None = None
        self.profile: Cia402Profile | None = None
        """The drive as a device profile, once set up (its ratings, its stop, 0x6085)."""
        self.confirmed: Limits | None = None
        """The limits the drive last confirmed (read back)."""
        self.pending: Limits | None = None
        """Written, not yet confirmed."""
        self.clock = ClockCharge()
        """Charged by the clock (envelope mode, and after a write behind the guard)."""
        self.metered_uj = 0
        self.unbooked_uj = 0
        """Charged, not yet taken by the guard (``take``): every charge ends up booked."""
        self.worst_gap_us = 0
        self.worst_age_us = 0
        self.reaction_us = 0
        self.latency_us = 0
        self.suspect_from: int | None = None
        """A write behind the guard was seen: charged at the reach by the clock from then (in
        counter mode from the last trusted reading) until the configuration is verified."""
        self.rebase = False
        """Counter mode: verified; the next reading is the new baseline (not differenced)."""

    @property
    def sound(self) -> bool:
        return self.kind.metering.sound

    # -- set-up and limits ------------------------------------------------------------------
    def ready(self, now: int, setup: DriveSetup) -> None:
        """The drive is set up: its ratings known, its set-up limits confirmed."""
        self.setup = setup
        counter = self.counter.config if self.counter is not None else None
        on_drive = None if counter is None or counter.node is not None else counter
        key = None if on_drive is None else (on_drive.index, on_drive.subindex)
        self.profile = Cia402Profile(setup.ratings, self.stop, setup.deceleration, counter=key)
        r = setup.ratings
        self.sampled.config = replace(
            self.sampled.config,
            rated_torque_mnm=r.rated_torque_mnm,
            rated_current_ma=r.rated_current_ma,
        )
        self.latency_us = max(self.latency_us, setup.latency_us)
        self.confirmed, self.pending = setup.limits, None
        if self.sound:
            self.clock.start(now, self.in_force_fw(now))

    def envelope_fw(self, limits: Limits | None) -> int:
        if limits is None or self.profile is None:
            return 0
        return self.profile.envelope(limits).fw

    @property
    def reach(self) -> Limits | None:
        return None if self.setup is None else self.setup.reach

    def in_force_fw(self, now: int) -> int:
        """The largest envelope the drive may be working to now."""
        fw = max(self.envelope_fw(self.confirmed), self.envelope_fw(self.pending))
        if self.suspect_from is not None:
            fw = max(fw, self.envelope_fw(self.reach))
        return self.clock.held(fw, now)

    def write(self, now: int, limits: Limits) -> None:
        """The guard writes ``limits``: a raise counts from now."""
        self.charge(now)
        self.pending = limits
        self.clock.raise_to(self.in_force_fw(now))

    def confirm(self, now: int, limits: Limits) -> None:
        """The drive read back ``limits``."""
        self.charge(now)
        before = self.in_force_fw(now)
        self.confirmed = limits
        if self.pending == limits:
            self.pending = None
        if self.in_force_fw(now) < before:
            self.clock.lower(before, now + self.timings().latency_us)
        self.clock.raise_to(self.in_force_fw(now))

    def target(self) -> Limits | None:
        """The limits written or being written."""
        return self.pending if self.pending is not None else self.confirmed

    def suspect(self, now: int, since: int) -> None:
        """A write the bound depends on was seen at ``since``: charge the reach from then."""
        clock = self.clock
        if not self.sound or self.setup is None or clock.until is None:
            return
        self.rebase = False
        if self.suspect_from is not None:
            return
        if self.kind is MeterKind.ENVELOPE:
            self.charge(now)
            early = max(0, clock.until - since)  # charged below the reach meanwhile
            self.suspect_from = since
            # metered now, not when the clock next runs: the host may exit before it does
            self._charged(clock.owed(self.envelope_fw(self.reach) * early))
        else:  # the counter may be lying from here: the clock at the reach, from the last reading
            last = self.counter.last_us if self.counter is not None else None
            clock.until = min(since, now if last is None else last)
            self.suspect_from = clock.until
        clock.fw = self.in_force_fw(now)
        self.charge(now)

    def verified(self, now: int) -> None:
        """The configuration read back as the guard expects: back to the limits in force (in
        counter mode from the next reading, the new baseline)."""
        if self.suspect_from is None:
            return
        self.charge(now)
        if self.kind is MeterKind.COUNTER:
            self.rebase = True
            return
        self.suspect_from = None
        self.clock.fw = self.in_force_fw(now)

    # -- charging ---------------------------------------------------------------------------
    def take(self) -> int:
        """µJ charged since the last ``take``, for the guard to spend."""
        drawn, self.unbooked_uj = self.unbooked_uj, 0
        return drawn

    def owe(self, uj: int) -> None:
        """``uj`` the drive may draw that no reading will show (a quick stop under way as the
        host exits): charged now."""
        self._charged(uj)

    def _charged(self, drawn: int) -> None:
        self.metered_uj += drawn
        self.unbooked_uj += drawn

    def charge(self, now: int) -> None:
        """Envelope mode: charge what the drive may have drawn up to ``now``, by the host's
        clock (``take`` hands it over); a lowered envelope stops counting when it expired."""
        by_clock = self.kind is MeterKind.ENVELOPE or self.suspect_from is not None
        if by_clock:
            self._charged(self.clock.run(now, self.in_force_fw))

    def sample(self, now: int, values: dict[int, int], powerless: bool) -> None:
        """TPDO values received at ``now``: charge what was drawn since the last ones."""
        if self.kind is MeterKind.ENVELOPE:
            self.charge(now)
        elif self.kind is MeterKind.COUNTER:
            if self.counter is None or COUNTER_KEY not in values or self.setup is None:
                return
            if self.suspect_from is not None:
                self.charge(now)
                if not self.rebase:
                    return  # not trusted: the clock charges the reach
                self.suspect_from, self.rebase = None, False
                self.counter.last_raw = None  # the new baseline
            fw = max(self.clock.fw, self.in_force_fw(now))
            self.clock.fw = self.in_force_fw(now)
            self._charged(self.counter.sample(now, values[COUNTER_KEY], fw))
        else:
            self._charged(self.sampled.sample(now, values, charge=not powerless))

    def gap(self, gap_us: int) -> None:
        self.worst_gap_us = max(self.worst_gap_us, gap_us)

    def age(self, age_us: int) -> None:
        """A TPDO's age when the host took it in (sampled that long before)."""
        self.worst_age_us = max(self.worst_age_us, age_us)

    def watch(self, reaction_us: int, latency_us: int) -> None:
        """The longest host reaction and drive latency the link has measured."""
        self.reaction_us = max(self.reaction_us, reaction_us)
        self.latency_us = max(self.latency_us, latency_us)

    # -- the bound --------------------------------------------------------------------------
    def timings(self) -> Timings:
        a = self.allowances
        return Timings(
            gap_us=max(a.gap_us, self.worst_gap_us),
            reaction_us=max(a.reaction_us, self.reaction_us),
            latency_us=max(a.latency_us, self.latency_us),
            stop_timeout_us=a.stop_timeout_us,
            age_us=self.worst_age_us,
        )

    def bound(self, limits: Limits | None) -> Bound | None:
        """What a drive working to ``limits`` may draw past its last charged reading (None in
        the sampled modes, or before set-up)."""
        if not self.sound or limits is None or self.setup is None:
            return None
        resolution = 0
        if self.counter is not None and self.kind is MeterKind.COUNTER:
            resolution = self.counter.config.unit_uj
        assert self.profile is not None
        return bound(self.profile, limits, self.timings(), resolution)

    def status(self, now: int) -> dict[str, Any]:
        out: dict[str, Any] = {
            "meter": self.kind.value,
            "guarantee": self.kind.metering.guarantee,
            "metered_uj": self.metered_uj,
            "stop": self.stop.value,
        }
        if not self.sound:
            m = self.sampled
            out |= {
                "bound_uj": None,
                "regenerated_uj": m.regen_uj,
                "peak_power_w": round(m.peak_fw / 1e15, 3),
                "samples": m.samples,
            }
            return out
        t = self.timings()
        target = self.target()
        worst = self.bound(self.full)
        if self.profile is not None and self.full is not None:
            full = self.profile.envelope(self.full)
            out |= {
                "profile": "cia402",
                "envelope_formula": full.formula,
                "envelope_parts": full.parts,
            }
        now_bound = self.bound(target)
        reach = self.bound(self.reach)
        out |= {
            "bound_uj": None if worst is None else worst.total_uj,
            "bound_reach_uj": None if reach is None else reach.total_uj,
            "suspect": self.suspect_from is not None,
            "bound_stop_uj": None if worst is None else worst.stop_uj,
            "bound_now_uj": None if now_bound is None else now_bound.total_uj,
            "envelope_w": round(self.in_force_fw(now) / 1e15, 3),
            "limits": None
            if target is None
            else {f"0x{i:04X}": v for i, v in target.as_objects().items()},
            "limits_confirmed": self.confirmed == target,
            "worst_gap_us": self.worst_gap_us,
            "bound_timings_us": {
                "gap": t.gap_us,
                "reaction": t.reaction_us,
                "latency": t.latency_us,
                "stop_timeout": t.stop_timeout_us,
                "age": t.age_us,
            },
        }
        if self.counter is not None:
            c = self.counter
            out |= {"counter_readings": c.readings, "counter_ambiguous": c.ambiguous}
        return out
