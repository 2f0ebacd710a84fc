"""candump-style lines with the decoded message after them, coloured per transaction on a TTY."""

from __future__ import annotations

from datetime import datetime

from canergy.inspect.frames import Described
from canergy.messages import QUANTUM_UJ, Direction

_COLOURS = ["\033[36m", "\033[33m", "\033[35m", "\033[32m", "\033[34m", "\033[91m"]
_RESET = "\033[0m"
RAW_WIDTH = 62
"""The candump part with an absolute timestamp is padded to this width: the decoded part
starts in one column."""
_STAMP_WIDTH = len("(1700000000.123456)  ")
STAMP_MODES = ("a", "d", "z", "A")


class Stamps:
    """candump's ``-t`` timestamps: ``a`` absolute ``(1700000000.123456)``, ``d`` since the
    previous frame, ``z`` since the first one, ``A`` absolute local date and time
    ``(2026-11-27 03:30:00.123456)``. Fed the frames shown, in order."""

    def __init__(self, mode: str) -> None:
        if mode not in STAMP_MODES:
            raise ValueError(f"timestamp mode {mode!r}: one of {', '.join(STAMP_MODES)}")
        self.mode = mode
        self.first: int | None = None
        self.last: int | None = None

    def text(self, timestamp: float | None) -> str | None:
        """The stamp of a frame shown; None for the line's usual absolute one (mode ``a``, or
        a frame without a time)."""
        if timestamp is None or self.mode == "a":
            return None
        micros = round(timestamp * 1_000_000)
        if self.mode == "A":
            seconds, micro = divmod(micros, 1_000_000)
            try:
                when = datetime.fromtimestamp(seconds)
            except (OverflowError, OSError, ValueError):  # not a time of day: as mode a
                return None
            return f"({when:%Y-%m-%d %H:%M:%S}.{micro:06d})"
        if self.first is None:
            self.first = micros
        since = self.last if self.mode == "d" and self.last is not None else self.first
        self.last = micros
        seconds, micro = divmod(max(micros - since, 0), 1_000_000)
        return f"({seconds:03d}.{micro:06d})"


def raw_part(d: Described, stamp: str | None = None) -> str:
    """The candump part: ``(timestamp)  channel  ID   [dlc]  bytes``; ``stamp`` instead of the
    absolute timestamp (``Stamps``)."""
    if stamp is None:
        stamp = f"({d.timestamp:.6f})" if d.timestamp is not None else ""
    stamp = f"{stamp}  " if stamp else ""
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
    if m is None and d.other is not None:
        return d.other.text()
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


def line(d: Described, *, colour: bool, stamp: str | None = None) -> str:
    """The frame's line; ``stamp``: a ``Stamps`` text instead of the absolute timestamp (the
    decoded part moves by the difference in width, the same for every line of one mode)."""
    width = RAW_WIDTH if stamp is None else RAW_WIDTH - _STAMP_WIDTH + len(stamp) + 2
    text = f"{raw_part(d, stamp):<{width}}  {decoded_part(d)}".rstrip()
    key = d.transaction
    if not colour or key is None:
        return text
    node, kind, number = key
    shade = (node * 7 + number * 3 + (kind == "return")) % len(_COLOURS)
    return f"{_COLOURS[shade]}{text}{_RESET}"
