"""Bits a classic CAN data frame occupies on the wire, beside the codec that fills it.

SOF, arbitration (11-bit: ID + RTR = 12 bits; 29-bit: ID + SRR + IDE + 18 + RTR = 32), control
(6), data (8 per byte), CRC (15) + delimiter, ACK (2), EOF (7) and the 3-bit intermission:
47 + 8n bits (11-bit) or 67 + 8n (29-bit); an 8-byte 11-bit frame is 111. Bit stuffing adds at
most one bit per four after the first, over SOF to the end of the CRC: worst case 135 bits for
an 8-byte 11-bit frame.
"""

from __future__ import annotations


def frame_bits(data_bytes: int, extended: bool, worst_stuffing: bool) -> int:
    """Bits of one classic data frame of ``data_bytes``, stuffing at its worst if asked."""
    fixed = 67 if extended else 47
    bits = fixed + 8 * data_bytes
    if worst_stuffing:
        stuffed_span = (54 if extended else 34) + 8 * data_bytes  # SOF .. end of CRC
        bits += (stuffed_span - 1) // 4
    return bits
