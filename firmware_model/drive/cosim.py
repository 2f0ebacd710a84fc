"""A guarded drive in virtual time: canergy's supervisor, guard and loop against ``DriveModel``.

Everything runs on one integer clock, so a run is exact and repeatable: the supervisor service
and ``GuardedSupervisor`` exactly as ``canergy supervisor --cia402`` runs them, with the CAN
links replaced by delays: TPDO values reach the guard every ``pdo_period_us`` (late by a jitter,
or lost, as the scenario says), a command (controlword or limits) reaches the drive
``reaction_us`` after the guard decided it, and the host's heartbeats reach the drive's consumer.
The application writes the drive's objects at the instants the scenario gives (``app``), e.g.
target velocity between two TPDOs; the host can pause (its loop, receive stamps and link worker
all stop). In ``counter`` mode the counter is the drive's 0x2011 (µJ, 32 bits) or a power-meter
node's 16-bit mJ counter (``counter_on="meter"``) sampled on the same schedule.

``python -m firmware_model.drive.cosim`` prints the table of BENCHMARKS.md: per metering mode
and TPDO period, what the drive drew past its grant against the bound the guard showed.
"""

from __future__ import annotations

import argparse
import contextlib
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

from canergy.cia402.counter import COUNTER_KEY, CounterConfig
from canergy.cia402.envelope import Limits, Ratings, StopKind
from canergy.cia402.guard import (
    STATUSWORD_KEY,
    Command,
    DriveGuard,
    GuardConfig,
    LimitsCommand,
    VerifyCommand,
)
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.cia402.metering import DriveSetup
from canergy.core import Timing
from canergy.live.canopen.cia402_host import HostBeat
from canergy.live.canopen.cia402_link import enable_step, power_state
from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, build_supervisor
from canergy.live.supervisor.policy import Limits as GrantLimits
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import ServiceConfig
from canergy.units import UJ_PER_J
from firmware_model.drive.model import DriveAbort, DriveModel
from firmware_model.drive.motor import LoadTorque, MotorParams

NODE = 10
HOST = 127
STEP_US = 500
ENERGY_OBJECT = 0x2011
"""The emulated drive's energy counter (µJ, 32 bits)."""
FIFTEEN_WATTS = Limits(265, 265, 100_500)
"""0.1325 N·m, 1.325 A, 100.5 rad/s: a 15.07 W envelope with the emulator's motor (R = 1 Ω),
just above what accelerating to 100 rad/s at 1,000 rad/s² against 0.02 N·m needs (14.7 W)."""

Write = tuple[int, int, int]
"""An application's SDO/RPDO write: (time µs, index, value)."""
ENABLE = ((0x6040, 0x06), (0x6040, 0x07), (0x6040, 0x0F))


@dataclass(frozen=True, slots=True)
class Scenario:
    meter: MeterKind = MeterKind.ENVELOPE
    limits: Limits | None = FIFTEEN_WATTS
    counter_on: str = "drive"
    """``drive`` (0x2011) or ``meter`` (a power-meter node's 16-bit mJ counter)."""
    stop: StopKind = StopKind.DISABLE
    pdo_period_us: int = 20_000
    pdo_timeout_us: int | None = None
    """The guard's gap allowance (None: the period plus 5 ms)."""
    pdo_jitter_us: tuple[int, ...] = (0,)
    """Each TPDO reaches the host this much late (cycled; arrivals stay in order)."""
    pdo_lost: frozenset[int] = frozenset()
    """TPDOs (by number from 0) that never arrive."""
    reaction_us: int = 2_000
    """From the guard's decision to its command taking effect on the drive."""
    budget_uj: int = 2 * UJ_PER_J
    """The supervisor's whole budget (all of it may go to the drive)."""
    max_grant_uj: int = 500_000
    target_uj: int | None = None
    """Top the drive up to this level (None: one grant of ``budget_uj`` at most per grant)."""
    reserve_uj: int = 0
    velocity: int = 100_000
    """Target velocity, 0.001 rad/s."""
    acceleration: int = 1_000_000
    quick_stop_deceleration: int = 2_000_000
    stop_timeout_us: int = 100_000
    load_nm: float = 0.02
    inertia: float | None = None
    """Rotor and load inertia, kg·m² (None: the motor's own)."""
    initial_rad_s: float = 0.0
    """The rotor already turning at the start (a flywheel)."""
    duration_us: int = 3_000_000
    app: tuple[Write, ...] = ()
    """The application's writes (target velocity, torque, mode, controlword) at their times."""
    pauses: tuple[tuple[int, int], ...] = ()
    """Host pauses: (start µs, length µs)."""
    auto_enable: bool = True
    fault_at_us: int | None = None
    host_crash_at_us: int | None = None
    consumer_timeout_ms: int = 200
    heartbeat_us: int = 50_000
    drop_stops: bool = False
    """Lose every stop command and every write that lowers the limits (a broken link)."""
    unanswered_limits: int = 0
    """The first limits writes whose answer never comes (another master garbled it on the
    drive's shared SDO server); every other one of them took effect all the same."""
    meter_config: MeterConfig | None = None
    """Sampled modes: how to compute power (None: mechanical with the motor's R)."""


@dataclass
class Result:
    drawn_uj: int
    granted_uj: int
    metered_uj: int
    overrun_uj: int
    debt_uj: int
    bound_uj: int | None
    """The guard's bound at its full limits, as its status showed it at the end."""
    tail_uj: int | None
    """Drawn from the last TPDO sampled before the guard found the budget exhausted to the end:
    what the bound bounds (None: the budget never ran out)."""
    peak_power_w: float
    states: list[str] = field(default_factory=list)
    timeline: list[tuple[int, int, int, str]] = field(default_factory=list)
    """Every 50 ms: time, energy granted so far, the proxy's budget, the drive's state."""
    guard: dict[str, Any] = field(default_factory=dict)
    supervisor: dict[str, Any] = field(default_factory=dict)
    """The supervisor's status at the end (its books, the guard's under ``cia402``)."""
    drive: dict[str, Any] = field(default_factory=dict)

    @property
    def overshoot_uj(self) -> int:
        return max(0, self.drawn_uj - self.granted_uj)


class _Link:
    """Stands for ``DriveLink``: samples in, commands out after the reaction time."""

    def __init__(self, setup: DriveSetup) -> None:
        self.samples: deque[tuple[int, dict[int, int], str | None, int]] = deque()
        self.limit_answers: deque[tuple[Limits, bool | None, str]] = deque()
        self.limits_writes = 0
        self.ready_at: int | None = 0
        self.setup: DriveSetup | None = setup
        self.pending_commands: deque[Command | LimitsCommand | VerifyCommand] = deque()
        self.verified: deque[tuple[int, dict[tuple[int, int], int | None]]] = deque()
        self.reaction_max_us = 0
        self.latency_max_us = 0

    def drain(self) -> list[tuple[int, dict[int, int], str | None, int]]:
        out = list(self.samples)
        self.samples.clear()
        return out

    def drain_limits(self) -> list[tuple[Limits, bool | None, str]]:
        out = list(self.limit_answers)
        self.limit_answers.clear()
        return out

    def drain_writes(self) -> list[Any]:
        return []  # nobody else writes to the drive here

    def drain_verified(self) -> list[tuple[int, dict[tuple[int, int], int | None]]]:
        out = list(self.verified)
        self.verified.clear()
        return out

    def pending(self) -> bool:
        return bool(self.samples or self.limit_answers or self.verified)

    def command(self, cmd: Command | LimitsCommand | VerifyCommand) -> None:
        self.pending_commands.append(cmd)

    def close(self) -> None:
        pass

    def status(self) -> dict[str, Any]:
        return {"pending_commands": len(self.pending_commands)}


@dataclass(frozen=True)
class _Drives:
    """The one drive and its simulated link, as the builder takes guarded CiA 402 drives."""

    guard: DriveGuard
    link: _Link
    beat: HostBeat
    nodes: tuple[int, ...] = (NODE,)

    def open(
        self, network: Any, now: int, clock: Any
    ) -> tuple[dict[int, tuple[Any, Any]], HostBeat, None]:
        return {NODE: (self.guard, self.link)}, self.beat, None


class _Bus:
    def __init__(self) -> None:
        self.frames: list[Any] = []

    def send(self, frame: Any, timeout: float | None = None) -> None:
        self.frames.append(frame)


def _drive(sc: Scenario) -> DriveModel:
    params = MotorParams() if sc.inertia is None else MotorParams(inertia=sc.inertia)
    load = LoadTorque.constant(sc.load_nm, opposing=True)
    drive = DriveModel(NODE, 0, params=params, load=load)
    drive.motor.omega = sc.initial_rad_s
    drive.set_nmt("OPERATIONAL", 0)
    drive.write(0x1016, 1, HOST << 16 | sc.consumer_timeout_ms, 0)
    drive.write(0x6060, 0, 3, 0)
    drive.write(0x6083, 0, sc.acceleration, 0)
    drive.write(0x6085, 0, sc.quick_stop_deceleration, 0)
    drive.write(0x60FF, 0, sc.velocity, 0)
    return drive


def _write_limits(drive: DriveModel, limits: Limits, t: int) -> None:
    for index, value in limits.as_objects().items():
        drive.write(index, 0, value, t)


def _guard_config(sc: Scenario, drive: DriveModel, timing: Timing) -> GuardConfig:
    params = drive.motor.params
    sampled = sc.meter_config or MeterConfig(
        kind=sc.meter if sc.meter.sampled else MeterKind.SAMPLED_MECHANICAL,
        resistance_mohm=round(params.resistance * 1000),
    )
    counter = None
    if sc.meter is MeterKind.COUNTER:
        counter = (
            CounterConfig(ENERGY_OBJECT)
            if sc.counter_on == "drive"
            else CounterConfig(0x2100, node=20, bits=16, unit_uj=1000)
        )
    return GuardConfig(
        meter=replace(sampled, kind=sc.meter),
        limits=None if sc.meter.sampled else sc.limits,
        counter=counter,
        stop=sc.stop,
        timing=timing,
        pdo_timeout_us=sc.pdo_timeout_us or sc.pdo_period_us + 5_000,
        stop_timeout_us=sc.stop_timeout_us,
        reaction_us=sc.reaction_us + STEP_US,
        latency_us=STEP_US,
        reserve_uj=sc.reserve_uj,
        auto_enable=sc.auto_enable,
    )


def _counter_values(sc: Scenario, drive: DriveModel) -> dict[int, int]:
    if sc.meter is not MeterKind.COUNTER:
        return {}
    if sc.counter_on == "drive":
        return {COUNTER_KEY: drive.drawn_uj % 2**32}
    return {COUNTER_KEY: drive.drawn_uj // 1000 % 2**16}


def _setup(sc: Scenario, drive: DriveModel, config: GuardConfig) -> DriveSetup:
    params = drive.motor.params
    closed = None if config.limits is None else config.limits.closed()
    if closed is not None:
        _write_limits(drive, closed, 0)
    ratings = Ratings(
        drive.read(0x6076),
        drive.read(0x6075),
        resistance_mohm=round(params.resistance * 1000),
    )
    return DriveSetup(ratings, drive.read(0x6085), STEP_US, closed)


def run(sc: Scenario) -> Result:
    drive = _drive(sc)
    timing = Timing(response_timeout_us=20_000, retries=3)
    config = _guard_config(sc, drive, timing)
    guard = DriveGuard(NODE, config, 0, nonce=0x1234)
    link, bus = _Link(_setup(sc, drive, config)), _Bus()
    built = build_supervisor(
        SupervisorConfig(
            core=CoreConfig((NODE,), sc.budget_uj, timing=timing),
            service=ServiceConfig(
                policy=TopUp(sc.target_uj) if sc.target_uj is not None else TopUp(sc.budget_uj),
                limits=GrantLimits(max_grant=sc.max_grant_uj),
                fsync=False,
                status_period_us=10**12,
                local_nodes=frozenset({NODE}),
            ),
            cia402=_Drives(guard, link, HostBeat(HOST, sc.heartbeat_us)),
        ),
        heartbeat_bus=bus,
        clock=lambda: 0,
    )
    service, host = built.service, built.handler
    app = sorted(sc.app)
    in_flight: deque[tuple[int, dict[int, int], str | None, int, int]] = deque()
    seen_drawn, decided_drawn = 0, None
    states: list[str] = []
    timeline: list[tuple[int, int, int, str]] = []
    pdo_number, last_arrival = 0, 0
    for t in range(0, sc.duration_us + 1, STEP_US):
        drive.advance(t)
        while app and app[0][0] <= t:
            _, index, value = app.pop(0)
            with contextlib.suppress(DriveAbort):  # refused: the application's problem
                drive.write(index, 0, value, t)
        if sc.fault_at_us is not None and t == sc.fault_at_us:
            drive.fault("injected fault", 0x5000, t)
        if not states or states[-1] != drive.state:
            states.append(drive.state)
        if t % 50_000 == 0:
            b = service.ledger.books()[NODE]
            timeline.append((t, b["delivered_uj"] - b["returned_uj"], guard.usable, drive.state))
        if t % sc.pdo_period_us == 0:
            if pdo_number not in sc.pdo_lost:
                values = drive.tpdo_values() | _counter_values(sc, drive)
                jitter = sc.pdo_jitter_us[pdo_number % len(sc.pdo_jitter_us)]
                last_arrival = max(last_arrival, t + jitter)
                sampled = power_state(values[0x6041])
                in_flight.append((last_arrival, values, sampled, drive.drawn_uj, t))
            pdo_number += 1
        if sc.host_crash_at_us is not None and t >= sc.host_crash_at_us:
            continue
        if any(start <= t < start + length for start, length in sc.pauses):
            continue  # the whole host process stands still
        while in_flight and in_flight[0][0] <= t:
            arrival, carried, shown, seen_drawn, sampled_at = in_flight.popleft()
            taken = max(arrival, t - STEP_US)
            link.samples.append((taken, carried, shown, taken - sampled_at))
        _apply_commands(sc, drive, link, t)
        wakeup = host.next_wakeup()
        if wakeup is not None and wakeup <= t:
            host.on_wakeup(t)
            if decided_drawn is None and guard.stop_reason == "budget exhausted":
                decided_drawn = seen_drawn
        for _frame in bus.frames:
            drive.host_heartbeat(HOST, t)
        bus.frames.clear()
    books = service.ledger.books()[NODE]
    status = guard.status(sc.duration_us)
    return Result(
        drawn_uj=drive.drawn_uj,
        granted_uj=books["delivered_uj"] - books["returned_uj"],
        metered_uj=status["metered_uj"],
        overrun_uj=guard.overrun_uj,
        debt_uj=guard.debt_uj,
        bound_uj=status["bound_uj"],
        tail_uj=None if decided_drawn is None else drive.drawn_uj - decided_drawn,
        peak_power_w=drive.peak_power_w,
        states=states,
        timeline=timeline,
        guard=status,
        supervisor=service.status(),
        drive=drive.status(),
    )


def _apply_commands(sc: Scenario, drive: DriveModel, link: _Link, t: int) -> None:
    """Commands whose reaction time is up reach the drive; limits are read back."""
    while link.pending_commands and t >= link.pending_commands[0].at + sc.reaction_us:
        cmd = link.pending_commands.popleft()
        link.reaction_max_us = max(link.reaction_max_us, t - cmd.at - sc.reaction_us)
        if isinstance(cmd, VerifyCommand):
            keys = [*cmd.keys, STATUSWORD_KEY, *((i, 0) for i in (0x6072, 0x6073, 0x6080))]
            link.verified.append((cmd.seq, {k: drive.read(*k) for k in keys}))
            continue
        if isinstance(cmd, LimitsCommand):
            lowering = cmd.limits.torque_permille < drive.read(0x6072)
            link.limits_writes += 1
            if link.limits_writes <= sc.unanswered_limits:
                if link.limits_writes % 2:
                    _write_limits(drive, cmd.limits, t)
                link.limit_answers.append((cmd.limits, None, "no SDO response received"))
            elif not (sc.drop_stops and lowering):
                _write_limits(drive, cmd.limits, t)
                link.limit_answers.append((cmd.limits, True, ""))
            continue
        controlword = cmd.controlword
        if controlword is None:
            controlword = enable_step(power_state(drive.read(0x6041)))
        elif sc.drop_stops:
            continue
        if controlword is not None:
            drive.write(0x6040, 0, controlword, t)


MODES = (
    ("counter", MeterKind.COUNTER, StopKind.DISABLE),
    ("counter, quick stop", MeterKind.COUNTER, StopKind.QUICK),
    ("envelope", MeterKind.ENVELOPE, StopKind.DISABLE),
    ("envelope, quick stop", MeterKind.ENVELOPE, StopKind.QUICK),
    ("sampled-mechanical", MeterKind.SAMPLED_MECHANICAL, StopKind.QUICK),
)


def table(periods_ms: tuple[int, ...] = (5, 10, 20, 50)) -> list[dict[str, Any]]:
    """Each mode at each TPDO period: the plain velocity profile (3 s), and ``pulsing``'s 10 s of
    pulses timed between TPDOs."""
    rows = []
    for name, kind, stop in MODES:
        for ms in periods_ms:
            period = ms * 1000
            steady = Scenario(meter=kind, stop=stop, pdo_period_us=period)
            for profile, sc in (("steady", steady), ("pulses", pulsing(steady))):
                r = run(sc)
                rows.append(
                    {
                        "mode": name,
                        "pdo_period_ms": ms,
                        "profile": profile,
                        "granted_j": r.granted_uj / 1e6,
                        "drawn_j": r.drawn_uj / 1e6,
                        "overshoot_mj": r.overshoot_uj / 1e3,
                        "tail_mj": None if r.tail_uj is None else r.tail_uj / 1e3,
                        "bound_mj": None if r.bound_uj is None else r.bound_uj / 1e3,
                    }
                )
    return rows


def pulsing(sc: Scenario, offset_us: int = 1_000) -> Scenario:
    """``sc`` with the issue's application: target 100 rad/s just after each TPDO and 0 at
    mid-period, 10,000 rad/s² both ways (0x6083, 0x6084), for 10 s."""
    ramps = ((0, 0x6084, 10_000_000),)
    app = (*ramps, *pulses(sc.pdo_period_us, 10_000_000, offset_us=offset_us))
    return replace(sc, velocity=0, acceleration=10_000_000, app=app, duration_us=10_000_000)


def pulses(
    period_us: int, until_us: int, high: int = 100_000, offset_us: int = 1_000
) -> tuple[Write, ...]:
    """Target velocity ``high`` just after each TPDO, back to 0 at mid-period."""
    out: list[Write] = []
    for start in range(0, until_us, period_us):
        out += [(start + offset_us, 0x60FF, high), (start + period_us // 2, 0x60FF, 0)]
    return tuple(out)


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    print("| mode | TPDO period | profile | granted | drawn | overshoot | after decision | bound |")
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    for row in table():
        tail = "-" if row["tail_mj"] is None else f"{row['tail_mj']:.1f} mJ"
        bound = "none" if row["bound_mj"] is None else f"{row['bound_mj']:.1f} mJ"
        print(
            f"| {row['mode']} | {row['pdo_period_ms']} ms | {row['profile']} | "
            f"{row['granted_j']:.3f} J | {row['drawn_j']:.4f} J | {row['overshoot_mj']:.1f} mJ | "
            f"{tail} | {bound} |"
        )


if __name__ == "__main__":
    main()
