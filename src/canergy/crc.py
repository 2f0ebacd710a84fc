"""CRC-8 SAE J1850 (polynomial 0x1D, init 0xFF, final XOR 0xFF), the CRC of AUTOSAR E2E Profile 1.

Table-driven. ``crc8_update`` continues a running register so a per-(type, node) Data ID prefix
can be folded in once and reused for every frame.
"""

from __future__ import annotations

POLY = 0x1D
INIT = 0xFF
XOR_OUT = 0xFF


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        reg = byte
        for _ in range(8):
            reg = ((reg << 1) ^ POLY) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
        table.append(reg)
    return tuple(table)


TABLE = _make_table()


def crc8_update(register: int, data: bytes) -> int:
    """Feed ``data`` into a CRC register (no final XOR)."""
    table = TABLE
    for byte in data:
        register = table[register ^ byte]
    return register


def crc8(data: bytes, register: int = INIT) -> int:
    """CRC-8 SAE J1850 of ``data``; ``crc8(b"123456789") == 0x4B``."""
    return crc8_update(register, data) ^ XOR_OUT
