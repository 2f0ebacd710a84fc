"""candump-style lines with the decoded message after them, coloured per transaction on a TTY."""

from __future__ import annotations

from canergy.inspect.frames import Described
from canergy.messages import QUANTUM_UJ, Direction

_COLOURS = ["\033[36m", "\033[33m", "\033[35m", "\033[32m", "\033[34m", "\033[91m"]
_RESET = "\033[0m"


def raw_part(d: Described) -> str:
    """The candump part: ``(timestamp)  channel  ID   [dlc]  bytes``."""
    stamp = f"({d.timestamp:.6f})  " if d.timestamp is not None else ""
    ident = f"{d.arbitration_id:08X}" if d.extended else f"{d.arbitration_id:03X}"
    if d.error_frame:
        body = "ERRORFRAME"
    elif d.remote:
        body = "remote request"
    else:
        body = " ".join(f"{b:02X}" for b in d.data)
    return f"{stamp}{d.channel or '-':>6}  {ident:>8}   [{len(d.data)}]  {body}"


_MAC = {"ok": "mac ok", "BAD": "MAC BAD", "unverified": "mac ?"}


def decoded_part(d: Described) -> str:
    m = d.message
    if m is None and d.mac is not None:
        return f"{d.problem}  {_MAC[d.mac]}"
    if m is None:
        return f"!! {d.problem}" if d.ours else ""
    arrow = f"S->{m.node}" if m.TYPE.direction is Direction.TO_CLIENT else f"{m.node}->S"
    parts = [f"{m.TYPE.name:<14} {arrow:<7}"]
    for name in m.__slots__:
        if name == "node":
            continue
        value = getattr(m, name)
        if name.endswith("_mj"):
            parts.append(f"{name[:-3]} {value * QUANTUM_UJ / 1e6:.3f} J")
        else:
            parts.append(f"{name} {value}")
    parts.append("crc ok" if d.crc_ok else "CRC BAD")
    if d.mac is not None:
        parts.append(_MAC[d.mac])
    return "  ".join(parts)


def line(d: Described, *, colour: bool) -> str:
    text = f"{raw_part(d):<62}  {decoded_part(d)}".rstrip()
    key = d.transaction
    if not colour or key is None:
        return text
    node, kind, number = key
    shade = (node * 7 + number * 3 + (kind == "return")) % len(_COLOURS)
    return f"{_COLOURS[shade]}{text}{_RESET}"
