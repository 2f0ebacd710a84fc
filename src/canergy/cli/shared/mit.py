"""``--mit-model`` (and ``--mit-resistance``): one value for every MIT-mode motor, or one per
motor id, as ``canergy inline``, ``canergy supervisor --mit`` and ``dump``, ``decode``,
``audit`` and ``monitor`` (``--mit-names``) take them: ``DM4310``, or ``1:AK80-9,2:DM4310``
(``[IDS:]VALUE``, the way ``--cia402-counter`` names a node, ``NODE:INDEX``); and the gates'
flags ``canergy inline`` and ``canergy supervisor --mit`` share (``add_gate_flags``,
``mit_motors``)."""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from fractions import Fraction
from typing import Any

import can

from canergy.argtypes import PER_ID_SYNTAX, PerId, _shown, add_duration, duration, node_ids, per_id
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.cli.shared.cia402 import _number
from canergy.codec import Codec
from canergy.core import Timing
from canergy.devices.bus_ids import Ids, canopen_ids, collision, mit_ids, moteus_ids, odrive_ids
from canergy.devices.mit import MODELS, MitModel, default_master, reply_collision
from canergy.live.devices.mit_host import MitMotors
from canergy.live.devices.mit_motor import MitMotor

EXAMPLE = "1:AK80-9,2:DM4310"


def model_name(text: str) -> str:
    """A model of ``canergy.devices.mit.MODELS``, by name."""
    if text not in MODELS:
        raise argparse.ArgumentTypeError(
            f"unknown model {_shown(text)}: one of {', '.join(sorted(MODELS))} "
            f"({PER_ID_SYNTAX}, e.g. {EXAMPLE})"
        )
    return text


models_type = per_id(model_name, 1, 127, EXAMPLE)
resistances_type = per_id(_number("ohms", 1000, zero=False), 1, 127, "1:0.2,2:0.85")


def add_model_flag(
    group: argparse._ArgumentGroup, what: str, required: bool = False
) -> argparse.Action:
    return group.add_argument(
        "--mit-model",
        type=models_type,
        required=required,
        metavar="[IDS:]MODEL,...",
        help=f"{what}: one of {', '.join(sorted(MODELS))} for all, or per motor id, e.g. "
        f"{EXAMPLE} (a plain model is for the ids not named)",
    )


def add_resistance_flag(group: argparse._ArgumentGroup) -> argparse.Action:
    return group.add_argument(
        "--mit-resistance",
        type=resistances_type,
        metavar="[IDS:]OHMS,...",
        help="phase resistance: needed where the model table has none (CubeMars AK); per "
        "motor id (1:0.2) where the motors are of more than one model",
    )


def models_of(spec: PerId[str], ids: Iterable[int], ids_flag: str) -> dict[int, MitModel]:
    """The model of each of ``ids``; ``ValueError`` naming the flag for an id named that
    ``ids_flag`` does not list, or an id left without a model."""
    wanted = tuple(ids)
    names = spec.resolve(wanted, "--mit-model", ids_flag)
    for i in wanted:
        if i not in names:
            raise ValueError(
                f"--mit-model: no model for motor {i} (give {i}:MODEL, or a plain MODEL for "
                "the ids not named)"
            )
    return {i: MODELS[names[i]] for i in wanted}


def resistances_of(
    spec: PerId[Fraction] | None, models: dict[int, MitModel], ids_flag: str
) -> dict[int, Fraction]:
    """The phase resistance given for each motor (the table's where none is given is left
    out); ``ValueError`` naming the flag where a plain value would cover motors of different
    models, or a model without a table figure has none."""
    given: dict[int, Fraction] = {}
    if spec is not None:
        if spec.default is not None and len({m.name for m in models.values()}) > 1:
            raise ValueError(
                "--mit-resistance: the motors are of more than one model: give it per motor "
                "id (e.g. 1:0.2), not one figure for all"
            )
        given = spec.resolve(models, "--mit-resistance", ids_flag)
    for i, model in models.items():
        if model.resistance is None and i not in given:
            raise ValueError(
                f"--mit-model {model.name} (motor {i}): give --mit-resistance (no table figure)"
            )
    return given


def add_gate_flags(g: argparse._ArgumentGroup, model_required: bool) -> None:
    """The model and the gates' caps and times, after the group's ``--mit`` (its ids)."""
    add_model_flag(g, "the motors' model", required=model_required)
    g.add_argument(
        "--mit-max-torque",
        type=_number("N·m", 1000, zero=False),
        metavar="NM",
        help="the torque cap while the budget lasts (default: the model's torque range)",
    )
    g.add_argument(
        "--mit-max-power",
        type=_number("W", 100_000, zero=False),
        metavar="W",
        help="instead of --mit-max-torque: the largest cap whose envelope is within it",
    )
    g.add_argument(
        "--mit-max-speed",
        type=_number("rad/s", 10_000, zero=False),
        metavar="RAD_S",
        help="the velocity set point's cap (default: the model's velocity range)",
    )
    add_resistance_flag(g)
    add_duration(g, "--mit-hold", 20_000, "the command in force is clamped again this often")
    add_duration(g, "--mit-feedback-timeout", 300_000, "stop a motor not heard this long")
    g.add_argument(
        "--mit-max-watchdog",
        type=duration,
        metavar="TIME",
        help="Damiao: read each motor's CAN Timeout register (RID 9) at set-up and every "
        "second; off, longer than TIME or unanswered refuses the motor for good (default: not "
        "read, the status says so)",
    )
    add_duration(
        g,
        "--mit-stop-timeout",
        500_000,
        "a motor still showing torque this long after a stop is STUCK",
    )


def guard_config(args: argparse.Namespace) -> dict[str, Any]:
    """The gates' guards' times the flags give."""
    return {
        "feedback_timeout_us": args.mit_feedback_timeout,
        "stop_timeout_us": args.mit_stop_timeout,
        "max_watchdog_us": args.mit_max_watchdog,
    }


def mit_motors(args: argparse.Namespace, nodes: list[int]) -> list[MitMotor]:
    """The motors ``--mit`` and the gate flags describe, each with its proxy's canergy node id
    from ``nodes`` (``ValueError`` naming the flag)."""
    if args.mit_max_torque is not None and args.mit_max_power is not None:
        raise ValueError("--mit-max-torque or --mit-max-power, not both")
    if args.mit_model is None:
        raise ValueError("--mit needs --mit-model (the motors' model)")
    models = models_of(args.mit_model, args.mit, "--mit")
    resistances = resistances_of(args.mit_resistance, models, "--mit")
    if args.mit_hold <= 0:
        raise ValueError("--mit-hold must be more than 0")

    def number(x: Any) -> float | None:
        return None if x is None else float(x)

    replies = {i: default_master(models[i], i) for i in args.mit}
    if (why := reply_collision(replies)) is not None:
        raise ValueError(f"--mit: {why}")
    return [
        MitMotor(
            motor_id,
            node=node,
            model=models[motor_id].name,
            max_torque=number(args.mit_max_torque),
            max_power=number(args.mit_max_power),
            max_speed=number(args.mit_max_speed),
            resistance=number(resistances.get(motor_id)),
            hold_us=args.mit_hold,
        )
        for motor_id, node in zip(args.mit, nodes, strict=True)
    ]


# -- canergy supervisor --mit: the supervisor hosts the gates ------------------------------
APP = "mit-app"
"""The application's bus: ``--mit-app-interface``, ``--mit-app-channel``, ... (as ``canergy
inline``'s ``--app-*``)."""

SIDE_FILTER: dict[str, int | bool] = {"can_id": 0, "can_mask": 0x1FFFF800, "extended": True}
"""Extended frames with ids below 0x800: CubeMars servo-mode frames, seen to refuse a motor."""


def add_supervisor_mit_flags(p: argparse.ArgumentParser) -> None:
    """``--mit IDS``, the gates' flags and the application's bus (``--mit-app-*``)."""
    g = p.add_argument_group(
        "MIT-mode motors",
        "guard MIT-mode motors (CubeMars AK, Damiao DM) in line: the application talks to them "
        "on a bus of its own (--mit-app-interface, --mit-app-channel, ...), the supervisor "
        "forwards each command to the motors on its bus only while the motor's budget lasts, "
        "clamped so that the worst-case torque stays under the cap, or refuses it (both "
        "counted in the status); each motor gets a proxy client under its own id, and exits "
        "motor mode when its budget runs out; other frames cross both ways unchanged",
    )
    g.add_argument(
        "--mit", type=node_ids, metavar="IDS", help="motor CAN ids 1-127 (and proxy node ids)"
    )
    add_gate_flags(g, model_required=False)
    add_bus_flags(p, id_base_flag=False, prefix=APP)


def check_mit(args: argparse.Namespace) -> None:
    """Everything about the motors that can be judged before a bus is opened."""
    motors = args.mit or ()
    if not motors:
        if args.mit_model is not None or getattr(args, "mit-app_channel", None) is not None:
            raise ValueError("--mit-model and --mit-app-* are for --mit IDS")
        return
    if args.mit_model is not None:  # else refused below, naming the flag
        mine = mit_ids(
            (m, model, None) for m, model in models_of(args.mit_model, motors, "--mit").items()
        )
        for other in other_ids(args):
            if (why := collision(mine, other)) is not None:
                raise ValueError(f"{why}: guard them on two buses, or give other ids")
    if clash := sorted(set(motors) & set(args.nodes or ())):
        raise ValueError(
            f"--mit {','.join(map(str, clash))}: also in --nodes (a motor's proxy takes its id)"
        )
    if args.listen_only:
        raise ValueError("--mit guards motors and must send: not with --listen-only")
    app = (getattr(args, "mit-app_interface", None), getattr(args, "mit-app_channel", None))
    if app[1] is None:
        raise ValueError(
            "--mit needs the application's bus: --mit-app-channel (and --mit-app-interface)"
        )
    own = (getattr(args, "interface", None), getattr(args, "channel", None))
    if (own[1] == app[1] and None in (own[0], app[0])) or own == app:
        raise ValueError("-c and --mit-app-channel name the same bus: give the application its own")
    mit_motors(args, list(motors))


def other_ids(args: argparse.Namespace) -> list[Ids]:
    """The identifiers of the other groups the supervisor guards or serves on its bus."""
    out: list[Ids] = []
    if args.odrive:
        out.append(odrive_ids(args.odrive))
    if args.moteus:
        out.append(moteus_ids(args.moteus, args.moteus_source, args.moteus_prefix))
    if args.cia402:
        counter = getattr(args, "cia402_counter", None)  # a power-meter node, if any
        meter = () if counter is None or counter[0] is None else (counter[0],)
        out.append(canopen_ids("--cia402", (*args.cia402, *meter), args.cia402_host_id))
    if args.canopen:
        out.append(canopen_ids("--canopen", args.nodes or ()))
    return out


def mit_group(args: argparse.Namespace, timing: Timing) -> MitMotors:
    """The ``--mit*`` flags as the builder takes them (``MitMotors``)."""

    def open_app() -> can.BusABC:
        return open_bus(args, [], prefix=APP)

    others = other_ids(args)

    def theirs(extended: bool, arbitration_id: int) -> str | None:
        for ids in others:
            if (what := ids.reads(extended, arbitration_id)) is not None:
                return f"{what} ({ids.name})"
        return None

    return MitMotors(
        tuple(mit_motors(args, list(args.mit))),
        open_app,
        timing,
        guard_config(args),
        Codec(args.id_base),
        theirs if others else None,
    )
