"""One device under an energy budget, for any ``Profile``: a proxy client, the envelope of the
limits the guard wrote and read back, charged by the host's clock, and a stop rule. Sans-IO.

As for CiA 402 (``canergy.cia402.guard``), the device never runs canergy: the host keeps a
hardened ``Client`` as its proxy and charges to it what the device may have drawn. In the sound
mode (``envelope``) every µs is charged at the largest envelope in force: the limits confirmed,
the limits being written, and limits someone else wrote on the bus (charged from the moment
their frame was seen until the guard's own, written after it, is confirmed; not confirmed within
``feedback_timeout_us`` of the first such write, the device is stopped for good, the write named
in ``unverified`` and the stop reason, as a CiA 402 drive is). A lowered envelope
counts until the device had its latency to act on it. The guard stops the device when what is
left falls to the reserve plus the bound (envelope × (reaction + latency + intake) + what the
stop may draw; the intake is the longest a write behind the guard waited, from its frame's
arrival, to be taken in: a host held off lengthens it, the device running at the writer's limits
meanwhile), waking exactly when the clock gets there; then it writes the closed limits.

The guarantee (``PER_STRETCH``): drawn <= granted + stretches × bound, ``stretches`` being 1 (the
guard's own stop) plus the writes behind the guard seen or found by a periodic read-back: a
writer that raises the limits again after the stop runs the device at them until the guard's own
are in force again, one stretch of at most one bound each time (charged as debt).

In ``sampled`` mode the device's own power readings are integrated between samples: no limits,
no bound, guarantee "none".

A device that does not show itself powerless within ``stop_timeout_us`` of a stop, or whose
feedback is gone, is **STUCK**: the stop is repeated, the status and the host's report say so,
and what it may draw from then on (the envelope in force, by the clock) is booked as
``uncontained_uj``, not as metered. Limits that do not read back as written refuse the device,
naming the limit; limits that cannot be read back at all (ODrive 0.5) refuse it unless the
configuration trusts them (``trust_limits``), which the status shows as ``limits_verified``
false.

Inputs: ``on_ready``, ``on_limits``, ``on_feedback``, ``on_watched`` (a frame from someone
else as the profile reads it: ``on_foreign_limits`` or ``on_foreign_write``), ``on_message``,
``on_wakeup``; outputs: canergy frames to the supervisor
and ``commands`` (``WriteLimits``, ``Stop``) for the link.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Generic

from canergy.cia402.envelope import Bound, ceil_div
from canergy.cia402.meter import FW_US_PER_UJ
from canergy.core import Timing
from canergy.devices.clock import ClockCharge
from canergy.devices.profile import (
    PER_STRETCH,
    Foreign,
    L,
    LimitsWritten,
    Metering,
    Profile,
    ReadLimits,
    Stop,
    Unbounded,
    WriteLimits,
)
from canergy.devices.proxy import EXHAUSTED, NO_BUDGET, ProxyBooks
from canergy.devices.watchdog import WatchdogCheck, WatchdogPolicy, WatchdogReading
from canergy.messages import QUANTUM_UJ, Message, ToClient

FOREVER = 2**62
REREAD_US = 1_000_000
"""How often the ODrive and moteus guards read their limits back (a CiA 402 drive's 1 s too),
and the MIT gate a Damiao motor's CAN Timeout register."""


class GuardPhase(Enum):
    RUNNING = "running"
    STOPPING = "stopping"
    """Stop sent: waiting for the device to show itself powerless."""
    STOPPED = "stopped"
    STUCK = "stuck"
    """Stopped and not obeying (or not heard): the stop is repeated."""


@dataclass(frozen=True, slots=True)
class DeviceConfig(Generic[L]):
    limits: L
    """The full limits the guard writes while the device holds budget."""
    sampled: bool = False
    """Meter the device's own power readings (no bound) instead of the envelope."""
    trust_limits: bool = False
    """Take limits that cannot be read back as written (reported unverified)."""
    timing: Timing = field(default_factory=Timing)
    reaction_us: int = 10_000
    """Host reaction the bound allows (raised to what is measured)."""
    latency_us: int = 5_000
    """Device latency the bound allows (raised to what is measured)."""
    feedback_timeout_us: int = 300_000
    """Stop (and latch) when the device was not heard for this long."""
    stop_timeout_us: int = 500_000
    """A stopped device must show itself powerless within this, or it is STUCK."""
    retry_us: int = 100_000
    reserve_uj: int = 0
    resume_margin_uj: int = 10 * QUANTUM_UJ
    telemetry_period_us: int = 50_000
    reread_us: int = 0
    """Read the limits back this often where they can be read (0: never): limits changed where
    the guard cannot see stop the device for good."""
    stuck_limits: L | None = None
    """What a STUCK device is charged at, where one that ignores its stop may ignore the
    closed limits too (an MIT motor holds its last command): from the stop's notice on, as
    uncontained. None: the limits in force."""
    unreadable: str = (
        "the odrive limits cannot be read back (no answer, or firmware 0.5): trust them as "
        "written with --odrive-trust-limits"
    )
    """Why limits that did not read back refuse the device (the profile's words)."""
    watchdog: WatchdogPolicy | None = None
    """How the device's own watchdog is judged (``canergy.devices.watchdog``; None: the
    status has no ``watchdog``)."""


class DeviceGuard(ProxyBooks, Generic[L]):
    """The budget of one device of ``profile``."""

    def __init__(
        self, node: int, profile: Profile[L], config: DeviceConfig[L], now: int, nonce: int
    ) -> None:
        super().__init__(node, config.timing, config.telemetry_period_us, now, nonce)
        self.profile = profile
        self.config = config
        self.commands: list[WriteLimits[L] | Stop | ReadLimits] = []
        self.phase = GuardPhase.STOPPED
        self.phase_at = now
        self.stop_reason: str | None = NO_BUDGET
        self.latched = False
        self.refused: str | None = None
        self.stuck: str | None = None
        self.ready_at: int | None = None
        self.verified: bool | None = None
        """The limits read back (True), taken on trust (False), not known yet (None)."""
        self.powered: bool | None = None
        self.unpowered_since: int | None = None
        """Since when every feedback has shown the power stage off (None: the last showed it
        on, or none yet)."""
        self.device_state: str | None = None
        self.last_feedback_at: int | None = None
        self.confirmed: L | None = None
        self.pending: L | None = None
        self.pending_at = now
        self.foreign: L | None = None
        """Limits someone else wrote, in force until a write of the guard's after them is
        confirmed."""
        self.foreign_at: int | None = None
        self.unverified: str | None = None
        """The first write behind the guard not yet written over by limits of the guard's that
        read back; ``unverified_at``: when it was taken in (the device is stopped for good
        ``feedback_timeout_us`` later if it still is)."""
        self.unverified_at: int | None = None
        self.early_foreign: list[tuple[int, L]] = []
        """Limits someone else wrote before the set-up was done (when, which)."""
        self.clock = ClockCharge()
        """Charged by the clock from the set-up's start (envelope mode)."""
        self.unbooked_uj = 0
        self.metered_uj = 0
        self.uncontained_uj = 0
        self.last_sample: tuple[int, int] | None = None
        """Sampled mode: the last power reading (when, fW)."""
        self.reaction_max_us = 0
        self.latency_max_us = 0
        self.confirm_max_us = 0
        """The longest a limits write took from the guard's decision to its read-back."""
        self.intake_max_us = 0
        """The longest a write behind the guard waited, from its frame's arrival, before the
        guard took it in (a host held off: the device runs at the writer's limits meanwhile)."""
        self.foreign_worst: L | None = None
        """The limits with the largest envelope someone else wrote (the status's bound is
        raised to theirs at the timings measured since, the last write's too)."""
        self.crossing: int | None = None
        """When the clock brings the budget to the stop threshold (envelope mode)."""
        self.last_stop_at = -config.retry_us
        self.rewrite_at: int | None = None
        self.bound_max_uj = 0
        """The largest bound the stop threshold held back (limits someone else wrote
        included): the status's ``bound_uj``, raised, never lowered."""
        self.stops = 0
        self.restops = 0
        self.writes_seen = 0
        self.writes_found = 0
        """Limits changed behind the guard that only a periodic read-back found (no frame seen)."""
        self.halted = False
        self.next_reread = now + config.reread_us if config.reread_us else None
        self.rereading: int | None = None
        """When the periodic read-back in flight was asked."""
        self.confirmed_at = now
        """When limits last read back (a periodic read asked before shows nothing)."""
        self.unread_since: int | None = None
        """When the oldest periodic read-back still without an answer was asked."""
        self.watchdog = None if config.watchdog is None else WatchdogCheck(config.watchdog)

    def running(self) -> bool:
        return self.phase is GuardPhase.RUNNING

    def stretches(self) -> int:
        """How many bounds the device may have drawn past its grant (``PER_STRETCH``): one for
        the guard's own stop, one more per write behind the guard seen or found by a read-back."""
        return 1 + self.writes_seen + self.writes_found

    @property
    def metering(self) -> Metering:
        return Metering.SAMPLED if self.config.sampled else Metering.ENVELOPE

    @property
    def sound(self) -> bool:
        return self.metering.sound

    # -- envelope and bound ---------------------------------------------------------------
    def _fw(self, limits: L | None) -> int:
        return 0 if limits is None else self.profile.envelope(limits).fw

    def in_force_fw(self, now: int) -> int:
        fw = max(self._fw(self.confirmed), self._fw(self.pending), self._fw(self.foreign))
        if self.phase is GuardPhase.STUCK:
            fw = max(fw, self._fw(self.config.stuck_limits))
        return self.clock.held(fw, now)

    def latency_us(self) -> int:
        return max(self.config.latency_us, self.latency_max_us)

    def reaction_us(self) -> int:
        """From the decision to the device holding the new limits or the stop: the allowance,
        raised to the longest reaction and limits write (read-back included) seen."""
        return max(self.config.reaction_us, self.reaction_max_us, self.confirm_max_us)

    def notice_us(self) -> int:
        """What the bound allows from a decision (or a write behind the guard) to its effect:
        reaction and latency, and the longest a write behind the guard waited to be taken in."""
        return self.reaction_us() + self.latency_us() + self.intake_max_us

    def bound(self, limits: L | None) -> Bound | None:
        """What the device may draw past the moment the guard decides to stop it."""
        if not self.sound or limits is None:
            return None
        fw = self._fw(limits)
        notice = ceil_div(fw * self.notice_us(), FW_US_PER_UJ)
        stop_us = self.config.stop_timeout_us
        stop = ceil_div(self.profile.stop_fw_us(limits, stop_us), FW_US_PER_UJ)
        return Bound(fw, notice, stop)

    def threshold_uj(self) -> int:
        if not self.sound:
            return self.config.reserve_uj
        worst = 0
        for limits in (self.config.limits, self.confirmed, self.pending, self.foreign):
            b = self.bound(limits)
            worst = max(worst, 0 if b is None else b.total_uj)
        self.bound_max_uj = max(self.bound_max_uj, worst, self._foreign_bound_uj())
        return self.config.reserve_uj + worst

    def _foreign_bound_uj(self) -> int:
        """The bound at the largest limits someone else wrote, at the timings measured now (a
        reaction or intake measured after their write was over is in it)."""
        b = self.bound(self.foreign_worst)
        return 0 if b is None else b.total_uj

    # -- charging -------------------------------------------------------------------------
    def charge(self, now: int) -> None:
        self._meter(self.clock.run(now, self.in_force_fw))

    def _meter(self, drawn: int) -> None:
        """What the clock charged: uncontained while STUCK, else metered (and booked next)."""
        if self.phase is GuardPhase.STUCK:
            self.uncontained_uj += drawn
        else:
            self.metered_uj += drawn
            self.unbooked_uj += drawn

    def _recharge(self, now: int) -> None:
        """The envelope in force changed at ``now`` (a raise counts from now)."""
        self.clock.raise_to(self.in_force_fw(now))

    # -- inputs ---------------------------------------------------------------------------
    def on_ready(self, now: int, started_at: int, full: L | None, closed: L | None) -> None:
        """Set-up: the link wrote the full limits and then the closed ones at ``started_at``,
        and read each back (None: could not be read back)."""
        self.ready_at = now
        if not self.sound:
            self.verified = False
            return
        want = self.config.limits
        for wrote, read in ((want, full), (self.profile.closed(want), closed)):
            if read is None:
                continue
            if (why := self.profile.mismatch(wrote, read)) is not None:
                self._refuse(f"limits not taken: {why}")
        if full is None or closed is None:
            self.verified = False
            if not self.config.trust_limits:
                self._refuse(self.config.unreadable)
        elif self.refused is None:
            self.verified = True
        self.confirmed = self.profile.closed(want)
        # the full limits were in force from the set-up's start until the closed ones: debt
        self.clock.start(started_at, self._fw(want))
        self.clock.lower(self._fw(want), now + self.latency_us())
        self.charge(now)
        # limits someone else wrote while the set-up ran, after a read-back could show them
        for at, limits in self.early_foreign:
            self._take_foreign(now, max(at, started_at), limits)
        self.early_foreign.clear()

    def on_limits(self, now: int, wrote: L, read: L | None, at: int) -> list[Message]:
        """The device read back ``read`` after the guard wrote ``wrote`` at ``at`` (None: not
        readable, or no answer)."""
        self.charge(now)
        self.confirm_max_us = max(self.confirm_max_us, now - at)
        if read is not None and (why := self.profile.mismatch(wrote, read)) is not None:
            self._refuse(f"limits not taken: {why}")
            return self._settled(now)
        if read is None and not self.config.trust_limits:
            if wrote == self.pending:
                self.rewrite_at = now + self.config.retry_us
            return self._settled(now)
        before = self.in_force_fw(now)
        self.confirmed, self.confirmed_at = wrote, now
        if self.pending == wrote:
            self.pending = None
        if self.foreign_at is not None and at >= self.foreign_at:  # written after it
            self.foreign, self.foreign_at = None, None
            self.unverified, self.unverified_at = None, None
        if self.in_force_fw(now) < before:
            self.clock.lower(before, now + self.latency_us())
        self._recharge(now)
        return self._settled(now)

    def on_read(self, now: int, read: L | None) -> list[Message]:
        """The periodic read-back's answer (None: not readable now; asked again next time)."""
        asked, self.rereading = self.rereading, None
        self.charge(now)
        if read is None:  # unanswered: past the feedback timeout, stopped for good
            if asked is not None and self.unread_since is None:
                self.unread_since = asked
            return self._settled(now)
        self.unread_since = None
        quiet = self.pending is None and self.foreign is None and self.confirmed is not None
        if asked is None or not quiet or self.confirmed_at > asked:
            return self._settled(now)  # a write since, or in flight: its own read-back checks
        assert self.confirmed is not None
        if (why := self.profile.mismatch(self.confirmed, read)) is not None:
            self.writes_found += 1  # a write behind the guard no frame showed: a stretch too
            self._refuse(f"limits changed behind the guard (a periodic read-back): {why}")
            # in force since the read was asked at the latest: charged at their envelope from
            # then until the guard's own limits (written at once) read back
            self._take_foreign(now, asked, read)
        return self._settled(now)

    def on_feedback(
        self,
        now: int,
        at: int,
        powered: bool | None,
        state: str | None = None,
        power_w: float | None = None,
        measured: dict[str, float] | None = None,
    ) -> list[Message]:
        """The device was heard at ``at`` (taken in at ``now``): whether its power stage is on,
        its state by name, a power reading (sampled mode) and figures that raise the envelope's
        parts."""
        self.charge(now)
        at = min(at, now)
        self.last_feedback_at = max(at, self.last_feedback_at or at)
        if powered is not None:
            self.powered = powered
            if powered:
                self.unpowered_since = None
            elif self.unpowered_since is None:
                self.unpowered_since = at
        if state is not None:
            self.device_state = state
        if measured:
            self.profile.observe(measured)
            self._recharge(now)
        if power_w is not None and not self.sound:
            fw = max(0, round(power_w * 1e15)) if power_w == power_w else 0
            self._sample_to(at)
            self.last_sample = (at, fw)
        return self._settled(now)

    def _sample_to(self, at: int) -> None:
        """Sampled mode: the last power reading charged up to ``at`` (and from ``at`` on)."""
        if self.last_sample is None:
            return
        since, fw = self.last_sample
        if self.ready_at is not None:
            drawn = fw * max(0, at - since) // FW_US_PER_UJ
            self.metered_uj += drawn
            self.unbooked_uj += drawn
        self.last_sample = (max(since, at), fw)

    def on_foreign_limits(self, now: int, at: int, limits: L) -> list[Message]:
        """Someone else wrote ``limits`` (seen at ``at``): charged from then, written over."""
        if not self.sound:
            return []
        self.writes_seen += 1
        self.intake_max_us = max(self.intake_max_us, now - at)
        if self.clock.until is None:  # during the set-up: taken in by ``on_ready``
            self.early_foreign.append((at, limits))
            return []
        self._take_foreign(now, at, limits)
        return self._settled(now)

    def _take_foreign(self, now: int, at: int, limits: L) -> None:
        clock = self.clock
        assert clock.until is not None
        self.charge(now)
        # the time since ``at`` already charged, each stretch up to these limits' envelope (the
        # envelope in force now may have been raised within it: not what it was charged at)
        # metered now, not when the clock next runs: the host may exit before it does
        self._meter(clock.back_charge(at, self._fw(limits)))
        if self._fw(limits) > self._fw(self.foreign):
            self.foreign = limits
        if self._fw(limits) > self._fw(self.foreign_worst):
            self.foreign_worst = limits
        self.foreign_at = at
        if self.unverified_at is None:
            fields = ", ".join(f"{k} {v:g}" for k, v in self.profile.fields(limits).items())
            self.unverified, self.unverified_at = f"limits {fields}", now
        self._recharge(now)
        self.threshold_uj()  # the status's bound raised to them, refused or not
        self.rewrite_at = now  # the guard's own limits again, at once

    def on_watched(self, now: int, at: int, seen: Foreign[L]) -> list[Message]:
        """A frame someone else sent the device (at ``at``), as the profile reads it."""
        if isinstance(seen, LimitsWritten):
            return self.on_foreign_limits(now, at, seen.limits)
        if isinstance(seen, Unbounded):
            return self.on_foreign_write(now, seen.what)
        return []

    def on_watchdog(
        self, now: int, reading: WatchdogReading | None, periodic: bool, alone: bool = False
    ) -> list[Message]:
        """The device's watchdog read back (None: unanswered), at set-up or with a periodic
        read-back: one the policy does not take refuses the device (stopped for good).
        ``alone``: a periodic read-back of the watchdog alone (``WatchdogCheck.take``)."""
        if self.watchdog is None:
            return []
        why = self.watchdog.take(now, reading, periodic, alone)
        if why is None:
            return []
        self._refuse(why)
        return self._settled(now)

    def on_foreign_write(self, now: int, what: str) -> list[Message]:
        """A write behind the guard whose effect it cannot bound: stopped for good."""
        self.writes_seen += 1
        self._refuse(f"a write behind the guard: {what}")
        return self._settled(now)

    def on_unseen(self, now: int, why: str) -> list[Message]:
        """Frames to the device may have passed unseen (``why``): stopped for good."""
        self._refuse(why)
        return self._settled(now)

    def on_message(self, msg: ToClient, now: int) -> list[Message]:
        self.charge(now)
        out = self._carry_out(self.client.receive(msg, now), now)
        return out + self._pay_debt(now) + self._settled(now)

    def watch(self, reaction_us: int, latency_us: int) -> None:
        self.reaction_max_us = max(self.reaction_max_us, reaction_us)
        self.latency_max_us = max(self.latency_max_us, latency_us)

    def halt(self, now: int) -> None:
        self.halted = True
        self._evaluate(now)

    def on_exit(self, now: int) -> list[Message]:
        """The host exits, its stop on the bus at ``now`` (``halt``, then the link closed) and
        what the link heard taken in: charged up to the device's latency past ``now`` (until
        it acts on the stop; a STUCK device's as uncontained), or its last power reading up to
        ``now`` (sampled), and booked. Nothing charges it after this."""
        self.charge(now + self.latency_us())
        self._sample_to(now)
        return self._settled(now)

    def next_wakeup(self) -> int:
        times = self._proxy_wakeups()
        if self.crossing is not None:
            times.append(self.crossing)
        if self.last_feedback_at is not None and self.phase is GuardPhase.RUNNING:
            times.append(self.last_feedback_at + self.config.feedback_timeout_us + 1)
        if self.phase in (GuardPhase.STOPPING, GuardPhase.STUCK):
            times.append(self.last_stop_at + self.config.retry_us)
        if self.phase is GuardPhase.STOPPING:  # STUCK keeps the stop's time: long past
            times.append(self.phase_at + self.config.stop_timeout_us + 1)
        if self.phase is GuardPhase.STUCK and self.unpowered_since is not None:
            times.append(self.unpowered_since + self.notice_us())
        if self.rewrite_at is not None:
            times.append(self.rewrite_at)
        if self.unverified_at is not None:
            times.append(self.unverified_at + self._verify_us() + 1)
        if self.unread_since is not None:
            times.append(self.unread_since + self._verify_us() + 1)
        if self.next_reread is not None:
            times.append(self.next_reread)
        return min(times)

    def on_wakeup(self, now: int) -> list[Message]:
        out = self._proxy_due(now)
        self.charge(now)
        if self.next_reread is not None and now >= self.next_reread:
            self.next_reread = now + self.config.reread_us
            lost = self.rereading is not None and now - self.rereading > self.config.reread_us
            if lost and self.unread_since is None:
                self.unread_since = self.rereading
            if self.verified and (self.rereading is None or lost) and self.refused is None:
                self.rereading = now
                self.commands.append(ReadLimits("periodic read-back", now))
        out += self._settled(now)
        if now >= self.next_telemetry:
            out.append(self.telemetry(now))
        return out

    # -- books ----------------------------------------------------------------------------
    def _settled(self, now: int) -> list[Message]:
        out = self._book(now)
        out += self._evaluate(now)
        return out + self._book(now)

    def _book(self, now: int) -> list[Message]:
        drawn, self.unbooked_uj = self.unbooked_uj, 0
        return self._spend_drawn(drawn, now)

    # -- decisions ------------------------------------------------------------------------
    def alive(self, now: int) -> bool:
        """Grants make sense: set up, heard lately, not refused or stuck."""
        heard = self.last_feedback_at
        return (
            heard is not None
            and self.ready_at is not None
            and now <= heard + self.config.feedback_timeout_us
            and self.refused is None
            and self.stuck is None
        )

    def _refuse(self, why: str) -> None:
        if self.refused is None:
            self.refused = why
        self.latched = True

    def _stop_reason(self, now: int) -> str | None:
        if self.halted:
            return "supervisor stopping"
        if self.refused is not None:
            return self.refused
        if self.unread_since is not None and now > self.unread_since + self._verify_us():
            ms = (now - self.unread_since) // 1000
            self._refuse(f"limits not read back for {ms} ms (the periodic read-back unanswered)")
            self.rewrite_at = now
            return self.refused
        if self.unverified_at is not None and now > self.unverified_at + self._verify_us():
            self._refuse(f"a write behind the guard ({self.unverified}) not verified in time")
            self.rewrite_at = now  # the closed limits, whatever is in force
            return self.refused
        if self.ready_at is None:
            return "not set up yet"
        heard = self.last_feedback_at if self.last_feedback_at is not None else self.ready_at
        if now > heard + self.config.feedback_timeout_us:
            self.latched = True
            return "feedback stopped"
        if self.usable <= self.threshold_uj():
            if self.crossing is not None and now >= self.crossing:
                self.reaction_max_us = max(self.reaction_max_us, now - self.crossing)
            return EXHAUSTED
        return None

    def _verify_us(self) -> int:
        """How long limits written behind the guard may stay unverified: the feedback
        timeout (as a CiA 402 drive's writes get the PDO timeout)."""
        return self.config.feedback_timeout_us

    def _evaluate(self, now: int) -> list[Message]:
        before = self.phase
        why = self._stop_reason(now)
        if why is not None:
            self._stop(why, now)
        elif self.phase is GuardPhase.STOPPED and self._may_resume():
            self._set_phase(GuardPhase.RUNNING, None, now)
        if self.phase is GuardPhase.STOPPED:
            self.stop_reason = self.held_back(self.stop_reason, why)
        self._steer_limits(now)
        self._watch_stop(now)
        self.crossing = self._crossing()
        return [self.telemetry(now)] if self.phase is not before else []

    def _crossing(self) -> int | None:
        """When the clock, at the envelope charged now, brings what is left to the stop
        threshold (None: not running, or nothing charged)."""
        clock = self.clock
        if self.phase is not GuardPhase.RUNNING or clock.until is None or clock.fw <= 0:
            return None
        left = self.usable - self.threshold_uj()
        room = max(0, left * FW_US_PER_UJ - clock.remainder)
        return clock.until + ceil_div(room, clock.fw)

    def _stop(self, why: str, now: int) -> None:
        if self.phase is GuardPhase.RUNNING:
            self.stops += 1
            self._set_phase(GuardPhase.STOPPING, why, now)
            self._send_stop(why, now)
        elif self.phase is GuardPhase.STOPPED and self.powered:
            self.restops += 1  # powered again behind the guard
            self._set_phase(GuardPhase.STOPPING, why, now)
            self._send_stop(f"powered behind the guard ({why})", now)

    def _watch_stop(self, now: int) -> None:
        """A stop is confirmed by feedback showing the device powerless after it; else STUCK."""
        if self.phase not in (GuardPhase.STOPPING, GuardPhase.STUCK):
            return
        # feedback older than the stop plus the notice the bound allows may predate its effect
        settled = self.phase_at + self.notice_us()
        heard_since = self.last_feedback_at is not None and self.last_feedback_at > settled
        was_stuck = self.phase is GuardPhase.STUCK
        # a STUCK device is taken as stopped only once it has shown its power stage off for a
        # whole notice: one quiet reply between powered ones (an MIT motor that ignores exit
        # but shows little torque for a moment) would book it STOPPED and stop the uncontained
        # booking, and each time it went STUCK again the booking would restart later
        quiet = self.unpowered_since is not None and (
            not was_stuck or now - self.unpowered_since >= self.notice_us()
        )
        if heard_since and self.powered is False and quiet:
            self.charge(now)  # what a STUCK device may have drawn until now, as uncontained
            self.stuck = None
            self._set_phase(GuardPhase.STOPPED, self.stop_reason, now)
            if was_stuck and self.clock.until == now:  # no longer at the STUCK rate
                self.clock.fw = self.in_force_fw(now)
            return
        if now >= self.last_stop_at + self.config.retry_us:
            self._send_stop("not stopped yet: again", now)
        if self.phase is GuardPhase.STOPPING and now > self.phase_at + self.config.stop_timeout_us:
            self.stuck = self._stuck_why(heard_since)
            self.charge(now)
            self.phase = GuardPhase.STUCK  # keeps phase_at: the stop's time
            if self.config.stuck_limits is not None:  # it did not obey since the notice
                since = max(0, now - self.phase_at - self.notice_us())
                fw = self._fw(self.config.stuck_limits)
                self.uncontained_uj += ceil_div(fw * since, FW_US_PER_UJ)
            self._recharge(now)

    def _stuck_why(self, heard_since: bool) -> str:
        """Why a stop is not confirmed by its timeout: feedback showed the device powered, none
        came, or all that came fell within the notice (which may predate the stop's effect:
        a stop timeout no longer than the notice the guard has measured confirms nothing)."""
        ms = self.config.stop_timeout_us / 1000
        if heard_since:
            return f"still powered {ms:g} ms after the stop"
        heard = self.last_feedback_at is not None and self.last_feedback_at > self.phase_at
        if heard:
            notice = self.notice_us() / 1000
            return f"heard {ms:g} ms after the stop only within its notice ({notice:g} ms)"
        return f"not heard for {ms:g} ms after the stop"

    def _send_stop(self, why: str, now: int) -> None:
        self.commands.append(Stop(why, now))
        self.last_stop_at = now

    def release_uj(self) -> int:
        return self.threshold_uj() + self.config.resume_margin_uj

    def _may_resume(self) -> bool:
        return not self.latched and self.usable > self.release_uj() and self.ready_at is not None

    def _desired(self) -> L | None:
        if not self.sound or self.ready_at is None:
            return None
        if self.phase is GuardPhase.RUNNING:
            return self.config.limits
        return self.profile.closed(self.config.limits)

    def _steer_limits(self, now: int) -> None:
        desired = self._desired()
        target = self.pending if self.pending is not None else self.confirmed
        again = self.rewrite_at is not None and now >= self.rewrite_at
        if desired is None or (desired == target and not again):
            return
        self.rewrite_at = None
        self.charge(now)
        self.pending, self.pending_at = desired, now
        self._recharge(now)
        why = "open" if desired == self.config.limits else "closed"
        self.commands.append(WriteLimits(desired, why, now))

    def _set_phase(self, phase: GuardPhase, why: str | None, now: int) -> None:
        self.phase, self.stop_reason, self.phase_at = phase, why, now

    def _after_exit_fw(self) -> int:
        """What the device may run at once the host is gone: the full limits, or what a STUCK
        device is charged at where that is more (an MIT motor's last command, no longer
        re-clamped, may ask up to the model's whole range as it moves)."""
        return max(self._fw(self.config.limits), self._fw(self.config.stuck_limits))

    def status(self, now: int) -> dict[str, Any]:
        """The same fields as a CiA 402 drive's where they mean the same, and the profile's."""
        target = self.pending if self.pending is not None else self.confirmed
        worst = self.bound(self.config.limits)
        now_bound = self.bound(target)
        bound_uj = (
            None
            if worst is None
            else max(worst.total_uj, self.bound_max_uj, self._foreign_bound_uj())
        )
        envelope = self.profile.envelope(target if target is not None else self.config.limits)
        full = self.profile.envelope(self.config.limits)
        return {
            "node": self.node,
            "profile": self.profile.name,
            "drive_state": self.device_state,
            "guard": self.phase.value,
            "stop_reason": self.stop_reason,
            "stuck": self.stuck,
            "refused": self.refused,
            "latched": self.latched,
            "alive": self.alive(now),
            "joining": self.joining,
            "ready": self.ready_at is not None,
            **self.books_status(),
            "meter": self.metering.value,
            "guarantee": PER_STRETCH if self.sound else self.metering.guarantee,
            "stretches": self.stretches() if self.sound else None,
            "metered_uj": self.metered_uj,
            "uncontained_uj": self.uncontained_uj,
            "bound_uj": bound_uj,
            "bound_now_uj": None if now_bound is None else now_bound.total_uj,
            "bound_stop_uj": None if worst is None else worst.stop_uj,
            "envelope_w": round(self.in_force_fw(now) / 1e15, 3) if self.sound else None,
            "envelope_full_w": round(full.fw / 1e15, 3) if self.sound else None,
            "envelope_formula": full.formula if self.sound else None,
            "envelope_parts": full.parts if self.sound else None,
            "envelope_now_parts": envelope.parts if self.sound else None,
            "limits": None if target is None else self.profile.fields(target),
            "limits_confirmed": self.pending is None and self.foreign is None,
            "limits_verified": self.verified,
            "foreign_limits": None if self.foreign is None else self.profile.fields(self.foreign),
            "bound_timings_us": {
                "reaction": self.reaction_us(),
                "latency": max(self.config.latency_us, self.latency_max_us),
                "intake": self.intake_max_us,
                "stop_timeout": self.config.stop_timeout_us,
            },
            "stop_at_uj": self.threshold_uj(),
            "overrun_uj": self.overrun_uj,
            "debt_uj": self.debt_uj,
            "stops": self.stops,
            "restops": self.restops,
            "writes_seen": self.writes_seen,
            "unverified": self.unverified,
            "feedback_age_us": None
            if self.last_feedback_at is None
            else now - self.last_feedback_at,
            "watchdog": None
            if self.watchdog is None
            else self.watchdog.status(self._after_exit_fw() if self.sound else None, now),
        }
