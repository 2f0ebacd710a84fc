"""can-utils' candump conventions for ``canergy dump``: its ``CHANNEL,FILTER,...`` argument, its
log lines (``candump -l``/``-L``) and log file names, and the log files of python-can's writers.

Filters read as candump reads them (``ID:MASK`` matches when ``received_id & MASK == ID & MASK``,
``ID~MASK`` when it does not, hexadecimal); ids and masks are the kernel's 32-bit values, with
the flags above the 29 identifier bits (``0x80000000`` extended frame, ``0x40000000`` remote
frame). An ID of more than 3 hex digits, or above 0x7FF, filters 29-bit frames: candump sets the
extended-frame flag for it; here the mask gets the flag too, so that such a filter never lets an
11-bit frame through.
"""

from __future__ import annotations

import copy
import math
import os
import re
import stat
import struct
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Protocol, TextIO

import can

EFF_FLAG = 0x8000_0000
"""The kernel's extended-frame flag in a CAN id (``CAN_EFF_FLAG``)."""
RTR_FLAG = 0x4000_0000
ERR_FLAG = 0x2000_0000
ID_BITS = 0x1FFF_FFFF
SFF_MAX = 0x7FF
CANFD_BRS = 0x01
CANFD_ESI = 0x02

_FILTER = re.compile(r"(?:0[xX])?([0-9A-Fa-f]{1,8})([:~])(?:0[xX])?([0-9A-Fa-f]{1,8})")
_SHOWN = 40
"""Longest piece of an argument quoted back in an error message."""
_AUTO_TRIES = 100
"""Names ``-l`` tries in one second before it gives up."""


def _shown(text: str) -> str:
    return repr(text) if len(text) <= _SHOWN else f"{text[:_SHOWN]!r}..."


@dataclass(frozen=True, slots=True)
class CandumpFilter:
    can_id: int
    """The kernel's 32-bit id (flags included)."""
    can_mask: int
    inverted: bool = False

    @classmethod
    def parse(cls, text: str) -> CandumpFilter:
        """``ID:MASK`` or ``ID~MASK``; ``ValueError`` names the text."""
        m = _FILTER.fullmatch(text)
        if m is None:
            raise ValueError(f"filter {_shown(text)}: expected ID:MASK or ID~MASK in hex")
        digits, mode, mask_text = m.groups()
        can_id, mask = int(digits, 16), int(mask_text, 16) & ~ERR_FLAG  # as candump
        if len(digits) > 3 or can_id & ID_BITS > SFF_MAX:
            can_id |= EFF_FLAG
            mask |= EFF_FLAG
        return cls(can_id, mask, mode == "~")

    def matches(self, frame: can.Message) -> bool:
        hit = kernel_id(frame) & self.can_mask == self.can_id & self.can_mask
        return hit != self.inverted

    def as_python_can(self) -> dict[str, Any]:
        """python-can's ``can_filters`` entry (not for an inverted filter): the remote-frame
        flag is left to the software check."""
        entry: dict[str, Any] = {
            "can_id": self.can_id & ID_BITS,
            "can_mask": self.can_mask & ID_BITS,
        }
        if self.can_mask & EFF_FLAG:
            entry["extended"] = bool(self.can_id & EFF_FLAG)
        return entry


def kernel_id(frame: can.Message) -> int:
    """The frame's id as the kernel's filters see it: the identifier and its flags."""
    return (
        frame.arbitration_id & ID_BITS
        | (EFF_FLAG if frame.is_extended_id else 0)
        | (RTR_FLAG if frame.is_remote_frame else 0)
    )


@dataclass(frozen=True, slots=True)
class ChannelFilters:
    """``CHANNEL[,FILTER[,FILTER...]]``: a channel and the frames to take from it."""

    channel: str
    filters: tuple[CandumpFilter, ...] = ()
    join: bool = False
    """candump's ``j``: a frame must match every filter (default: any one)."""

    @classmethod
    def parse(cls, text: str) -> ChannelFilters:
        channel, *parts = text.split(",")
        if not channel.strip() or channel != channel.strip():
            raise ValueError(f"{_shown(text)}: no channel name before the filters")
        filters: list[CandumpFilter] = []
        join = False
        for part in parts:
            if part in ("j", "J"):
                join = True
            elif part.startswith("#"):
                raise ValueError(
                    f"filter {_shown(part)}: error frame filters (#ERRMASK) are not supported; "
                    "canergy dump shows every error frame the interface delivers"
                )
            else:
                filters.append(CandumpFilter.parse(part))
        return cls(channel, tuple(filters), join)

    def accepts(self, frame: can.Message) -> bool:
        """Whether the filters let ``frame`` through (error frames always: no id to match)."""
        if not self.filters or frame.is_error_frame:
            return True
        hits = (f.matches(frame) for f in self.filters)
        return all(hits) if self.join else any(hits)

    def hardware(self) -> list[dict[str, Any]]:
        """The filters as python-can's ``can_filters``, for the interface (or the kernel) to
        apply; none (take everything, check in software) when one is inverted or joined, which
        python-can cannot pass on."""
        if self.join or any(f.inverted for f in self.filters):
            return []
        return [f.as_python_can() for f in self.filters]


# --- log files --------------------------------------------------------------------------------


def auto_log_name(start: datetime) -> str:
    """The file ``candump -l`` writes, named after its start in local time."""
    return f"candump-{start:%Y-%m-%d_%H%M%S}.log"


def log_line(frame: can.Message, channel: str, timestamp: float | None = None) -> str:
    """One frame as ``candump -l`` logs it: ``(seconds.micro) CHANNEL ID#DATA`` (CAN FD:
    ``ID##FLAGS DATA``, flags 1 bit rate switch, 2 error state indicator; remote: ``ID#R``
    and the DLC when not 0). ``timestamp``: instead of the frame's."""
    when = frame.timestamp if timestamp is None else timestamp
    micros = round(when * 1_000_000) if math.isfinite(when) else 0
    seconds, micro = divmod(max(micros, 0), 1_000_000)
    if frame.is_error_frame:
        ident = f"{ERR_FLAG | frame.arbitration_id & ID_BITS:08X}"
    elif frame.is_extended_id:
        ident = f"{frame.arbitration_id & ID_BITS:08X}"
    else:
        ident = f"{frame.arbitration_id & SFF_MAX:03X}"
    if frame.is_remote_frame and not frame.is_error_frame:
        body = "R" + (f"{frame.dlc:X}" if 0 < frame.dlc <= 8 else "")
    elif frame.is_fd:
        flags = (CANFD_BRS if frame.bitrate_switch else 0) | (
            CANFD_ESI if frame.error_state_indicator else 0
        )
        body = f"#{flags:X}{bytes(frame.data).hex().upper()}"
    else:
        body = bytes(frame.data).hex().upper()
    return f"({seconds:010d}.{micro:06d}) {channel} {ident}#{body}\n"


def channel_name(frame: can.Message, default: str) -> str:
    """The channel a log line names: the frame's, else the one opened; one word (a log line
    is split on spaces), an interface number as ``can<n>`` like python-can's writer."""
    channel = frame.channel if frame.channel is not None else default
    if isinstance(channel, int) or (isinstance(channel, str) and channel.isdigit()):
        channel = f"can{channel}"
    text = str(channel) or "can0"
    return "".join("_" if c.isspace() else c for c in text)


class FrameLog(Protocol):
    """A log being written: python-can's writers are ones, so is ``CandumpLog``."""

    def on_message_received(self, msg: can.Message) -> None: ...

    def stop(self) -> None: ...


class CandumpLog:
    """A ``candump -l`` log file: one line per frame, each written out as it comes (a file
    followed with ``tail -f``, or cut short by a crash, holds every frame logged so far)."""

    def __init__(self, path: Path, channel: str, *, exclusive: bool = False) -> None:
        self.channel = channel
        self.file: TextIO = open(  # noqa: SIM115 -- closed by stop()
            path, "x" if exclusive else "w", encoding="utf-8", buffering=1
        )

    def on_message_received(self, msg: can.Message) -> None:
        when = msg.timestamp or time.time()  # an interface without receive times: now
        self.file.write(log_line(msg, channel_name(msg, self.channel), when))

    def stop(self) -> None:
        self.file.close()


class WriterLog:
    """python-can's writer for the other formats (``can.Logger``). A frame whose channel the
    format cannot hold (BLF keeps a number below 65536: ``bus-123456`` is channel 123457) is
    written with the writer's default channel rather than lost."""

    def __init__(self, path: Path) -> None:
        self.writer = can.Logger(str(path))

    def on_message_received(self, msg: can.Message) -> None:
        try:
            self.writer.on_message_received(msg)
        except (struct.error, OverflowError):
            if msg.channel is None:
                raise
            anonymous = copy.copy(msg)
            anonymous.channel = None
            self.writer.on_message_received(anonymous)

    def stop(self) -> None:
        self.writer.stop()


def _formats() -> str:
    return ", ".join(sorted(can.io.MESSAGE_WRITERS))


def log_format(path: Path) -> str:
    """The format ``path``'s extension names (``.log``; ``.asc.gz``: ``.asc`` compressed), or
    ``ValueError`` when python-can has no writer for it (or not installed here)."""
    suffixes = [s.lower() for s in path.suffixes]
    compressed = bool(suffixes) and suffixes[-1] == ".gz"
    suffix = (suffixes[-2] if len(suffixes) > 1 else "") if compressed else path.suffix.lower()
    if suffix not in can.io.MESSAGE_WRITERS:
        shown = "".join(path.suffixes[-2:] if compressed else path.suffixes[-1:])
        what = f"unknown log format {shown!r}" if shown else "no extension to name its format"
        raise ValueError(
            f"--log {path}: {what} (known: {_formats()}; .gz: compressed, not .blf or .db)"
        )
    if compressed and suffix in (".blf", ".db"):
        raise ValueError(f"--log {path}: python-can cannot compress {suffix} files")
    if suffix == ".mf4":
        from can.io import mf4

        if getattr(mf4, "asammdf", None) is None:  # python-can's optional import failed
            raise ValueError(f"--log {path}: .mf4 needs asammdf: pip install 'canergy[mf4]'")
    return suffix + (".gz" if compressed else "")


def log_path(given: Path, start: datetime) -> tuple[Path, bool]:
    """Where the log goes (a directory: candump's name for the file in it) and whether that
    name was made up here; ``ValueError`` for a path that cannot be written, checked before
    anything is opened and nothing created."""
    if not str(given):
        raise ValueError("--log: empty file name")
    auto = given.is_dir()
    path = given / auto_log_name(start) if auto else given
    log_format(path)
    folder = path.parent
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise ValueError(f"--log {path}: {exc.strerror or exc}") from None
    if mode is not None and auto:
        mode = None  # taken by a dump started in the same second: open_log picks another name
    if mode is not None and not stat.S_ISREG(mode):
        raise ValueError(f"--log {path}: not a regular file")
    if mode is not None and not os.access(path, os.W_OK):
        raise ValueError(f"--log {path}: not writable (permission denied)")
    if mode is None and not folder.is_dir():
        raise ValueError(f"--log {path}: no such directory {str(folder)!r}")
    if mode is None and not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"--log {path}: cannot create a file in {str(folder)!r}")
    return path, auto


def open_log(path: Path, channel: str, *, auto: bool = False) -> tuple[FrameLog, Path]:
    """The writer for ``path`` (``log_path``'s) and the file it writes: candump's own lines for
    ``.log``, python-can's ``can.Logger`` for the other formats. ``auto`` (a name made up by
    ``log_path``): never replace a file, take the next free ``-2``, ``-3``... name instead."""
    if not auto:
        if log_format(path) == ".log":
            return CandumpLog(path, channel), path
        return WriterLog(path), path
    for number in range(1, _AUTO_TRIES + 1):
        name = path if number == 1 else path.with_name(f"{path.stem}-{number}{path.suffix}")
        try:
            return CandumpLog(name, channel, exclusive=True), name
        except FileExistsError:
            continue
    raise FileExistsError(f"{path} and {_AUTO_TRIES - 1} more names like it exist already")
