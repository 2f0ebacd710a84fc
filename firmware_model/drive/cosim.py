"""A guarded drive in virtual time: canergy's supervisor, guard and loop against ``DriveModel``.

Everything runs on one integer clock, so a run is exact and repeatable: the supervisor service
and ``GuardedSupervisor`` exactly as ``canergy supervisor --cia402`` runs them, with the CAN
links replaced by delays: TPDO values reach the guard every ``pdo_period_us``, a controlword
reaches the drive ``reaction_us`` after the guard decided it, and the host's heartbeats reach the
drive's consumer. The application sets profile velocity and a target; the guard enables the drive
while it holds budget (``auto_enable``) and stops it when the budget runs out.

``python -m firmware_model.drive.cosim`` prints the overshoot table of the README.
"""

from __future__ import annotations

import argparse
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from canergy.cia402.guard import POWERLESS, QUICK_STOP, Command, DriveGuard, GuardConfig
from canergy.cia402.meter import MeterConfig, overshoot_bound_uj
from canergy.core import Supervisor, Timing
from canergy.live.cia402_host import GuardedSupervisor, HostBeat
from canergy.live.cia402_link import enable_step, power_state
from canergy.live.policy import Limits, TopUp
from canergy.live.service import ServiceConfig, SupervisorService
from canergy.units import UJ_PER_J
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque

NODE = 10
HOST = 127
STEP_US = 500


@dataclass(frozen=True, slots=True)
class Scenario:
    pdo_period_us: int = 10_000
    reaction_us: int = 2_000
    """Host reaction plus transmission: from a TPDO's arrival to its controlword taking effect."""
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
    load_nm: float = 0.02
    duration_us: int = 3_000_000
    pdo_loss_at_us: int | None = None
    pdo_back_at_us: int | None = None
    auto_enable: bool = True
    app_enables_at_us: int | None = None
    """The application enables the drive itself at this time (shutdown, switch on, enable)."""
    fault_at_us: int | None = None
    host_crash_at_us: int | None = None
    consumer_timeout_ms: int = 200
    drop_stops: bool = False
    """Lose every quick stop and disable on the way (a broken link: tests that the checks fail)."""


@dataclass
class Result:
    drawn_uj: int
    granted_uj: int
    metered_uj: int
    overrun_uj: int
    peak_power_w: float
    stop_us: int | None
    """From the first stop command reaching the drive to the drive putting out no more power."""
    tail_uj: int | None
    """Drawn from the TPDO that showed the budget gone to the end: what the stop itself cost."""
    bound_uj: int
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

    def __init__(self, meter: MeterConfig) -> None:
        self.samples: deque[tuple[int, dict[int, int], str | None]] = deque()
        self.ready_at: int | None = 0
        self.meter: MeterConfig | None = meter
        self.pending: deque[Command] = deque()
        self.reaction_max_us = 0

    def drain(self) -> list[tuple[int, dict[int, int], str | None]]:
        out = list(self.samples)
        self.samples.clear()
        return out

    def command(self, cmd: Command) -> None:
        self.pending.append(cmd)

    def close(self) -> None:
        pass

    def status(self) -> dict[str, Any]:
        return {"pending_commands": len(self.pending)}


class _Bus:
    def __init__(self) -> None:
        self.frames: list[Any] = []

    def send(self, frame: Any, timeout: float | None = None) -> None:
        self.frames.append(frame)


def run(sc: Scenario) -> Result:
    drive = DriveModel(NODE, 0, load=LoadTorque.constant(sc.load_nm, opposing=True))
    drive.set_nmt("OPERATIONAL", 0)
    drive.write(0x1016, 1, HOST << 16 | sc.consumer_timeout_ms, 0)
    drive.write(0x6060, 0, 3, 0)
    drive.write(0x6083, 0, sc.acceleration, 0)
    drive.write(0x6085, 0, sc.quick_stop_deceleration, 0)
    drive.write(0x60FF, 0, sc.velocity, 0)
    params = drive.motor.params
    meter = MeterConfig(
        rated_torque_mnm=drive.read(0x6076),
        rated_current_ma=drive.read(0x6075),
        resistance_mohm=round(params.resistance * 1000),
    )
    timing = Timing(response_timeout_us=20_000, retries=3)
    service = SupervisorService(
        Supervisor((NODE,), sc.budget_uj, timing=timing),
        ServiceConfig(
            policy=TopUp(sc.target_uj) if sc.target_uj is not None else TopUp(sc.budget_uj),
            limits=Limits(max_grant=sc.max_grant_uj),
            fsync=False,
            status_period_us=10**12,
        ),
        0,
    )
    guard_config = GuardConfig(
        meter=meter,
        timing=timing,
        pdo_timeout_us=max(5 * sc.pdo_period_us, 50_000),
        reserve_uj=sc.reserve_uj,
        auto_enable=sc.auto_enable,
    )
    guard = DriveGuard(NODE, guard_config, 0, nonce=0x1234)
    link, bus = _Link(meter), _Bus()
    drives: dict[int, Any] = {NODE: (guard, link)}
    host = GuardedSupervisor(service, drives, bus, HostBeat(HOST, 50_000), 0)  # type: ignore[arg-type]
    stop_sent_at: int | None = None
    stop_us: int | None = None
    decided_drawn: int | None = None
    states: list[str] = []
    timeline: list[tuple[int, int, int, str]] = []
    next_pdo = 0
    for t in range(0, sc.duration_us + 1, STEP_US):
        drive.advance(t)
        if sc.fault_at_us is not None and t == sc.fault_at_us:
            drive.fault("injected fault", 0x5000, t)
        if not states or states[-1] != drive.state:
            states.append(drive.state)
        if t % 50_000 == 0:
            b = service.books()[NODE]
            timeline.append((t, b["delivered_uj"] - b["returned_uj"], guard.usable, drive.state))
        crashed = sc.host_crash_at_us is not None and t >= sc.host_crash_at_us
        if crashed:
            continue
        if sc.app_enables_at_us is not None and t == sc.app_enables_at_us:
            for step in (0x06, 0x07, 0x0F):
                drive.write(0x6040, 0, step, t)
        back = sc.pdo_back_at_us is not None and t >= sc.pdo_back_at_us
        lost = sc.pdo_loss_at_us is not None and t >= sc.pdo_loss_at_us and not back
        if t >= next_pdo:
            next_pdo += sc.pdo_period_us
            if not lost:
                values = drive.tpdo_values()
                link.samples.append((t, values, power_state(values[0x6041])))
        while link.pending and t >= link.pending[0].at + sc.reaction_us:
            cmd = link.pending.popleft()
            controlword = cmd.controlword
            if controlword is None:
                controlword = enable_step(power_state(drive.read(0x6041)))
            elif stop_sent_at is None and drive.state == "OPERATION ENABLED":
                stop_sent_at = t  # the first stop of a running drive
            if controlword is not None and not (sc.drop_stops and cmd.controlword is not None):
                drive.write(0x6040, 0, controlword, t)
        if stop_sent_at is not None and stop_us is None and _powerless(drive):
            stop_us = t - stop_sent_at
        wakeup = host.next_wakeup()
        if wakeup is not None and wakeup <= t:
            host.on_wakeup(t)
            if decided_drawn is None and any(c.why == "budget exhausted" for c in link.pending):
                decided_drawn = drive.drawn_uj if drive.state == "OPERATION ENABLED" else None
        for _frame in bus.frames:
            drive.host_heartbeat(HOST, t)
        bus.frames.clear()
    books = service.books()[NODE]
    granted = books["delivered_uj"] - books["returned_uj"]
    bound = overshoot_bound_uj(
        round(drive.peak_power_w * 1e6),
        sc.pdo_period_us,
        sc.reaction_us + STEP_US,
        stop_us if stop_us is not None else sc.duration_us,
    )
    return Result(
        drawn_uj=drive.drawn_uj,
        granted_uj=granted,
        metered_uj=guard.meter.metered_uj,
        overrun_uj=guard.overrun_uj,
        peak_power_w=drive.peak_power_w,
        stop_us=stop_us,
        tail_uj=None if decided_drawn is None else drive.drawn_uj - decided_drawn,
        bound_uj=bound,
        states=states,
        timeline=timeline,
        guard=guard.status(sc.duration_us),
        supervisor=service.status(),
        drive=drive.status(),
    )


def _powerless(drive: DriveModel) -> bool:
    standing = abs(drive.velocity_rad_s) < 0.01
    return drive.state in POWERLESS or (drive.state == QUICK_STOP and standing)


def table(periods_ms: tuple[int, ...] = (1, 5, 10, 20, 50)) -> list[dict[str, Any]]:
    rows = []
    for ms in periods_ms:
        r = run(Scenario(pdo_period_us=ms * 1000))
        rows.append(
            {
                "pdo_period_ms": ms,
                "granted_j": r.granted_uj / 1e6,
                "drawn_j": r.drawn_uj / 1e6,
                "overshoot_mj": r.overshoot_uj / 1e3,
                "tail_mj": None if r.tail_uj is None else r.tail_uj / 1e3,
                "bound_mj": r.bound_uj / 1e3,
                "peak_power_w": round(r.peak_power_w, 2),
                "stop_ms": None if r.stop_us is None else r.stop_us / 1e3,
            }
        )
    return rows


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    print("| TPDO period | granted | drawn | overshoot | drawn after the stop decision | bound |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in table():
        print(
            f"| {row['pdo_period_ms']} ms | {row['granted_j']:.3f} J | {row['drawn_j']:.4f} J | "
            f"{row['overshoot_mj']:.1f} mJ | {row['tail_mj']:.1f} mJ | {row['bound_mj']:.1f} mJ |"
        )
    print(f"peak power {row['peak_power_w']} W, stop time {row['stop_ms']} ms (last row)")


if __name__ == "__main__":
    main()
