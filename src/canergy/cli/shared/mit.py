"""``--mit-model`` (and ``--mit-resistance``): one value for every MIT-mode motor, or one per
motor id, as ``canergy inline`` and ``dump``, ``decode``, ``audit`` and ``monitor``
(``--mit-names``) take them: ``DM4310``, or ``1:AK80-9,2:DM4310`` (``[IDS:]VALUE``, the way
``--cia402-counter`` names a node, ``NODE:INDEX``)."""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from fractions import Fraction

from canergy.argtypes import PER_ID_SYNTAX, PerId, _shown, per_id
from canergy.cli.shared.cia402 import _number
from canergy.devices.mit import MODELS, MitModel

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
