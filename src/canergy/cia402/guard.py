"""One CiA 402 drive under an energy budget: a proxy client, a meter and a stop rule. Sans-IO.

The drive never runs canergy. The host keeps a *proxy*: a real hardened ``Client`` that the
supervisor grants to like any node. Every set of TPDO values is metered (``EnergyMeter``) and
spent from the proxy's budget. When the budget falls to the reserve, or the TPDOs stop, the guard
commands quick stop, and disables the drive once it stands still (or after ``stop_timeout_us``).

A drive cannot be stopped at once: what it draws past its budget is bounded by peak power ×
(PDO period + host reaction + stop time) (``overshoot_bound_uj``); a reserve at least that large
keeps the drive inside what was granted. Energy metered that the budget no longer covered is
counted as ``overrun_uj``: the proxy never spends more than it holds.

The proxy's record is volatile: a restarted host has no books for it, so it JOINs and the
supervisor writes off what it held (the drive was stopped meanwhile by its heartbeat consumer).

Inputs: ``on_values`` (TPDO values with the power state decoded by the caller), ``on_message``
(canergy frames from the supervisor), ``on_wakeup``; outputs: frames to the supervisor, and
controlword commands collected in ``commands`` for the caller to write.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from canergy.cia402.meter import VELOCITY_ACTUAL, EnergyMeter, MeterConfig
from canergy.core import (
    Action,
    Client,
    ClientCommitted,
    Credited,
    Send,
    Timing,
)
from canergy.core.state import Phase
from canergy.messages import LEVEL_MAX_MJ, QUANTUM_UJ, Message, Telemetry, ToClient

CW_QUICK_STOP = 0x0002
CW_DISABLE_VOLTAGE = 0x0000
ENABLED = "OPERATION ENABLED"
QUICK_STOP = "QUICK STOP ACTIVE"
FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")
POWERLESS = ("SWITCH ON DISABLED", "READY TO SWITCH ON", "NOT READY TO SWITCH ON", "FAULT")
"""States in which a drive puts no torque on its motor."""


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
    timing: Timing = field(default_factory=Timing)
    pdo_timeout_us: int = 200_000
    """Quick stop when no TPDO came for this long."""
    stop_timeout_us: int = 1_000_000
    """Disable the drive this long after quick stop even if it still moves."""
    retry_us: int = 100_000
    """Repeat a command the drive's state does not show after this long."""
    reserve_uj: int = 0
    """Quick stop when the budget falls to this; resume above it by ``resume_margin_uj``."""
    resume_margin_uj: int = 10 * QUANTUM_UJ
    standstill: int = 10
    """|velocity actual| at or below this (drive units) counts as standing still."""
    auto_enable: bool = False
    """Bring the drive to OPERATION ENABLED while it holds budget (else the application does)."""
    telemetry_period_us: int = 50_000


@dataclass(frozen=True, slots=True)
class Command:
    """A controlword for the drive: a value, or ``None`` for one step toward OPERATION ENABLED
    (the caller picks it from the drive's current state)."""

    controlword: int | None
    why: str
    at: int


class DriveGuard:
    """The budget of one CiA 402 drive."""

    def __init__(self, node: int, config: GuardConfig, now: int, nonce: int) -> None:
        self.config = config
        self.client = Client(node, timing=config.timing)
        self.meter = EnergyMeter(config.meter)
        self.started_at = now
        self.values: dict[int, int] = {}
        self.state: str | None = None
        """The drive's power state as its statusword last showed it."""
        self.last_values_at: int | None = None
        self.phase = GuardPhase.STOPPED  # nothing granted yet: the drive must not run
        self.phase_at = now
        self.stop_reason: str | None = "no budget yet"
        self.latched = False
        """Stopped for lost TPDOs: never re-enabled by the guard (the application may)."""
        self.commands: list[Command] = []
        self.last_command_at = -config.retry_us
        self.state_at_command: str | None = None
        self.ready_at: int | None = None
        """When the drive was set up (PDOs mapped and started); TPDOs are awaited from then."""
        self.overrun_uj = 0
        self.stops = 0
        self.halted = False
        """The supervisor is stopping: stop the drive and keep it stopped."""
        self.next_telemetry = now
        self.outbox = self._carry_out(self.client.books_lost(nonce, now), now)

    @property
    def node(self) -> int:
        return self.client.node

    @property
    def usable(self) -> int:
        return self.client.state.usable

    @property
    def joining(self) -> bool:
        return self.client.state.phase is Phase.JOINING

    # -- inputs -----------------------------------------------------------------------------
    def on_values(self, now: int, values: dict[int, int], state: str | None) -> list[Message]:
        """TPDO values received at ``now`` (all objects of one TPDO), ``state`` decoded from the
        statusword when the TPDO carried it."""
        self.values.update(values)
        off = self.state in POWERLESS and (state or self.state) in POWERLESS
        if state is not None:
            self.state = state
        self.last_values_at = now
        drawn = self.meter.sample(now, self.values, charge=not off)
        take = min(drawn, self.usable)
        self.overrun_uj += drawn - take
        out = self._carry_out(self.client.spend(take), now) if take else []
        return out + self._evaluate(now)

    def on_message(self, msg: ToClient, now: int) -> list[Message]:
        return self._carry_out(self.client.receive(msg, now), now) + self._evaluate(now)

    def next_wakeup(self) -> int:
        times = [self.next_telemetry]
        if (deadline := self._pdo_deadline()) is not None:
            times.append(deadline + 1)
        if (timer := self.client.get_timer()) is not None:
            times.append(timer)
        if self.phase is not GuardPhase.RUNNING or self._wants_enable():
            times.append(self.last_command_at + self.config.retry_us)
        if self.phase is GuardPhase.STOPPING:
            times.append(self.phase_at + self.config.stop_timeout_us)
        return min(times)

    def on_wakeup(self, now: int) -> list[Message]:
        out, self.outbox = self.outbox, []
        if (timer := self.client.get_timer()) is not None and timer <= now:
            out += self._carry_out(self.client.handle_timer(now), now)
        out += self._evaluate(now)
        if now >= self.next_telemetry:
            out.append(self.telemetry(now))
        return out

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

    def on_ready(self, now: int) -> None:
        """The drive is set up and started: from now on its TPDOs must keep coming."""
        self.ready_at = now

    def _pdo_deadline(self) -> int | None:
        since = self.last_values_at if self.last_values_at is not None else self.ready_at
        return None if since is None else since + self.config.pdo_timeout_us

    def halt(self, now: int) -> None:
        """Stop the drive for good (the supervisor is shutting down)."""
        self.halted = True
        self._evaluate(now)

    def _stop_reason(self, now: int) -> str | None:
        if self.halted:
            return "supervisor stopping"
        deadline = self._pdo_deadline()
        if deadline is not None and now > deadline:
            return "TPDOs stopped"
        if self.usable <= self.config.reserve_uj:
            return "budget exhausted"
        return None

    def _evaluate(self, now: int) -> list[Message]:
        before = self.phase
        why = self._stop_reason(now)
        if why is not None:
            self._stop(why, now)
        elif self.phase is GuardPhase.STOPPED and self._may_resume():
            self._set_phase(GuardPhase.RUNNING, None, now)
        elif self.phase is GuardPhase.STOPPING:
            self._advance_stop(now)  # the cause went away (topped up, TPDOs back): finish first
        if self._wants_enable() and (
            self.state != self.state_at_command
            or now >= self.last_command_at + self.config.retry_us
        ):
            self._command(None, "budget available", now)
        return [self.telemetry(now)] if self.phase is not before else []

    def _stop(self, why: str, now: int) -> None:
        retry_due = now >= self.last_command_at + self.config.retry_us
        self.latched = self.latched or why == "TPDOs stopped"  # in any phase
        if self.phase is GuardPhase.RUNNING or (
            self.phase is GuardPhase.STOPPED and self.state == ENABLED and retry_due
        ):  # the guard's own decision, or the drive enabled again (by the application)
            self.stops += 1
            self._set_phase(GuardPhase.STOPPING, why, now)
            self._command(CW_QUICK_STOP, why, now)
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
            and self.state not in FAULT_STATES
            and self.usable > self.config.reserve_uj + self.config.resume_margin_uj
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

    def _set_phase(self, phase: GuardPhase, why: str | None, now: int) -> None:
        self.phase, self.stop_reason, self.phase_at = phase, why, now

    def _command(self, controlword: int | None, why: str, now: int) -> None:
        self.commands.append(Command(controlword, why, now))
        self.last_command_at, self.state_at_command = now, self.state

    # -- the proxy client -------------------------------------------------------------------
    def telemetry(self, now: int) -> Telemetry:
        self.next_telemetry = now + self.config.telemetry_period_us
        flags = (
            (Telemetry.LOW if self.usable <= self.config.reserve_uj else 0)
            | (Telemetry.HALTED if self.phase is not GuardPhase.RUNNING else 0)
            | (Telemetry.JOINING if self.joining else 0)
        )
        return Telemetry(self.node, min(self.usable // QUANTUM_UJ, LEVEL_MAX_MJ), flags)

    def _carry_out(self, actions: list[Action], now: int) -> list[Message]:
        out: list[Message] = []
        for action in actions:
            if isinstance(action, Send):
                out.append(action.message)
            elif isinstance(action, ClientCommitted | Credited):
                self.next_telemetry = now  # report the new level at the next wakeup
        return out

    def status(self, now: int) -> dict[str, Any]:
        c = self.client.state
        return {
            "node": self.node,
            "drive_state": self.state,
            "guard": self.phase.value,
            "stop_reason": self.stop_reason,
            "latched": self.latched,
            "alive": self.alive(now),
            "joining": self.joining,
            "usable_uj": c.usable,
            "spent_uj": c.spent,
            "credited_uj": c.credited,
            "return_seq": c.return_seq,
            "return_pending_uj": c.return_pending,
            "metered_uj": self.meter.metered_uj,
            "overrun_uj": self.overrun_uj,
            "regenerated_uj": self.meter.regen_uj,
            "peak_power_w": round(self.meter.peak_fw / 1e15, 3),
            "samples": self.meter.samples,
            "stops": self.stops,
            "tpdo_age_us": None if self.last_values_at is None else now - self.last_values_at,
        }
