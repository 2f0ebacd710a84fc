"""Wire model: bits per frame and per transaction from the actual frames, and the bus's limit.

Classic CAN data frame: SOF, arbitration (11-bit: ID + RTR = 12 bits; 29-bit: ID + SRR + IDE +
18 + RTR = 32), control (6), data (8 per byte), CRC (15) + delimiter, ACK (2), EOF (7) and the
3-bit intermission: 47 + 8n bits (11-bit) or 67 + 8n (29-bit); an 8-byte 11-bit frame is 111.
Bit stuffing adds at most one bit per four after the first, over SOF to the end of the CRC:
worst case 135 bits for an 8-byte 11-bit frame.
"""

from __future__ import annotations

from typing import Any

from canergy.codec import Codec
from canergy.messages import Ack, Commit, Committed, Intention, Message

NOMINAL: list[Message] = [Intention(1, 1, 500, 0), Ack(1, 1), Commit(1, 1, 500), Committed(1, 1)]
BITRATES = (125_000, 250_000, 500_000, 1_000_000)


def frame_bits(data_bytes: int, extended: bool, worst_stuffing: bool) -> int:
    fixed = 67 if extended else 47
    bits = fixed + 8 * data_bytes
    if worst_stuffing:
        stuffed_span = (54 if extended else 34) + 8 * data_bytes  # SOF .. end of CRC
        bits += (stuffed_span - 1) // 4
    return bits


def model() -> dict[str, Any]:
    codec = Codec()
    sizes = [len(codec.encode(m)[1]) for m in NOMINAL]
    rows = []
    for extended in (False, True):
        for stuffing in (False, True):
            bits = sum(frame_bits(n, extended, stuffing) for n in sizes)
            rows.append(
                {
                    "ids": "29-bit" if extended else "11-bit",
                    "stuffing": "worst" if stuffing else "none",
                    "bits_per_tx": bits,
                    "max_tx_per_s": {str(b): b // bits for b in BITRATES},
                }
            )
    return {"frames_per_tx": len(NOMINAL), "frame_bytes": sizes, "rows": rows}


def headroom(supervisor_cpu_us_per_frame: float) -> dict[str, float]:
    """Wire time of an average canergy frame at 1 Mbit/s (29-bit, no stuffing, the best case
    for the bus) against the supervisor's CPU time per frame; >= 1 means it keeps up."""
    codec = Codec()
    sizes = [len(codec.encode(m)[1]) for m in NOMINAL]
    wire_us = sum(frame_bits(n, True, False) for n in sizes) / len(sizes)  # 1 bit = 1 µs
    return {
        "wire_us_per_frame_1mbit": wire_us,
        "supervisor_cpu_us_per_frame": supervisor_cpu_us_per_frame,
        "headroom": wire_us / supervisor_cpu_us_per_frame,
    }
