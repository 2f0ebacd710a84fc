"""The client's non-volatile record and its A/B store, laid out as firmware would in flash/EEPROM.

Record (30 bytes, little-endian, packed)::

    u32 usable_uj        energy the actuator may still draw (at most USABLE_MAX_UJ)
    u32 credited_mj      Rc: all energy ever credited (whole wire quanta), modulo 2**32
    u64 spent_uj         energy taken by the actuator
    u32 last_tx          last transaction resolved, modulo 2**32
    u32 return_seq       number of the last return sent, modulo 2**32
    u32 return_pending_uj  amount of that return until acknowledged
    u8  outcome          how ``last_tx`` ended
    u8  flags            bit 0: admitted without books, Rc comes with the next intention;
                         bit 1: the pending debit is a draw (witnessed rules), not a return

The three counters are only ever compared with the wire's 24- and 16-bit values through
serial-number arithmetic, so keeping them modulo 2**32 (a multiple of both wire ranges) changes
no comparison. A file with no valid slot holds no books: the node must JOIN (``load`` is None).

Slot (40 bytes): ``u16 magic, u32 counter, record padded to 30 bytes, u32 crc32`` over magic to
padding. The store has two slots; a write goes to the slot *not* holding the newest valid record,
so a power loss mid-write (torn or corrupted slot) leaves the previous record readable. Loading
picks the valid slot written last (counters compare as 32-bit serial numbers, so the choice
survives the wrap). Nothing is acted on before its write completes, so the fallback record never
holds more energy than was committed.

Sealed store (a node run with its key, ``--auth``): the same slots, then a seal per record slot
after the parameter slot, 8 bytes each at offset 120 + 8 i (a 136-byte file): the first 8 bytes
of AES-CMAC over the whole slot under the **NV seal key**, derived from the node key by the
project's KDF with label ``canergy node nv seal`` and context the node id (1 byte); the C node's
``canergy_nv_seal`` (firmware/include/canergy/nv.h) makes the same bytes. A slot whose seal does
not hold is a damaged slot (the other is taken); none left, or a record never sealed, is refused
(``NvError``). The seal proves a key holder wrote the slot; it cannot tell a genuine older
sealed record put back from the newest (the witnessed rules' RESUME finds that behind).
"""

from __future__ import annotations

import hmac
import os
import struct
import weakref
import zlib
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives import cmac
from cryptography.hazmat.primitives.ciphers import algorithms

from canergy.auth.state_key import derive
from canergy.core.state import ClientState, Outcome
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    QUANTUM_UJ,
    USABLE_MAX_UJ,
    counter_beyond,
)
from canergy.seqnum import unwrap

RECORD = struct.Struct("<IIQIIIBB")
RECORD_SIZE = RECORD.size
assert RECORD_SIZE <= 32
_MAGIC = 0xCE57
_HEAD = struct.Struct("<HI")
_PAD = 30
_CREDITED_UNKNOWN = 0x01
_PENDING_DRAW = 0x02
_CRC = struct.Struct("<I")
SLOT_SIZE = _HEAD.size + _PAD + _CRC.size
SEAL_SIZE = 8
SEALS_AT = 3 * SLOT_SIZE
SEALED_SIZE = SEALS_AT + 2 * SEAL_SIZE
SEAL_LABEL = b"canergy node nv seal"
NV_FILE_SIZES = (0, 2 * SLOT_SIZE, 3 * SLOT_SIZE, SEALED_SIZE)
"""Sizes an NV file can have: new, two record slots, the CANopen parameter slot too, and the
seals after it (a sealed store)."""
U32 = 0xFFFFFFFF
PARAM_SLOT = 2
PARAMS = struct.Struct("<IIIB")
"""Response timeout (ms), power (mW), telemetry period (ms) as CANopen 0x2100-0x2102, and a
mask of which of the three were written."""


class NvError(ValueError):
    """A value does not fit the record, or the store cannot be read at all."""


class NvBeyondBound(NvError):
    """A record whose counter is at or beyond ``COUNTER_BOUND``: refused, never taken as no
    books (the other slot may be an older copy, and an older copy is not covered)."""


class SimulatedPowerLoss(Exception):
    """Raised by a store told to lose power during a write (the slot is left torn)."""


def pack_record(c: ClientState) -> bytes:
    if c.credited % QUANTUM_UJ:
        raise NvError(f"credited {c.credited} µJ is not whole quanta")
    fields = (
        c.usable,
        c.credited // QUANTUM_UJ & U32,
        c.spent,
        c.last_tx & U32,
        c.return_seq & U32,
        c.return_pending,
        int(c.outcome),
        (_CREDITED_UNKNOWN if c.credited_unknown else 0) | (_PENDING_DRAW if c.pending_draw else 0),
    )
    try:
        return RECORD.pack(*fields)
    except struct.error as exc:
        raise NvError(f"client record does not fit the NV layout: {exc}") from exc


def unpack_record(node: int, data: bytes) -> ClientState:
    usable, credited_mj, spent, last_tx, return_seq, pending, outcome, flags = RECORD.unpack(data)
    pending_ok = pending % QUANTUM_UJ == 0 and pending <= AMOUNT_MAX_MJ * QUANTUM_UJ
    pending_ok &= pending > 0 or not flags & _PENDING_DRAW
    if outcome not in Outcome._value2member_map_ or usable > USABLE_MAX_UJ or not pending_ok:
        raise NvError(f"node {node}: the record holds values no client writes")
    for name, value in (("last_tx", last_tx), ("return_seq", return_seq)):
        if value >= COUNTER_BOUND:
            raise NvBeyondBound(f"node {node}: {name} {counter_beyond(value)}")
    return ClientState(
        node,
        usable=usable,
        credited=credited_mj * QUANTUM_UJ,
        spent=spent,
        last_tx=last_tx,
        outcome=Outcome(outcome),
        return_seq=return_seq,
        return_pending=pending,
        credited_unknown=bool(flags & _CREDITED_UNKNOWN),
        pending_draw=bool(flags & _PENDING_DRAW),
    )


def encode_slot(counter: int, record: bytes) -> bytes:
    body = _HEAD.pack(_MAGIC, counter) + record.ljust(_PAD, b"\0")
    return body + _CRC.pack(zlib.crc32(body))


def newest(valid: list[tuple[int, int, bytes]]) -> tuple[int, int, bytes]:
    """Of the valid ``(counter, slot, record)``s, the one written last: counters compare as
    32-bit serial numbers, so slot order survives the counter's wrap (equal: the later slot)."""
    if len(valid) == 1:
        return valid[0]
    first, second = valid
    return second if unwrap(second[0], first[0], 32) >= first[0] else first


def decode_slot(raw: bytes) -> tuple[int, bytes] | None:
    """``(counter, record)`` of a valid slot, else None."""
    if len(raw) != SLOT_SIZE:
        return None
    body, (crc,) = raw[: -_CRC.size], _CRC.unpack(raw[-_CRC.size :])
    magic, counter = _HEAD.unpack(body[: _HEAD.size])
    if magic != _MAGIC or zlib.crc32(body) != crc:
        return None
    return counter, body[_HEAD.size : _HEAD.size + RECORD_SIZE]


class NvSeal:
    """Seals a node's record slots under its NV seal key (the key itself never shown)."""

    __slots__ = ("_keyed", "node")

    def __init__(self, node_key: bytes, node: int) -> None:
        self._keyed = cmac.CMAC(algorithms.AES(derive(node_key, SEAL_LABEL, bytes([node]))))
        self.node = node

    def __repr__(self) -> str:
        return f"NvSeal(node={self.node})"

    def seal(self, slot: bytes) -> bytes:
        """The seal of one slot image: 8 bytes of its AES-CMAC."""
        c = self._keyed.copy()
        c.update(slot)
        return c.finalize()[:SEAL_SIZE]

    def holds(self, slot: bytes, found: bytes) -> bool:
        """``found`` is ``slot``'s seal (compared in constant time)."""
        return hmac.compare_digest(self.seal(slot), found)


def _names(slots: list[int]) -> str:
    return " and ".join(map(str, slots))


@dataclass(slots=True)
class NvStats:
    writes: int = 0
    fallbacks: int = 0
    """Loads that found the newest slot invalid and used the older one."""


class NvStore:
    """Two slots in one file; ``crash_after=N`` tears the N-th write and raises."""

    def __init__(
        self,
        path: Path,
        node: int,
        *,
        fsync: bool = True,
        crash_after: int | None = None,
        seal: NvSeal | None = None,
    ) -> None:
        self.path = path
        self.node = node
        self.seal = seal
        """With a key: each record slot sealed, and only sealed records taken."""
        self.set_aside: list[int] = []
        """Slots the last load set aside because their seal did not hold."""
        self.fsync = fsync
        self.crash_after = crash_after
        self.stats = NvStats()
        self._counter = 0
        self._newest_slot = 1  # so the first write goes to slot 0
        self._fd: int | None = None
        self._closer: weakref.finalize[[int], NvStore] | None = None
        self._size = 0

    def load(self) -> ClientState | None:
        """The newest valid record; None when there is none (a new, wiped or corrupted file):
        the node then has no books and must JOIN."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise NvError(f"{self.path}: {exc}") from exc
        chunks = [raw[i * SLOT_SIZE : (i + 1) * SLOT_SIZE] for i in (0, 1)]
        slots = [decode_slot(chunk) for chunk in chunks]
        slots = self._unseal(raw, chunks, slots)
        valid = [(s[0], i, s[1]) for i, s in enumerate(slots) if s is not None]
        if any(s is None and chunk.strip(b"\0") for s, chunk in zip(slots, chunks, strict=True)):
            self.stats.fallbacks += 1  # a torn or corrupted slot: its write never completed
        if not valid:
            return None
        counter, index, record = newest(valid)
        self._counter, self._newest_slot = counter, index
        try:
            return unpack_record(self.node, record)
        except NvBeyondBound as exc:
            raise NvError(f"--nv {self.path}: {exc}") from None
        except NvError:
            self.stats.fallbacks += 1
            return None  # a checksum collision over garbage: no books, not a crash

    def _unseal(
        self, raw: bytes, chunks: list[bytes], slots: list[tuple[int, bytes] | None]
    ) -> list[tuple[int, bytes] | None]:
        """The slots a sealed store may take (those whose seal holds); refuses a sealed file
        without a key, a record never sealed with one, and a file where no seal holds."""
        where = f"--nv {self.path}: node {self.node}"
        self.set_aside = []
        if self.seal is None:
            if len(raw) == SEALED_SIZE:
                raise NvError(
                    f"{where}: sealed by a node with a key (--auth): without that key its seals "
                    "cannot be checked; run with --auth and this node's key file"
                )
            return slots
        again = ": nothing taken. Move the file away to JOIN afresh (what it held is then lost, "
        again += "never created)"
        if len(raw) != SEALED_SIZE:
            found = [i for i, s in enumerate(slots) if s is not None]
            if found:
                raise NvError(
                    f"{where}: slot {_names(found)} holds a record that is not sealed (written "
                    "without --auth, or its seals cut off): a node with a key takes sealed "
                    f"records only{again}"
                )
            return slots
        seals = [raw[SEALS_AT + i * SEAL_SIZE : SEALS_AT + (i + 1) * SEAL_SIZE] for i in (0, 1)]
        for i, chunk in enumerate(chunks):
            if chunk.strip(b"\0") and not self.seal.holds(chunk, seals[i]):
                self.set_aside.append(i)
                slots[i] = None  # a damaged slot
        if self.set_aside and all(s is None for s in slots):
            raise NvError(
                f"{where}: slot {_names(self.set_aside)}: the seal does not hold (the record "
                "edited, or sealed under another node's key), and no other slot holds a sealed "
                f"record{again}"
            )
        return slots

    def save(self, c: ClientState) -> None:
        record = pack_record(c)
        slot = 1 - self._newest_slot
        data = encode_slot((self._counter + 1) & U32, record)
        self.stats.writes += 1
        if self.crash_after is not None and self.stats.writes >= self.crash_after:
            self._write(slot, data[: len(data) // 2])  # the power fails mid-write
            raise SimulatedPowerLoss(
                f"node {self.node}: power lost during NV write {self.stats.writes}"
            )
        self._write(slot, data)
        self._counter, self._newest_slot = (self._counter + 1) & U32, slot

    def save_params(self, params: tuple[int, ...]) -> None:
        """Parameters written over CANopen, in a third CRC-protected slot (configuration, not
        energy: a torn write only loses them, and the command line applies again)."""
        self._write(PARAM_SLOT, encode_slot(0, PARAMS.pack(*params)))

    def load_params(self) -> tuple[int, ...] | None:
        try:
            raw = self.path.read_bytes()[PARAM_SLOT * SLOT_SIZE : (PARAM_SLOT + 1) * SLOT_SIZE]
        except OSError:
            return None
        slot = decode_slot(raw)
        return None if slot is None else PARAMS.unpack(slot[1][: PARAMS.size])

    def _write(self, slot: int, data: bytes) -> None:
        """Write one slot (a whole record slot in a sealed store: then its seal; torn between
        the two, this slot is not taken) through the file kept open from the first write on (a
        flash driver set up once), grown to hold the slot, and with a key the seals, if it is
        shorter."""
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            self._closer = weakref.finalize(self, os.close, self._fd)
            self._size = os.fstat(self._fd).st_size
        least = max(2, slot + 1) * SLOT_SIZE
        if self.seal is not None:
            least = max(least, SEALED_SIZE)
        if self._size < least:
            self._size = least
            os.ftruncate(self._fd, self._size)
        os.pwrite(self._fd, data, slot * SLOT_SIZE)
        if self.seal is not None and slot < PARAM_SLOT and len(data) == SLOT_SIZE:
            os.pwrite(self._fd, self.seal.seal(data), SEALS_AT + slot * SEAL_SIZE)
        if self.fsync:
            os.fsync(self._fd)

    def close(self) -> None:
        """Close the file (also done when the store is garbage-collected)."""
        if self._closer is not None:
            self._closer()
        self._fd, self._closer = None, None
