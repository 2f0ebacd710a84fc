"""``canergy supervisor --bus``: several buses, each given as ``[NAME=]INTERFACE:CHANNEL:NODES``
(the argparse type and the check that each bus is given once, under a name of its own)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import can

from canergy.argtypes import node_ids
from canergy.live.supervisor.multi_bus import BusSpec

BUS_SYNTAX = "[NAME=]INTERFACE:CHANNEL:NODES"


def bus_spec(text: str) -> BusSpec:
    """argparse type of ``--bus``: ``[NAME=]INTERFACE:CHANNEL:NODES``, e.g.
    ``socketcan:can1:1-40`` or ``left=pcan:PCAN_USBBUS1:1-5,9``. The channel may hold ':' (the
    first field is the interface, the last the nodes); a name is what precedes a '=' before the
    first ':'."""
    shown = repr(text[:40]) + ("..." if len(text) > 40 else "")
    head, eq, rest = text.partition("=")
    name, body = (head, rest) if eq and ":" not in head else ("", text)
    interface, sep, tail = body.partition(":")
    channel, last, nodes = tail.rpartition(":")
    if not (sep and last and interface and channel and nodes):
        raise argparse.ArgumentTypeError(
            f"{shown}: expected {BUS_SYNTAX}, e.g. socketcan:can1:1-40 or left=socketcan:can0:1-5,9"
        )
    if eq and ":" not in head and not name:
        raise argparse.ArgumentTypeError(f"{shown}: the name before '=' is empty")
    if interface not in can.VALID_INTERFACES:
        raise argparse.ArgumentTypeError(
            f"{shown}: unknown interface {interface[:24]!r} (one of "
            f"{', '.join(sorted(can.VALID_INTERFACES))})"
        )
    return BusSpec(name or channel, interface, channel, node_ids(nodes))


def check_buses(specs: Sequence[BusSpec]) -> None:
    """Every bus once, under a name of its own (``ValueError`` otherwise)."""
    for i, spec in enumerate(specs):
        for other in specs[:i]:
            if (spec.interface, spec.channel) == (other.interface, other.channel):
                raise ValueError(
                    f"--bus {spec.interface}:{spec.channel} is given twice; give each bus once "
                    "with all its nodes"
                )
            if spec.name == other.name:
                raise ValueError(
                    f"two buses are named {spec.name!r}; name them apart: "
                    f"--bus NAME={spec.interface}:{spec.channel}:NODES"
                )
