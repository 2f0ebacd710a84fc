"""One MIT-mode motor to guard in line (``MitMotor``) and its gate (``gate_for``): what
``MitBus``, ``canergy inline`` and ``canergy supervisor --mit`` are given."""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

from canergy.core import Timing
from canergy.devices.guard import DeviceConfig
from canergy.devices.mit import (
    FW_PER_W,
    MODELS,
    TIMEOUT_RID,
    UNM_PER_NM,
    MitLimits,
    MitModel,
    cap_for_power,
)
from canergy.devices.mit_gate import MitGate
from canergy.devices.watchdog import WatchdogPolicy


@dataclass(frozen=True, slots=True)
class MitMotor:
    """One guarded motor: its CAN id, its proxy's canergy node id, its model, and the cap."""

    motor_id: int
    node: int
    model: str = "DM4310"
    max_torque: float | None = None
    """N·m: the cap while the budget lasts (default: the model's torque range)."""
    max_power: float | None = None
    """W: instead of ``max_torque``, the largest cap whose envelope stays within it."""
    max_speed: float | None = None
    """rad/s: the velocity set point's cap (default: the model's range)."""
    resistance: float | None = None
    """Ω: the phase resistance where the table has none (CubeMars AK)."""
    master_id: int | None = None
    """The replies' identifier (default: 0 for CubeMars, motor_id + 0x10 for Damiao)."""
    hold_us: int = 20_000


def mit_watchdog(model: MitModel, max_us: int | None = None) -> WatchdogPolicy:
    """How the motor's own watchdog is judged: Damiao's ``CAN Timeout`` register, read at
    set-up and every second (``canergy.devices.mit.TIMEOUT_RID``, ``canergy.devices.mit_gate``)
    when ``max_us`` is given (``--mit-max-watchdog``: off, longer or unanswered refuses the
    motor), else not read; CubeMars AK firmware has none."""
    if not model.damiao:
        return WatchdogPolicy(
            kind=f"{model.name}: the firmware has no watchdog (a relay on its supply)",
            read=False,
            exists=False,
        )
    return WatchdogPolicy(
        kind=f"{model.name}: the CAN Timeout register (RID {TIMEOUT_RID})",
        read=max_us is not None,
        max_us=max_us or 0,
        remedy="set its CAN Timeout, or leave out --mit-max-watchdog (then not read)",
        unread="give --mit-max-watchdog to read it",
    )


def gate_for(
    motor: MitMotor, now: int, timing: Timing, config: dict[str, Any] | None = None
) -> MitGate:
    """The gate of ``motor`` (``ValueError`` for an unknown model or a missing figure)."""
    if motor.model not in MODELS:
        raise ValueError(f"unknown MIT model {motor.model!r}: one of {', '.join(sorted(MODELS))}")
    model = MODELS[motor.model]
    r = Fraction(motor.resistance) if motor.resistance is not None else model.resistance
    if r is None:
        raise ValueError(f"{model.name}: no phase resistance in the table; give it (ohms)")
    if motor.max_power is not None:
        torque = cap_for_power(model, round(motor.max_power * FW_PER_W), r)
    elif motor.max_torque is not None:
        torque = min(round(motor.max_torque * UNM_PER_NM), int(model.t_max * UNM_PER_NM))
    else:
        torque = int(model.t_max * UNM_PER_NM)
    speed = motor.max_speed if motor.max_speed is not None else float(model.v_max)
    limits = MitLimits(torque, min(round(speed * UNM_PER_NM), int(model.v_max * UNM_PER_NM)))
    whole = MitLimits(int(model.t_max * UNM_PER_NM), int(model.v_max * UNM_PER_NM))
    # a motor that ignores exit holds its last command, whose stiffness term grows as it moves
    config = dict(config or {})
    config.setdefault("watchdog", mit_watchdog(model, config.pop("max_watchdog_us", None)))
    device = DeviceConfig(limits=limits, timing=timing, stuck_limits=whole, **config)
    nonce = secrets.randbits(16)
    return MitGate(
        motor.motor_id, motor.node, model, device, now, nonce, resistance=r, hold_us=motor.hold_us
    )
