"""Bus flags exactly as python-can's own tools take them, and opening the bus with clear errors."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import can
import can.cli

from canergy.argtypes import bounded_int, id_base
from canergy.codec import DEFAULT_ID_BASE, ID_MASK
from canergy.errors import BusOpenError


def add_bus_flags(
    parser: argparse.ArgumentParser,
    *,
    id_base_flag: bool = True,
    prefix: str | None = None,
    fd_default: bool = False,
) -> None:
    """``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``, ``--fd``, ``--data-bitrate``,
    ``--timing``, ``--bus-kwargs`` (python-can's ``can.cli``), plus canergy's ``--id-base``
    (not for a program that sends no canergy frames: ``id_base_flag=False``). ``prefix``: a
    second bus, as python-can names it: ``--<prefix>-interface`` ... ``--<prefix>-id-base``.
    ``fd_default``: a command that opens its bus with ``open_receiving_bus`` (FD on anyway)."""
    can.cli.add_bus_arguments(parser, prefix=prefix)
    dest = f"{prefix}_" if prefix else ""
    for action in parser._actions:  # python-can takes any int: bound them like canergy's numbers
        if action.dest in (f"{dest}bitrate", f"{dest}data_bitrate"):
            action.type = bounded_int(1, 20_000_000)
        if fd_default and action.dest == f"{dest}fd":
            action.help = (
                "CAN FD is on here without it, where the interface supports FD (kept for "
                "python-can's tools' command lines: changes nothing)"
            )
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


def open_receiving_bus(args: argparse.Namespace, filters: list[dict[str, Any]]) -> can.BusABC:
    """Open the bus for a command that only receives (``dump``, ``monitor``) with CAN FD on, so
    that FD frames are seen without ``--fd`` (which changes nothing then). An interface that
    will not open for FD is opened for classic CAN, with one line on stderr saying so; one that
    opens neither way is the classic attempt's ``BusOpenError``, as without FD."""
    fd = argparse.Namespace(**{**vars(args), "fd": True})
    try:
        return open_bus(fd, filters)
    except BusOpenError as exc:
        if isinstance(exc.__cause__, can.CanInterfaceNotImplementedError):
            raise  # no such interface here (or its package is missing): FD has nothing to do
        refused = exc.__cause__ or exc
    classic = argparse.Namespace(**{k: v for k, v in vars(args).items() if k != "fd"})
    bus = open_bus(classic, filters)
    where = " ".join(x for x in reversed(bus_where(args)) if x) or "the bus"
    command = getattr(args, "command", None) or "canergy"
    print(
        f"canergy {command}: {where} did not open for CAN FD ({refused}); opened for classic "
        "CAN: FD frames will not be seen (most interfaces need --data-bitrate or --timing for "
        "FD: see python-can's page on the interface)",
        file=sys.stderr,
    )
    return bus


def bus_where(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """(channel, interface) of the bus the flags open, as python-can resolves them (a flag not
    given comes from its configuration: ``~/.canrc``, ``CAN_INTERFACE``...); None: unknown."""
    given = {k: getattr(args, k) for k in ("interface", "channel") if getattr(args, k, None)}
    try:
        config: dict[str, Any] = dict(can.util.load_config(config=given))
    except Exception:  # no configuration to resolve from: what was given
        config = given
    channel, interface = config.get("channel"), config.get("interface")
    return (
        None if channel is None else str(channel),
        None if interface is None else str(interface),
    )


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


def bus_argv(args: argparse.Namespace, *, id_base: bool = True) -> list[str]:
    """The bus flags of ``args`` as a command line for another program taking the same flags."""
    if getattr(args, "interface", None) == "virtual":
        raise ValueError(
            "-i virtual: python-can's virtual bus does not cross processes; run `canergy bench` "
            "without bus flags for the in-process bench"
        )
    if getattr(args, "timing", None) is not None:
        raise ValueError("--timing is not passed on to the node processes: give -b/--data-bitrate")
    out = []
    for flag, name in (("-i", "interface"), ("-c", "channel"), ("-b", "bitrate")):
        if (value := getattr(args, name, None)) is not None:
            out += [flag, str(value)]
    if getattr(args, "fd", False):
        out.append("--fd")
    if (data_bitrate := getattr(args, "data_bitrate", None)) is not None:
        out += ["--data-bitrate", str(data_bitrate)]
    if kwargs := getattr(args, "bus_kwargs", None):
        out += ["--bus-kwargs", *(f"{k}={v}" for k, v in kwargs.items())]
    if id_base:
        out += ["--id-base", f"0x{args.id_base:08X}"]
    return out
