"""Wire model: bits per transaction from the actual frames (``canergy.frame_bits``), and the
bus's limit.
"""

from __future__ import annotations

from typing import Any

from canergy.codec import Codec
from canergy.frame_bits import frame_bits
from canergy.messages import Ack, Commit, Committed, Intention, Message

NOMINAL: list[Message] = [Intention(1, 1, 500, 0), Ack(1, 1), Commit(1, 1, 500), Committed(1, 1)]
BITRATES = (125_000, 250_000, 500_000, 1_000_000)


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
