"""A small capture with a known story, for the monitor and plot tests.

Node 3 reports 0.750 J, commits 0.500 J (tx 1) and returns 0.120 J. Node 5 never answers tx 1
(0.300 J, sent three times); ten minutes later its tx 2 carries Gs 0.300 J: tx 1 was written off.
Then node 5 commits tx 2 (0.200 J) and node 3 reports 0.630 J. Also one 11-bit CANopen frame and
one canergy frame with a broken CRC.
"""

from __future__ import annotations

from pathlib import Path

import can

from canergy.codec import Codec
from canergy.messages import (
    Ack,
    Commit,
    Committed,
    Intention,
    Message,
    Return,
    ReturnAck,
    Telemetry,
)

T0 = 1_700_000_000.0
GAP = 600.0
"""Seconds of silence before node 5's second intention."""
CHANNEL = "vcan0"

_STORY: list[tuple[float, Message]] = [
    (0.00, Telemetry(3, 750)),
    (0.05, Intention(3, 1, 500, 0)),
    (0.06, Ack(3, 1)),
    (0.07, Commit(3, 1, 500)),
    (0.08, Committed(3, 1)),
    (0.10, Return(3, 1, 120)),
    (0.11, ReturnAck(3, 1)),
    (0.15, Intention(5, 1, 300, 0)),
    (0.20, Intention(5, 1, 300, 0)),
    (0.25, Intention(5, 1, 300, 0)),
    (GAP, Intention(5, 2, 200, 300)),
    (GAP + 0.05, Ack(5, 2)),
    (GAP + 0.10, Commit(5, 2, 200)),
    (GAP + 0.15, Committed(5, 2)),
    (GAP + 0.50, Telemetry(3, 630)),
]
WRITE_OFF_AT = 12
"""Index in ``frames()`` of the intention that shows the write-off."""


def _frame(t: float, arbitration_id: int, data: bytes, extended: bool = True) -> can.Message:
    return can.Message(
        timestamp=T0 + t,
        arbitration_id=arbitration_id,
        data=data,
        is_extended_id=extended,
        channel=CHANNEL,
    )


def frames() -> list[can.Message]:
    codec = Codec()
    out = []
    for t, msg in _STORY:
        ident, data = codec.encode(msg)
        out.append(_frame(t, ident, data))
    ident, data = codec.encode(Ack(3, 1))
    broken = bytes([data[0] ^ 0xFF]) + data[1:]
    out.insert(10, _frame(0.27, 0x701, b"\x05", extended=False))  # a CANopen heartbeat
    out.insert(11, _frame(0.30, ident, broken))
    return out


def write(path: Path) -> Path:
    """The capture in the format ``path``'s suffix names (python-can's writers)."""
    writer = can.Logger(str(path))
    try:
        for frame in frames():
            writer.on_message_received(frame)
    finally:
        writer.stop()
    return path


def cell(head: str, line: str, title: str) -> str:
    """The value in ``line`` under the right-aligned column ``title`` of the header ``head``."""
    end = head.index(f" {title} ") + len(title) + 1
    start = head.rindex(" ", 0, end - len(title))
    return line[start:end].strip()
