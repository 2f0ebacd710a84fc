"""What others write to a guarded drive, read from the frames on the bus the guard reads. Sans-IO.

Every frame addressed to the drive that the guard did not send is decoded into ``Write``\\ s:
SDO download requests (0x600 + id) from any client, expedited, segmented or block (the value is
known only when expedited; every frame of an open segmented or block download counts as a write
to its object again, so the guard reads back after the last one), RPDOs (by the map read at
set-up) and NMT commands to the drive or to all nodes (a reset puts the whole object dictionary
back to its defaults: an unknown write). ``Watched`` says which writes the bound depends on, and
``check`` compares what the guard reads back with what it expects. Reads (uploads) change nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

from canergy.cia402.envelope import (
    LIMIT_OBJECTS,
    QUICK_STOP_DECELERATION,
    Limits,
    StopKind,
)

SDO_REQUEST = 0x600
NMT = 0x000
CONTROLWORD = 0x6040
MODE_OF_OPERATION = 0x6060
HEARTBEAT_CONSUMER = 0x1016
ABORT_CONNECTION = 0x6007
QUICK_STOP_OPTION = 0x605A
PROFILE_DECELERATION = 0x6084
RATINGS = (0x6075, 0x6076)
RESTORE_DEFAULTS = 0x1011
PDO_CONFIG = range(0x1400, 0x1C00)
RAMPS = (QUICK_STOP_DECELERATION, PROFILE_DECELERATION)
"""A stop ramp may grow steeper (a faster stop draws less), never flatter."""
NMT_HARMLESS = (0x01,)
"""Start remote node: the guard wants its drives OPERATIONAL anyway."""

Key = tuple[int, int]
"""(index, sub-index)."""


@dataclass(frozen=True, slots=True)
class Write:
    """Something written to the drive by someone else. ``index`` None: unknown (a frame of a
    transfer the guard did not see begin, an NMT reset): everything may have changed."""

    index: int | None
    subindex: int = 0
    value: int | None = None
    via: str = "SDO"

    def describe(self) -> str:
        what = "everything" if self.index is None else f"0x{self.index:04X}:{self.subindex}"
        value = "" if self.value is None else f" = {self.value}"
        return f"{what}{value} by {self.via}"


class SdoWatch:
    """Decodes one drive's SDO requests (its 0x600 + id), any client's."""

    def __init__(self) -> None:
        self.open: tuple[int, int, str] | None = None
        """A segmented or block download in progress: its object and how it goes."""

    def frame(self, data: bytes) -> list[Write]:
        if not data:
            return []
        first = data[0]
        ccs = first >> 5
        if self.open is not None:
            index, sub, via = self.open
            if first == 0x80 or (via == "SDO block" and first & 0xE1 == 0xC1):
                self.open = None  # an abort or the block's end: the last frame of it
            elif via == "SDO segmented" and ccs == 0:
                if first & 1:
                    self.open = None  # the last segment
            elif via == "SDO segmented":
                self.open = None  # a new request: a segmented download has ccs 0 throughout
                return self.frame(data)
            return [Write(index, sub, None, via)]
        if len(data) < 4 or ccs not in (0, 1, 6):
            return []  # uploads, aborts, block uploads: reads
        if ccs == 0:  # a segment of a download whose start was not seen
            return [Write(None, 0, None, "SDO segment")]
        index, sub = data[1] | data[2] << 8, data[3]
        if ccs == 6:
            if first & 1:
                return []  # the end of a block the guard did not see start: harmless alone
            self.open = (index, sub, "SDO block")
            return [Write(index, sub, None, "SDO block")]
        expedited, sized = bool(first & 2), bool(first & 1)
        if not expedited:
            self.open = (index, sub, "SDO segmented")
            return [Write(index, sub, None, "SDO segmented")]
        value = None
        if len(data) == 8:
            size = 4 - (first >> 2 & 3) if sized else 4
            value = int.from_bytes(data[4 : 4 + size], "little")
        return [Write(index, sub, value)]


def nmt_writes(data: bytes, node: int) -> list[Write]:
    """An NMT command (COB-ID 0) to ``node`` or to all: anything but start is an unknown
    write (a reset restores the defaults, stop and pre-operational cut the PDOs)."""
    if len(data) < 2 or data[1] not in (0, node) or data[0] in NMT_HARMLESS:
        return []
    return [Write(None, 0, data[0], "NMT")]


def pdo_writes(data: bytes, mapping: tuple[tuple[int, int, int], ...]) -> list[Write]:
    """An RPDO's objects, by its map at set-up: (index, sub-index, bits) in order."""
    out: list[Write] = []
    raw = int.from_bytes(data, "little")
    at = 0
    for index, sub, bits in mapping:
        if at + bits > 8 * len(data):
            break
        out.append(Write(index, sub, raw >> at & ((1 << bits) - 1), "RPDO"))
        at += bits
    return out


def powerless(statusword: int) -> bool:
    """The statusword shows a state without torque: not ready to switch on, switch on
    disabled, ready to switch on, fault (the profile's masks)."""
    return statusword & 0x4F in (0x00, 0x40, 0x08) or statusword & 0x6F == 0x21


def enables(controlword: int | None) -> bool:
    """A controlword that may lead toward torque: voltage on and no quick stop (shutdown,
    switch on, enable operation); unknown counts."""
    return controlword is None or controlword & 0x6 == 0x6


@dataclass(frozen=True, slots=True)
class Watched:
    """What one drive's bound depends on."""

    stop: StopKind
    counter: Key | None = None
    """The counter object on the drive (counter mode), or None."""

    def matters(self, write: Write) -> bool:
        """A write the bound depends on (the controlword is the guard's own matter)."""
        i = write.index
        if i is None or i in PDO_CONFIG or i in LIMIT_OBJECTS or i in RATINGS:
            return True
        if i in (MODE_OF_OPERATION, HEARTBEAT_CONSUMER, ABORT_CONNECTION, RESTORE_DEFAULTS):
            return True
        if self.counter is not None and i == self.counter[0]:
            return True
        quick = (QUICK_STOP_DECELERATION, PROFILE_DECELERATION, QUICK_STOP_OPTION)
        return self.stop is StopKind.QUICK and i in quick


def expected_keys(stop: StopKind) -> tuple[Key, ...]:
    """The objects beside the PDO configuration and the limits that are read back and must
    hold what they held at set-up (the stop ramps 0x6084 and 0x6085 may rise)."""
    keys: list[Key] = [(HEARTBEAT_CONSUMER, 1), (ABORT_CONNECTION, 0), *((r, 0) for r in RATINGS)]
    if stop is StopKind.QUICK:
        keys += [(QUICK_STOP_DECELERATION, 0), (PROFILE_DECELERATION, 0), (QUICK_STOP_OPTION, 0)]
    return tuple(keys)


def check(setup: dict[Key, int], read: dict[Key, int | None], limits: Limits | None) -> str | None:
    """What differs between the configuration read back (``read``; None: could not be read)
    and what the guard expects: ``setup`` as read at set-up (a stop ramp may be steeper), the
    limits it wrote. None: all holds."""
    wrong: list[str] = []
    expect = dict(setup)
    if limits is not None:
        expect |= {(i, 0): v for i, v in limits.as_objects().items()}
    for key, want in sorted(expect.items()):
        got = read.get(key)
        if got == want or (key[0] in RAMPS and got is not None and got > want):
            continue
        wrong.append(f"0x{key[0]:04X}:{key[1]} = {got} (expected {want})")
    return None if not wrong else "; ".join(wrong)
