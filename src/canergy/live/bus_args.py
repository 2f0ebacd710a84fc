"""Bus flags exactly as python-can's own tools take them, and opening the bus with clear errors."""

from __future__ import annotations

import argparse
from typing import Any

import can
import can.cli

from canergy.argtypes import bounded_int, id_base
from canergy.codec import DEFAULT_ID_BASE, ID_MASK


class BusOpenError(RuntimeError):
    """The bus could not be opened; the message says what to fix."""


def add_bus_flags(
    parser: argparse.ArgumentParser, *, id_base_flag: bool = True, prefix: str | None = None
) -> None:
    """``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``, ``--fd``, ``--data-bitrate``,
    ``--timing``, ``--bus-kwargs`` (python-can's ``can.cli``), plus canergy's ``--id-base``
    (not for a program that sends no canergy frames: ``id_base_flag=False``). ``prefix``: a
    second bus, as python-can names it: ``--<prefix>-interface`` ... ``--<prefix>-id-base``."""
    can.cli.add_bus_arguments(parser, prefix=prefix)
    dest = f"{prefix}_" if prefix else ""
    for action in parser._actions:  # python-can takes any int: bound them like canergy's numbers
        if action.dest in (f"{dest}bitrate", f"{dest}data_bitrate"):
            action.type = bounded_int(1, 20_000_000)
    if not id_base_flag:
        return
    parser.add_argument(
        f"--{prefix}-id-base" if prefix else "--id-base",
        type=id_base,
        default=DEFAULT_ID_BASE,
        help=f"29-bit identifier block of canergy frames, low 12 bits clear "
        f"(default 0x{DEFAULT_ID_BASE:08X}; mask 0x{ID_MASK:08X})",
    )


def open_bus(
    args: argparse.Namespace, filters: list[dict[str, Any]], *, prefix: str | None = None
) -> can.BusABC:
    """Open the bus the flags describe, with ``filters`` as hardware acceptance filters."""
    try:
        return can.cli.create_bus_from_namespace(args, prefix=prefix, can_filters=filters)
    except argparse.ArgumentError as exc:
        cause = exc.__cause__ or exc
        hint = ""
        given = getattr(args, f"{prefix}_interface" if prefix else "interface", None)
        flag = f"--{prefix}-interface" if prefix else "-i/--interface"
        if given is None and isinstance(cause, can.CanInterfaceNotImplementedError):
            hint = f" (give {flag}, e.g. socketcan, pcan, kvaser, slcan, virtual)"
        which = f"the {prefix} CAN bus" if prefix else "the CAN bus"
        raise BusOpenError(f"cannot open {which}: {cause}{hint}") from cause


def open_bus_at(
    args: argparse.Namespace,
    interface: str,
    channel: str,
    filters: list[dict[str, Any]],
    name: str,
) -> can.BusABC:
    """Open ``interface``/``channel`` (one ``--bus``, called ``name``) with the other bus flags
    of ``args``: bit rates, ``--fd``, ``--timing``, ``--bus-kwargs``."""
    one = argparse.Namespace(**{**vars(args), "interface": interface, "channel": channel})
    try:
        return open_bus(one, filters)
    except BusOpenError as exc:
        raise BusOpenError(f"--bus {name}: {exc}") from exc.__cause__
