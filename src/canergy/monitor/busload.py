"""Time a frame occupies the bus, for the load shown in the header.

Classic frames use the wire model of ``canergy.frame_bits`` (47 + 8n bits with 11-bit
identifiers, 67 + 8n with 29-bit ones, intermission included). CAN FD frames add their own
control and CRC fields; with bit rate switching their data phase runs at the data bit rate. Stuff
bits depend on the bits themselves and are not counted, so the load shown is a lower bound (at
most about a fifth more with the worst stuffing).
"""

from __future__ import annotations

from functools import cache

import can

from canergy.frame_bits import frame_bits

_FD_TAIL = 1 + 2 + 7 + 3
"""CRC delimiter, ACK slot and delimiter, end of frame, intermission: at the nominal rate."""


def fd_frame_bits(data_bytes: int, extended: bool) -> tuple[int, int]:
    """(nominal-phase bits, data-phase bits) of a CAN FD data frame, stuff bits aside.

    Nominal phase: SOF, identifier (29-bit: with SRR and IDE), RRS, (IDE,) FDF, res, BRS, and the
    tail. Data phase: ESI, DLC, the data, the stuff count (4) and CRC-17 (up to 16 bytes) or
    CRC-21 with their fixed stuff bits (6 or 7)."""
    head = 36 if extended else 17
    crc, fixed = (17, 6) if data_bytes <= 16 else (21, 7)
    return head + _FD_TAIL, 1 + 4 + 8 * data_bytes + 4 + crc + fixed


@cache
def _seconds(
    data_bytes: int, extended: bool, fd: bool, brs: bool, bitrate: int, data_bitrate: int | None
) -> float:
    if not fd:
        return frame_bits(data_bytes, extended, False) / bitrate
    nominal, data = fd_frame_bits(data_bytes, extended)
    fast = data_bitrate if brs and data_bitrate else bitrate
    return nominal / bitrate + data / fast


def frame_seconds(frame: can.Message, bitrate: int, data_bitrate: int | None = None) -> float:
    """Seconds ``frame`` keeps the bus busy at ``bitrate`` (and ``data_bitrate`` for CAN FD frames
    with bit rate switching). An error frame counts its flag and delimiter, 14 to 20 bits: 20."""
    if frame.is_error_frame:
        return 20 / bitrate
    size = 0 if frame.is_remote_frame else len(frame.data)
    return _seconds(
        size, frame.is_extended_id, frame.is_fd, frame.bitrate_switch, bitrate, data_bitrate
    )
