"""Reading captures: candump text (default, ``-ta`` and ``-L``/``-l`` log lines) from a file or
stdin, and every file format python-can's ``LogReader`` knows (.asc, .blf, .csv, .trc, .mf4...).

Text input is read line by line; a line that is not a frame is reported with its number and
skipped. Binary formats are read by python-can; a damaged file is one clear error. A capture is
only ever read: a path that names no readable file is refused before any reader opens it (some of
python-can's, such as the SQLite one, would create it).
"""

from __future__ import annotations

import math
import os
import re
import stat
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import can

_HEX = re.compile(r"^[0-9A-Fa-f]*$")
# (1699999999.123456) vcan0 0CE00105#FF0100... [R|T]   -- candump -L / -l, python-can
_LOG = re.compile(
    r"^\((?P<ts>\d+\.\d+)\)\s+(?P<ch>\S+)\s+(?P<id>[0-9A-Fa-f]+)#(?P<rest>\S*)(?:\s+[RT])?\s*$"
)
# [(1699999999.123456)]  vcan0  0CE00105   [8]  FF 01 ...   -- candump default / -ta
_DUMP = re.compile(
    r"^(?:\((?P<ts>\d+\.\d+)\)\s+)?(?P<ch>\S+)\s+(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})\s+"
    r"\[(?P<dlc>\d{1,2})\]\s*(?P<rest>.*?)\s*$"
)
FD_LENGTHS = frozenset((*range(9), 12, 16, 20, 24, 32, 48, 64))
TEXT_SUFFIXES = {".log", ".txt", ".candump", ""}


class CaptureError(ValueError):
    """A capture file that cannot be read at all."""


def parse_line(line: str) -> can.Message:
    """One candump line as a ``can.Message``; ``ValueError`` says why it is not one."""
    text = line.strip()
    if m := _LOG.match(text):
        return _from_log(m)
    if m := _DUMP.match(text):
        return _from_dump(m)
    raise ValueError("not a candump line")


def _ident(text: str) -> tuple[int, bool]:
    if len(text) == 3:
        return int(text, 16), False
    if len(text) == 8:
        value = int(text, 16)
        if value > 0x1FFFFFFF:
            raise ValueError(f"identifier {text} beyond 29 bits")
        return value, True
    raise ValueError(f"identifier {text!r} must have 3 or 8 hex digits")


def _timestamp(text: str | None) -> float:
    value = float(text) if text else 0.0
    if not math.isfinite(value):
        raise ValueError("timestamp out of range")
    return value


CAN_ERR_FLAG = 0x20000000
"""SocketCAN's error-frame flag: candump -l writes an error frame's id with it set."""


def _from_log(m: re.Match[str]) -> can.Message:
    text, rest = m["id"], m["rest"]
    if len(text) == 8 and int(text, 16) & ~0x1FFFFFFF == CAN_ERR_FLAG:  # an error frame
        if not _HEX.match(rest) or len(rest) % 2 or len(rest) > 16:
            raise ValueError(f"bad error frame data {rest!r}")
        return can.Message(
            timestamp=_timestamp(m["ts"]),
            channel=m["ch"],
            arbitration_id=int(text, 16) & 0x1FFFFFFF,
            is_error_frame=True,
            data=bytes.fromhex(rest),
        )
    ident, extended = _ident(text)
    common = dict(
        timestamp=_timestamp(m["ts"]),
        channel=m["ch"],
        arbitration_id=ident,
        is_extended_id=extended,
    )
    if rest.startswith("#"):  # CAN FD: a flags digit (bit 0: bit rate switch), then the data
        flags, body = rest[1:2], rest[2:]
        if not flags or not _HEX.match(flags + body) or len(body) % 2:
            raise ValueError(f"bad CAN FD data {rest!r}")
        return _fd(common, bytes.fromhex(body), int(flags, 16))
    if rest.upper().startswith("R"):
        dlc = int(rest[1:]) if rest[1:].isdigit() else 0
        return can.Message(**common, is_remote_frame=True, dlc=dlc)  # type: ignore[arg-type]
    if not _HEX.match(rest) or len(rest) % 2 or len(rest) > 16:
        raise ValueError(f"bad data {rest!r}")
    return can.Message(**common, data=bytes.fromhex(rest))  # type: ignore[arg-type]


def _from_dump(m: re.Match[str]) -> can.Message:
    ident, extended = _ident(m["id"])
    dlc, rest = int(m["dlc"]), m["rest"]
    common = dict(
        timestamp=_timestamp(m["ts"]),
        channel=m["ch"],
        arbitration_id=ident,
        is_extended_id=extended,
    )
    if rest.startswith("remote request"):
        return can.Message(**common, is_remote_frame=True, dlc=dlc)  # type: ignore[arg-type]
    parts = rest.split()
    if len(parts) != dlc or not all(len(p) == 2 and _HEX.match(p) for p in parts):
        raise ValueError(f"expected {dlc} data bytes, got {rest!r}")
    data = bytes.fromhex("".join(parts))
    if dlc > 8:
        return _fd(common, data, 0)
    return can.Message(**common, data=data)  # type: ignore[arg-type]


def _fd(common: dict[str, Any], data: bytes, flags: int) -> can.Message:
    if len(data) not in FD_LENGTHS:
        raise ValueError(f"{len(data)} bytes is not a CAN FD length")
    return can.Message(**common, data=data, is_fd=True, bitrate_switch=bool(flags & 1))


def read_text(
    lines: Iterable[str], on_garbage: Callable[[int, str, str], None]
) -> Iterator[can.Message]:
    """Frames from candump text; ``on_garbage(line_number, line, reason)`` for the rest."""
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            yield parse_line(line)
        except ValueError as exc:
            on_garbage(number, line.rstrip("\n"), str(exc))


def check_capture(path: Path) -> None:
    """Raise ``CaptureError`` unless ``path`` names a capture that can be read, touching nothing.

    A regular file; candump text may also come through a pipe or a terminal (``<(candump -L
    vcan0)``, ``/dev/stdin``). Never a directory, nor a name that does not exist.
    """
    suffix = path.suffix.lower()
    if suffix not in TEXT_SUFFIXES and suffix not in can.io.MESSAGE_READERS:
        known = ", ".join(sorted({*TEXT_SUFFIXES - {""}, *can.io.MESSAGE_READERS}))
        raise CaptureError(f"{path}: unknown capture format (known: {known})")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such file") from None
    except OSError as exc:
        raise CaptureError(f"{path}: {exc.strerror or exc}") from None
    text = suffix in TEXT_SUFFIXES
    if stat.S_ISDIR(mode):
        raise CaptureError(f"{path}: is a directory, not a capture file")
    if not (stat.S_ISREG(mode) or (text and (stat.S_ISFIFO(mode) or stat.S_ISCHR(mode)))):
        raise CaptureError(f"{path}: not a regular file")
    if not os.access(path, os.R_OK):
        raise CaptureError(f"{path}: not readable (permission denied)")


def read_file(path: Path, on_garbage: Callable[[int, str, str], None]) -> Iterator[can.Message]:
    """Any capture: candump text by line, other formats through python-can. A path that is not
    a readable capture is refused here, at the call, before anything is opened."""
    check_capture(path)
    return _read_file(path, on_garbage)


def _read_file(path: Path, on_garbage: Callable[[int, str, str], None]) -> Iterator[can.Message]:
    if path.suffix.lower() in TEXT_SUFFIXES:
        try:
            with open(path, errors="replace") as f:
                yield from read_text(f, on_garbage)
        except OSError as exc:
            raise CaptureError(f"{path}: {exc}") from exc
        return
    try:
        yield from can.LogReader(str(path))
    except NotImplementedError as exc:  # python-can's reader needs an optional package
        hint = " (pip install 'canergy[mf4]')" if path.suffix.lower() == ".mf4" else ""
        raise CaptureError(f"{path}: cannot read {path.suffix} here: {exc}{hint}") from exc
    except Exception as exc:  # readers raise struct.error, zlib.error, KeyError...: one message
        if isinstance(exc, CaptureError):
            raise
        raise CaptureError(f"{path}: cannot read as {path.suffix} ({exc})") from exc
