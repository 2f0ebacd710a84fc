"""Bus flags exactly as python-can's own tools take them, and opening the bus with clear errors."""

from __future__ import annotations

import argparse
from typing import Any

import can
import can.cli

from canergy.cli_args import bounded_int, id_base
from canergy.codec import DEFAULT_ID_BASE, ID_MASK


class BusOpenError(RuntimeError):
    """The bus could not be opened; the message says what to fix."""


def add_bus_flags(parser: argparse.ArgumentParser, *, id_base_flag: bool = True) -> None:
    """``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``, ``--fd``, ``--data-bitrate``,
    ``--timing``, ``--bus-kwargs`` (python-can's ``can.cli``), plus canergy's ``--id-base``
    (not for a program that sends no canergy frames: ``id_base_flag=False``)."""
    can.cli.add_bus_arguments(parser)
    for action in parser._actions:  # python-can takes any int: bound them like canergy's numbers
        if action.dest in ("bitrate", "data_bitrate"):
            action.type = bounded_int(1, 20_000_000)
    if not id_base_flag:
        return
    parser.add_argument(
        "--id-base",
        type=id_base,
        default=DEFAULT_ID_BASE,
        help=f"29-bit identifier block of canergy frames, low 12 bits clear "
        f"(default 0x{DEFAULT_ID_BASE:08X}; mask 0x{ID_MASK:08X})",
    )


def open_bus(args: argparse.Namespace, filters: list[dict[str, Any]]) -> can.BusABC:
    """Open the bus the flags describe, with ``filters`` as hardware acceptance filters."""
    try:
        return can.cli.create_bus_from_namespace(args, can_filters=filters)
    except argparse.ArgumentError as exc:
        cause = exc.__cause__ or exc
        hint = ""
        given = getattr(args, "interface", None)
        if given is None and isinstance(cause, can.CanInterfaceNotImplementedError):
            hint = " (give -i/--interface, e.g. socketcan, pcan, kvaser, slcan, virtual)"
        raise BusOpenError(f"cannot open the CAN bus: {cause}{hint}") from cause
