"""An NV file in memory: firmware_model's own ``NvStore`` over a bytearray, and ``write_slot``,
what ``NvStore`` does to the file's bytes when it writes a slot.

The C side writes the NV images the C client asks for with ``write_slot`` into another
bytearray, so both sides' files can be compared byte for byte (tests/test_c_nv.py,
tests/test_c_node.py, ``support.side_by_side``).
"""

from __future__ import annotations

from firmware_model.nvstore import NvStore
from support.c_binding import SLOT


def write_slot(raw: bytearray, slot: int, data: bytes) -> None:
    """What NvStore._write does to a file: grow it to at least two slots, write in place."""
    size = max(2, slot + 1) * SLOT
    if len(raw) < size:
        raw.extend(bytes(size - len(raw)))
    raw[slot * SLOT : slot * SLOT + len(data)] = data


class _MemPath:
    """Enough of a Path for NvStore: the file's bytes live in a bytearray (absent when empty)."""

    def __init__(self, raw: bytearray) -> None:
        self.raw = raw

    def read_bytes(self) -> bytes:
        if not self.raw:
            raise FileNotFoundError("no NV file")
        return bytes(self.raw)


class MemNv(NvStore):
    """firmware_model's own NvStore (load, save, slot choice, counters), over memory."""

    def __init__(self, raw: bytearray, node: int = 1) -> None:
        super().__init__(_MemPath(raw), node, fsync=False)  # type: ignore[arg-type]
        self.raw = raw

    def _write(self, slot: int, data: bytes) -> None:
        write_slot(self.raw, slot, data)
