"""Which CAN identifiers each guarded group uses on one bus, and where two groups collide. Sans-IO.

MIT-mode motors share a bus with ODrive axes, moteus controllers or CANopen (CiA 402 drives,
``--canopen`` nodes) unless a frame one group sends in normal operation is one another group
reads as its own: a guard would then take it for a write behind its back, or a device for a
command. ``Ids`` holds a group's ``sends`` (by identifier, what the frame is) and ``reads`` (how
the group reads a frame, None where it ignores it); ``collision`` finds the first identifier one
sends and the other reads, named on both sides.

- MIT motor ``m``: sends its command ``m`` and its reply ``master``; reads those and the frames
  that reach it outside MIT mode (``canergy.devices.mit.side_channel``);
- ODrive axis ``n``: all 32 CAN Simple commands ``n << 5 | cmd``, both ways;
- CANopen node ``n`` (a CiA 402 drive, or a ``--canopen`` node): NMT ``0x000``, SYNC ``0x080``,
  its EMCY, PDOs, SDOs and heartbeat (``0x080`` to ``0x700`` + ``n``), and the host's heartbeat;
- moteus controller ``k`` (source ``s``, prefix ``p``): ``p << 16 | s << 8 | k`` (bit 15 asks a
  reply) and its replies ``k << 8 | s``; it reads every frame of its prefix to ``k`` or to all
  (0x7F), or from ``k``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from canergy.devices import moteus
from canergy.devices.mit import MitModel, default_master, side_channel
from canergy.devices.odrive import Cmd, split_id

Key = tuple[bool, int]
"""(extended, identifier)."""


@dataclass(frozen=True, slots=True)
class Ids:
    name: str
    """The flag, e.g. ``--mit``."""
    sends: dict[Key, str]
    reads: Callable[[bool, int], str | None]


def shown(key: Key) -> str:
    extended, arbitration_id = key
    return f"0x{arbitration_id:08X}" if extended else f"0x{arbitration_id:03X}"


def collision(a: Ids, b: Ids) -> str | None:
    """The first identifier one of ``a`` and ``b`` sends and the other reads, in words."""
    for x, y in ((a, b), (b, a)):
        for key in sorted(x.sends):
            if (theirs := y.reads(*key)) is not None:
                return (
                    f"{x.name} and {y.name} on one bus: {shown(key)} is {x.sends[key]}, which "
                    f"{y.name} reads as {theirs}"
                )
    return None


def mit_ids(motors: Iterable[tuple[int, MitModel, int | None]]) -> Ids:
    """Motors ``(id, model, replies' identifier or None for the model's default)``."""
    sends: dict[Key, str] = {}
    table: list[tuple[int, MitModel, int]] = []
    for motor_id, model, master in motors:
        reply = default_master(model, motor_id) if master is None else master
        table.append((motor_id, model, reply))
        sends[(False, motor_id)] = f"MIT motor {motor_id}'s command"
        sends.setdefault((False, reply), f"MIT motor {motor_id}'s reply")

    def reads(extended: bool, arbitration_id: int) -> str | None:
        if not extended and (what := sends.get((False, arbitration_id))) is not None:
            return what
        for motor_id, model, _ in table:
            if (why := side_channel(model, motor_id, arbitration_id, extended)) is not None:
                return f"a {why} to MIT motor {motor_id}"
        return None

    return Ids("--mit", sends, reads)


def odrive_ids(nodes: Iterable[int]) -> Ids:
    axes = set(nodes)
    sends: dict[Key, str] = {}
    for node in sorted(axes):
        for cmd in range(32):
            sends[(False, node << 5 | cmd)] = _odrive(node, cmd)

    def reads(extended: bool, arbitration_id: int) -> str | None:
        node, cmd = split_id(arbitration_id)
        return None if extended or node not in axes else _odrive(node, cmd)

    return Ids("--odrive", sends, reads)


def _odrive(node: int, cmd: int) -> str:
    name = Cmd(cmd).name if cmd in Cmd._value2member_map_ else "command"
    return f"ODrive node {node}'s 0x{cmd:02X} ({name})"


CANOPEN = {
    0x080: "EMCY",
    0x180: "TPDO1",
    0x200: "RPDO1",
    0x280: "TPDO2",
    0x300: "RPDO2",
    0x380: "TPDO3",
    0x400: "RPDO3",
    0x480: "TPDO4",
    0x500: "RPDO4",
    0x580: "SDO response",
    0x600: "SDO request",
    0x700: "heartbeat",
}


def canopen_ids(flag: str, nodes: Iterable[int], host_id: int | None = None) -> Ids:
    """CANopen nodes (and the supervisor's own heartbeat as ``host_id``)."""
    sends: dict[Key, str] = {(False, 0x000): "CANopen NMT", (False, 0x080): "CANopen SYNC"}
    for node in sorted(set(nodes)):
        for base, what in CANOPEN.items():
            sends[(False, base + node)] = f"CANopen node {node}'s {what}"
    if host_id is not None:
        sends[(False, 0x700 + host_id)] = f"the supervisor's CANopen heartbeat ({host_id})"

    def reads(extended: bool, arbitration_id: int) -> str | None:
        return None if extended else sends.get((False, arbitration_id))

    return Ids(flag, sends, reads)


def moteus_ids(nodes: Iterable[int], source: int, prefix: int) -> Ids:
    ids = set(nodes)
    sends: dict[Key, str] = {}
    for k in sorted(ids):
        for arbitration_id, what in (
            (moteus.can_id(source, k, False, prefix), f"to moteus {k}"),
            (moteus.can_id(source, k, True, prefix), f"to moteus {k}, a reply asked"),
            (moteus.can_id(k, source, False, prefix), f"moteus {k}'s reply"),
        ):
            sends[(moteus.extended(arbitration_id), arbitration_id)] = f"a frame {what}"

    def reads(extended: bool, arbitration_id: int) -> str | None:
        s, d, _, p = moteus.split_id(arbitration_id)
        if p != prefix or (p and not extended):
            return None
        for k in sorted(ids):  # as the link reads them (``MoteusLink.on_message_received``)
            if s == k and d != k:
                return f"a frame from moteus {k} (to {d})"
            if d in (k, moteus.BROADCAST) and s != k:
                return f"a frame from {s} to moteus {k}"
        return None

    return Ids("--moteus", sends, reads)
