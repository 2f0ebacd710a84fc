"""One CiA 402 drive under an energy budget: a proxy client, a meter and a stop rule. Sans-IO.

The drive never runs canergy. The host keeps a *proxy*: a real hardened ``Client`` that the
supervisor grants to like any node. What the drive may have drawn is charged to the proxy's
budget (``DriveMeter``: a counter, the envelope of the limits the guard writes, or sampled power).
The guard stops the drive while what is left still covers what it may draw before it stands:
in the sound modes the stop comes when the budget falls to the reserve plus the bound
(``envelope.bound``) of the limits in force, so a drive stays inside what it was granted. As the
budget falls the guard tapers the drive's torque and current limits, so the envelope and the bound
shrink with what is left; it closes them (0 torque, 0 current) while the drive is off.

Energy charged that the budget no longer covers is a **debt**: the next grant pays it first
(``debt_uj``; ``overrun_uj`` counts it all). The proxy never spends more than it holds.

The proxy's record is volatile: a restarted host has no books for it, so it JOINs and the
supervisor writes off what it held (the drive was stopped meanwhile by its heartbeat consumer).

Writes by others to what the bound depends on (the profile's ``watches``) are charged at the
drive's reach until the guard has read them back (``VerifyCommand``, checked by the profile's
``verify``); a read-back that differs, or that does not come within the PDO timeout, stops the
drive for good (docs/cia402.md).

Inputs: ``on_ready`` (set-up read from the drive), ``on_values`` (TPDO values with the power state
decoded by the caller), ``on_limits`` (the drive confirmed or refused limits), ``on_write`` (a
frame to the drive from someone else), ``on_verified`` (a read-back), ``on_message`` (canergy
frames from the supervisor), ``on_wakeup``; outputs: frames to the supervisor, and commands
(controlwords, limits, read-backs) collected in ``commands`` for the caller to carry out.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

from canergy.cia402.counter import COUNTER_KEY, CounterConfig
from canergy.cia402.envelope import LEVELS, LIMIT_OBJECTS, Limits, StopKind, bound
from canergy.cia402.meter import VELOCITY_ACTUAL, MeterConfig, MeterKind
from canergy.cia402.metering import Allowances, DriveMeter, DriveSetup
from canergy.cia402.watch import CONTROLWORD, PDO_CONFIG, Key, Write, enables, powerless
from canergy.core import Timing
from canergy.devices.proxy import EXHAUSTED, NO_BUDGET, ProxyBooks
from canergy.messages import QUANTUM_UJ, Message, ToClient

CW_QUICK_STOP = 0x0002
CW_DISABLE_VOLTAGE = 0x0000
ENABLED = "OPERATION ENABLED"
QUICK_STOP = "QUICK STOP ACTIVE"
FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")
POWERLESS = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "NOT READY TO SWITCH ON", "FAULT")
"""States in which a drive puts no torque on its motor."""
TAPER_DOWN, TAPER_UP = 2, 4
"""Lower the limits when what is left falls below 2× their bound; raise them again at 4×."""


class GuardPhase(Enum):
    RUNNING = "running"
    """The drive may run: budget above the reserve and TPDOs fresh."""
    STOPPING = "stopping"
    """Quick stop commanded; disable once standing still."""
    STOPPED = "stopped"
    """Voltage disabled by the guard."""


@dataclass(frozen=True, slots=True)
class GuardConfig:
    meter: MeterConfig
    """The metering mode (``meter.kind``) and, for the sampled modes, how to compute power."""
    limits: Limits | None = None
    """The drive's full limits (counter and envelope modes)."""
    counter: CounterConfig | None = None
    stop: StopKind = StopKind.QUICK
    timing: Timing = field(default_factory=Timing)
    pdo_timeout_us: int = 200_000
    """Stop when no TPDO came for this long: the worst gap the bound allows."""
    stop_timeout_us: int = 1_000_000
    """Disable the drive this long after quick stop even if it still moves."""
    reaction_us: int = 10_000
    """The host reaction the bound allows (raised to what is measured)."""
    latency_us: int = 5_000
    """The drive latency the bound allows (raised to what is measured)."""
    retry_us: int = 100_000
    """Repeat a command the drive's state does not show after this long."""
    reserve_uj: int = 0
    """Kept on top of the bound; with the sampled modes, the whole reserve. A drive whose bound
    at its full limits exceeds a reserve given here is refused."""
    resume_margin_uj: int = 10 * QUANTUM_UJ
    standstill: int = 10
    """|velocity actual| at or below this (drive units) counts as standing still."""
    auto_enable: bool = False
    """Bring the drive to OPERATION ENABLED while it holds budget (else the application does)."""
    telemetry_period_us: int = 50_000
    reread_us: int = 1_000_000
    """Read the configuration back this often (writes the guard cannot see); 0: never."""

    def allowances(self) -> Allowances:
        return Allowances(
            self.pdo_timeout_us, self.reaction_us, self.latency_us, self.stop_timeout_us
        )


@dataclass(frozen=True, slots=True)
class Command:
    """A controlword for the drive: a value, or ``None`` for one step toward OPERATION ENABLED
    (the caller picks it from the drive's current state)."""

    controlword: int | None
    why: str
    at: int
    by_sdo: bool = False
    """Written by SDO even where an RPDO carries the controlword: answered by the drive, and
    not overwritten by the next RPDO of an application that writes it too."""


@dataclass(frozen=True, slots=True)
class LimitsCommand:
    """Write these limits to the drive and read them back (answer with ``on_limits``)."""

    limits: Limits
    why: str
    at: int


@dataclass(frozen=True, slots=True)
class VerifyCommand:
    """Read back ``keys`` (and the limits and the statusword, always): answer with
    ``on_verified`` and this ``seq``."""

    seq: int
    keys: tuple[Key, ...]
    why: str
    at: int


STATUSWORD_KEY = (0x6041, 0)


def pdo_pair(index: int) -> tuple[int, int]:
    """A PDO's communication and mapping objects, from either."""
    comm = index - 0x200 if index & 0x200 else index
    return comm, comm + 0x200


class DriveGuard(ProxyBooks):
    """The budget of one CiA 402 drive."""

    def __init__(self, node: int, config: GuardConfig, now: int, nonce: int) -> None:
        super().__init__(node, config.timing, config.telemetry_period_us, now, nonce)
        self.config = config
        self.metering = DriveMeter(
            config.meter.kind,
            config.meter,
            config.limits,
            config.counter,
            config.stop,
            config.allowances(),
        )
        self.started_at = now
        self.values: dict[int, int] = {}
        self.state: str | None = None
        """The drive's power state as its statusword last showed it."""
        self.last_values_at: int | None = None
        self.last_counter_at: int | None = None
        self.phase = GuardPhase.STOPPED  # nothing granted yet: the drive must not run
        self.phase_at = now
        self.stop_reason: str | None = NO_BUDGET
        self.latched = False
        """Stopped for lost TPDOs or refused limits: never re-enabled by the guard."""
        self.refused: str | None = None
        """Why the drive cannot be guarded as configured (it is kept stopped)."""
        self.commands: list[Command | LimitsCommand | VerifyCommand] = []
        self.last_command_at = -config.retry_us
        self.state_at_command: str | None = None
        self.ready_at: int | None = None
        """When the drive was set up (PDOs mapped and started); TPDOs are awaited from then."""
        self.rewrite_at: int | None = None
        """A limits write went unanswered (the drive's SDO server busy with another master):
        when to write the same limits again (they are charged as if taken meanwhile)."""
        self.level = 0
        """Taper: torque and current at 1/2**level of the full limits."""
        self.stops = 0
        self.halted = False
        """The supervisor is stopping: stop the drive and keep it stopped."""
        self.suspect: str | None = None
        """The first write behind the guard not verified yet."""
        self.suspect_at: int | None = None
        self.scope: set[int] | None = set()
        """The objects to read back (None: everything)."""
        self.seq = 0
        """Bumped at each write seen: a read-back answers the writes seen before it was sent."""
        self.verifying: int | None = None
        self.asked_limits: tuple[Limits | None, ...] = ()
        """The limits written and in force when the read-back in flight was asked: what it may
        still read (the guard's own writes since may be taken in before its answer)."""
        self.controlword_seq = 0
        """``seq`` of the last enabling controlword seen: a read-back older shows nothing."""
        self.config_seq = 0
        """``seq`` of the last write other than a controlword."""
        self.verified_seq = 0
        """Every write up to this ``seq`` was read back as expected (or the drive seen off)."""
        self.next_reread = now + config.reread_us if config.reread_us else None
        self.writes_seen = 0
        self.restops = 0
        self.last_verify_at = now - config.retry_us

    def running(self) -> bool:
        return self.phase is GuardPhase.RUNNING

    # -- inputs -----------------------------------------------------------------------------
    def on_ready(self, now: int, setup: DriveSetup | None = None) -> None:
        """The drive is set up and started: from now on its TPDOs must keep coming. ``setup``:
        what was read from it (ratings, quick stop deceleration, latency, limits written)."""
        self.ready_at = now
        if setup is None:
            return
        self.metering.ready(now, setup)
        worst = self.metering.bound(self.config.limits)
        reserve = self.config.reserve_uj
        if worst is not None and reserve and worst.total_uj > reserve:
            self.refused = (
                f"bound {worst.total_uj / 1e6:.3f} J at the full limits (envelope "
                f"{worst.envelope_fw / 1e15:.2f} W × {self.metering.timings().notice_us / 1e3:g} "
                f"ms, stop {worst.stop_uj / 1e6:.3f} J) exceeds --cia402-reserve "
                f"{reserve / 1e6:.3f} J: lower --cia402-max-torque/--cia402-max-current/"
                "--cia402-max-speed, shorten --cia402-pdo-timeout, use --cia402-stop disable, "
                "or raise the reserve"
            )
            self.latched = True

    def on_values(
        self, now: int, values: dict[int, int], state: str | None, age_us: int = 0
    ) -> list[Message]:
        """TPDO values received at ``now`` (all objects of one TPDO), ``state`` decoded from the
        statusword when the TPDO carried it; ``age_us``: how old they were then (the bound
        grows by the oldest seen: what the drive drew since they were sampled is not in them)."""
        self.metering.age(age_us)
        off = self.state in POWERLESS and (state or self.state) in POWERLESS
        counter = COUNTER_KEY in values
        drive = any(k != COUNTER_KEY for k in values)
        self.values.update(values)
        if state is not None:
            self.state = state
        for seen, last in ((drive, self.last_values_at), (counter, self.last_counter_at)):
            if seen and last is not None:
                self.metering.gap(now - last)
        if drive:
            self.last_values_at = now
        if counter:
            self.last_counter_at = now
        self.metering.sample(now, self.values, off)
        self.values.pop(COUNTER_KEY, None)  # a reading counts once
        return self._settled(now)

    def on_limits(
        self, now: int, limits: Limits, taken: bool | None, detail: str = ""
    ) -> list[Message]:
        """The drive read back ``limits`` (``taken``), refused or changed them (False), or the
        write went unanswered (None: written again after ``retry_us``; until then the drive
        may be working to either)."""
        if taken is None:
            if limits == self.metering.target():
                self.rewrite_at = now + self.config.retry_us
        elif taken:
            self.metering.confirm(now, limits)
        else:
            self.refused = f"limits not taken ({limits.describe()}): {detail}"
            self.latched = True
        self.metering.charge(now)
        return self._settled(now)

    def on_write(self, now: int, write: Write, age_us: int = 0) -> list[Message]:
        """Someone else wrote ``write`` to the drive (seen ``age_us`` before ``now``)."""
        m = self.metering
        if m.setup is None:
            return []  # not set up yet: the set-up reads what it relies on afterwards
        held = self.phase is not GuardPhase.RUNNING or self.latched
        controlword = write.index == CONTROLWORD
        if controlword and not (held and enables(write.value)):
            return []  # the application's to give while the drive may run
        assert m.profile is not None  # set up
        if not controlword and not m.profile.watches(write):
            return []
        self.writes_seen += 1
        self.seq += 1
        if controlword:  # a drive the guard holds stopped is stopped again at once
            self.restops += 1
            self.controlword_seq = self.seq
            stop = CW_QUICK_STOP if self.phase is GuardPhase.STOPPING else CW_DISABLE_VOLTAGE
            why = f"enabled behind the guard ({write.describe()})"
            self.commands.append(Command(stop, why, now, by_sdo=True))
            self.last_command_at, self.state_at_command = now, self.state
            if self.config_seq <= self.verified_seq:  # the limits read back bound it: charged
                return self._settled(now)  # as they are (closed, while held stopped)
        else:
            self.config_seq = self.seq
        off = self.phase is GuardPhase.STOPPED and self.state in POWERLESS
        if controlword or not off:  # a drive held off gets torque only by a controlword
            m.suspect(now, now - age_us)
        if self.suspect is None:
            self.suspect, self.suspect_at = write.describe(), now
        if write.index is None or self.scope is None:
            self.scope = None
        elif write.index in PDO_CONFIG:
            self.scope.update(pdo_pair(write.index))
        else:
            self.scope.add(write.index)
        return self._settled(now)

    def on_verified(self, now: int, seq: int, read: dict[Key, int | None]) -> list[Message]:
        """The link read back what ``VerifyCommand`` ``seq`` asked for (None: not readable)."""
        self.verifying = None
        m = self.metering
        setup = m.setup
        if setup is None:
            return []
        always = [STATUSWORD_KEY, *(() if m.full is None else ((i, 0) for i in LIMIT_OBJECTS))]
        if any(read.get(k) is None for k in (*read, *always)):  # garbled by another master's
            if self.suspect is not None:
                self.last_verify_at = now - self.config.retry_us  # again (until the deadline)
            return self._settled(now)
        problem = None
        assert m.profile is not None
        for limits in (m.target(), m.confirmed, *self.asked_limits):
            problem = m.profile.verify(
                {k: v for k, v in setup.config.items() if k in read}, read, limits
            )
            if problem is None:
                break
        status = read.get(STATUSWORD_KEY)
        torque = status is None or not powerless(status)
        stopped = self.phase is GuardPhase.STOPPED
        what = self.suspect or "a periodic read-back"
        if problem is not None and not self.latched:
            self.refused = f"configuration changed behind the guard ({what}): {problem}"
            self.latched = True
        if problem is not None:
            self.rewrite_at = now  # the guard's limits again (closed), whatever else differs
        if problem is not None and (torque or not stopped):
            m.suspect(now, now)  # charged at the reach until the drive is seen off
            if self.suspect is None:  # a periodic read-back: read again until then
                self.suspect, self.suspect_at, self.seq = what, now, self.seq + 1
        # what was read holds unless the configuration was written since (a controlword
        # changes no limit); a drive seen off stays off whatever was written since but one
        held = problem is None and seq >= self.config_seq
        off = stopped and not torque and seq >= self.controlword_seq
        if not (held or off):
            if seq != self.seq:
                self.last_verify_at = now - self.config.retry_us  # written since: read again
        else:  # the limits as written bound it, or it is off: no charge at the reach
            m.verified(now)
            if seq >= self.config_seq:  # and nothing read back yet is left
                self.suspect, self.suspect_at, self.scope = None, None, set()
                self.verified_seq = max(self.verified_seq, seq)
            else:
                self.last_verify_at = now - self.config.retry_us
        return self._settled(now)

    def on_message(self, msg: ToClient, now: int) -> list[Message]:
        self.metering.charge(now)
        out = self._carry_out(self.client.receive(msg, now), now)
        return out + self._pay_debt(now) + self._settled(now)

    def watch(self, reaction_us: int, latency_us: int) -> None:
        """The longest host reaction and drive latency measured so far (the bound grows)."""
        self.metering.watch(reaction_us, latency_us)

    def next_wakeup(self) -> int:
        times = self._proxy_wakeups()
        if (deadline := self._pdo_deadline()) is not None:
            times.append(deadline + 1)
        if self.phase is not GuardPhase.RUNNING or self._wants_enable():
            times.append(self.last_command_at + self.config.retry_us)
        if self.phase is GuardPhase.STOPPING:
            times.append(self.phase_at + self.config.stop_timeout_us)
        if self.rewrite_at is not None:
            times.append(self.rewrite_at)
        if self.suspect_at is not None:
            times.append(self.suspect_at + self.config.pdo_timeout_us + 1)
            if self.verifying is None:
                times.append(self.last_verify_at + self.config.retry_us)
        if self.next_reread is not None:
            times.append(self.next_reread)
        return min(times)

    def on_wakeup(self, now: int) -> list[Message]:
        out = self._proxy_due(now)
        self.metering.charge(now)
        if self.next_reread is not None and now >= self.next_reread:
            self.next_reread = now + self.config.reread_us
            if self.suspect is None and self.verifying is None and self.ready_at is not None:
                self.scope = None
                self._verify("periodic read-back", now)
        out += self._settled(now)
        if now >= self.next_telemetry:
            out.append(self.telemetry(now))
        return out

    # -- booking ----------------------------------------------------------------------------
    def _settled(self, now: int) -> list[Message]:
        """Spend what was charged, decide, and spend what deciding charged (a limits write
        charges the envelope up to now): no charge is ever left unspent."""
        out = self._book(self.metering.take(), now)
        out += self._evaluate(now)
        return out + self._book(self.metering.take(), now)

    def _book(self, drawn: int, now: int) -> list[Message]:
        return self._spend_drawn(drawn, now)

    # -- decisions --------------------------------------------------------------------------
    def alive(self, now: int) -> bool:
        """Grants make sense: TPDOs fresh and the drive not in fault (a fault freezes the
        budget: nothing granted, nothing returned, until the drive is reset)."""
        deadline = self._pdo_deadline()
        return (
            self.last_values_at is not None
            and deadline is not None
            and now <= deadline
            and self.state not in FAULT_STATES
        )

    def _pdo_deadline(self) -> int | None:
        since = self.last_values_at if self.last_values_at is not None else self.ready_at
        if since is not None and self.metering.kind is MeterKind.COUNTER:
            counter = self.last_counter_at if self.last_counter_at is not None else self.ready_at
            since = min(since, counter if counter is not None else since)
        return None if since is None else since + self.config.pdo_timeout_us

    def halt(self, now: int) -> None:
        """Stop the drive for good (the supervisor is shutting down); what it charged is
        booked at the next input (the last: ``on_exit``)."""
        self.halted = True
        self._evaluate(now)

    def on_exit(self, now: int) -> list[Message]:
        """The host exits, its stop written by ``now`` (``halt``, then the link closed) and the
        TPDOs it heard taken in: charged by the clock up to the drive's latency past ``now``
        (envelope mode, or a write behind the guard not read back yet; a meter or a power
        reading counts what the TPDOs said); a quick stop under way, what it may draw (the
        bound's stop part: no reading will show it); and booked. Nothing charges it after this."""
        m = self.metering
        m.charge(now + m.timings().latency_us)
        if self.phase is GuardPhase.STOPPING:
            stops = [b.stop_uj for lim in (m.confirmed, m.pending) if (b := m.bound(lim))]
            m.owe(max(stops, default=0))
        return self._settled(now)

    def release_uj(self) -> int:
        return self.threshold_uj() + self.config.resume_margin_uj

    def threshold_uj(self) -> int:
        """Stop when the budget falls to this: the reserve, plus in the sound modes the bound
        of the limits in force or being tapered to (whichever is larger)."""
        m = self.metering
        if not m.sound or m.full is None:
            return self.config.reserve_uj
        worst = 0
        reach = m.reach if self.suspect is not None else None
        for limits in (m.confirmed, m.pending, m.full.tapered(self.level), reach):
            b = m.bound(limits)
            worst = max(worst, 0 if b is None else b.total_uj)
        return self.config.reserve_uj + worst

    def _stop_reason(self, now: int) -> str | None:
        if self.halted:
            return "supervisor stopping"
        if self.refused is not None:
            return self.refused
        if self.suspect_at is not None and now > self.suspect_at + self.config.pdo_timeout_us:
            self.refused = f"a write behind the guard ({self.suspect}) not verified in time"
            self.latched = True
            self.rewrite_at = now
            return self.refused
        deadline = self._pdo_deadline()
        if deadline is not None and now > deadline:
            self.metering.gap(now - (deadline - self.config.pdo_timeout_us))
            return "TPDOs stopped"
        if self.usable <= self.threshold_uj():
            return EXHAUSTED if self.suspect is None else f"written: {self.suspect}"
        if self.metering.sound and self.metering.setup is None:
            return "not set up yet"
        return None

    def _evaluate(self, now: int) -> list[Message]:
        before = self.phase
        if self.phase is GuardPhase.STOPPED and self.metering.full is not None:
            # the level what is left covers, also while stopped: a budget below the full
            # limits' bound starts the drive at tapered limits instead of never
            self.level = self._taper(resting=True)
        why = self._stop_reason(now)
        if why is not None:
            self._stop(why, now)
        elif self.phase is GuardPhase.STOPPED and self._may_resume():
            self._set_phase(GuardPhase.RUNNING, None, now)
        if self.phase is GuardPhase.STOPPED:
            self.stop_reason = self.held_back(self.stop_reason, why)
        elif self.phase is GuardPhase.STOPPING:
            self._advance_stop(now)  # the cause went away (topped up, TPDOs back): finish first
        self._steer_limits(now)
        if (
            self.suspect is not None
            and self.verifying is None
            and now >= self.last_verify_at + self.config.retry_us
        ):
            self._verify(self.suspect, now)
        if (
            self._wants_enable()
            and self._limits_open()
            and (
                self.state != self.state_at_command
                or now >= self.last_command_at + self.config.retry_us
            )
        ):
            self._command(None, "budget available", now)
        return [self.telemetry(now)] if self.phase is not before else []

    def _stop(self, why: str, now: int) -> None:
        retry_due = now >= self.last_command_at + self.config.retry_us
        self.latched = self.latched or why == "TPDOs stopped"  # in any phase
        quick = self.config.stop is StopKind.QUICK
        if self.phase is GuardPhase.RUNNING or (
            self.phase is GuardPhase.STOPPED and self.state == ENABLED and retry_due
        ):  # the guard's own decision, or the drive enabled again (by the application)
            self.stops += 1
            if quick:
                self._set_phase(GuardPhase.STOPPING, why, now)
                self._command(CW_QUICK_STOP, why, now)
            else:
                self._set_phase(GuardPhase.STOPPED, why, now)
                self._command(CW_DISABLE_VOLTAGE, why, now)
        elif self.phase is GuardPhase.STOPPING:
            self._advance_stop(now)
        elif self.state is not None and self.state not in POWERLESS and retry_due:
            self._command(CW_DISABLE_VOLTAGE, "still not disabled: again", now)

    def _advance_stop(self, now: int) -> None:
        standing = abs(self.values.get(VELOCITY_ACTUAL, 0)) <= self.config.standstill
        done = self.state in POWERLESS or (self.state == QUICK_STOP and standing)
        if done or now >= self.phase_at + self.config.stop_timeout_us:
            self._set_phase(GuardPhase.STOPPED, self.stop_reason, now)
            self._command(CW_DISABLE_VOLTAGE, "stopped", now)
        elif self.state == ENABLED and now >= self.last_command_at + self.config.retry_us:
            self._command(CW_QUICK_STOP, "quick stop not taken: again", now)

    def _may_resume(self) -> bool:
        return (
            not self.latched
            and self.suspect is None
            and self.state not in FAULT_STATES
            and self.usable > self.release_uj()
        )

    def _wants_enable(self) -> bool:
        return (
            self.config.auto_enable
            and self.phase is GuardPhase.RUNNING
            and not self.latched
            and self.state is not None
            and self.state != ENABLED
            and self.state not in FAULT_STATES
        )

    # -- limits -----------------------------------------------------------------------------
    def _taper(self, resting: bool = False) -> int:
        """The lowest level (most torque) whose bound what is left covers: twice over to go
        down to it, four times to come back up (twice from a stop: nothing to come back to)."""
        m = self.metering
        assert m.full is not None
        left = self.usable - self.config.reserve_uj
        for level in range(LEVELS):
            b = m.bound(m.full.tapered(level))
            factor = TAPER_DOWN if resting or level >= self.level else TAPER_UP
            if b is not None and left >= factor * b.total_uj:
                return level
        return LEVELS - 1

    def _desired_limits(self) -> Limits | None:
        m = self.metering
        if m.full is None or m.setup is None:
            return None
        if self.phase is GuardPhase.STOPPING:
            return m.target()  # a quick stop brakes with what it has
        if self.phase is GuardPhase.STOPPED or self.latched:
            return m.full.closed()
        self.level = self._taper()
        idle = self.state is None or self.state in POWERLESS
        if m.kind is MeterKind.ENVELOPE and idle and not self._wants_enable():
            return m.full.closed()  # an envelope is charged by the clock: closed while off
        return m.full.tapered(self.level)

    def _steer_limits(self, now: int) -> None:
        desired = self._desired_limits()
        again = self.rewrite_at is not None and now >= self.rewrite_at
        if desired is None or (desired == self.metering.target() and not again):
            return
        self.rewrite_at = None
        why = "closed" if desired.torque_permille == 0 else f"level {self.level}"
        self.metering.write(now, desired)
        self.commands.append(LimitsCommand(desired, why, now))

    def _limits_open(self) -> bool:
        m = self.metering
        return m.full is None or (m.confirmed is not None and m.confirmed.torque_permille > 0)

    def _verify(self, why: str, now: int) -> None:
        """Ask the link to read back the scope of the writes seen (the limits and the
        statusword always)."""
        config = self.metering.setup.config if self.metering.setup is not None else {}
        scope = self.scope
        keys = tuple(k for k in config if scope is None or k[0] in scope)
        self.verifying, self.last_verify_at = self.seq, now
        self.asked_limits = (self.metering.target(), self.metering.confirmed)
        self.commands.append(VerifyCommand(self.seq, keys, why, now))

    def _set_phase(self, phase: GuardPhase, why: str | None, now: int) -> None:
        self.phase, self.stop_reason, self.phase_at = phase, why, now

    def _command(self, controlword: int | None, why: str, now: int) -> None:
        self.commands.append(Command(controlword, why, now))
        self.last_command_at, self.state_at_command = now, self.state

    def _unseen_uj(self) -> int | None:
        """What a write the guard cannot see may cost: the reach's bound with the re-read
        period (and the PDO timeout the read-back may take) added to the gap."""
        m = self.metering
        if m.setup is None or m.reach is None or not self.config.reread_us:
            return None
        t = m.timings()
        gap = t.gap_us + self.config.reread_us + self.config.pdo_timeout_us
        assert m.profile is not None
        b = bound(m.profile, m.reach, replace(t, gap_us=gap))
        return b.total_uj

    def status(self, now: int) -> dict[str, Any]:
        return {
            "node": self.node,
            "drive_state": self.state,
            "guard": self.phase.value,
            "stop_reason": self.stop_reason,
            "refused": self.refused,
            "latched": self.latched,
            "alive": self.alive(now),
            "joining": self.joining,
            **self.books_status(),
            **self.metering.status(now),
            "bound_unseen_uj": self._unseen_uj(),
            "stop_at_uj": self.threshold_uj(),
            "taper_level": self.level,
            "overrun_uj": self.overrun_uj,
            "debt_uj": self.debt_uj,
            "stops": self.stops,
            "writes_seen": self.writes_seen,
            "restops": self.restops,
            "unverified": self.suspect,
            "tpdo_age_us": None if self.last_values_at is None else now - self.last_values_at,
        }
