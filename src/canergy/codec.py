"""Wire format: every message in one classic CAN frame with a 29-bit identifier and a CRC-8.

Identifier: ``id_base | type << 8 | node`` (``id_base`` has its low 12 bits clear; node 1-127).
Data: byte 0 is an E2E CRC-8 (SAE J1850) over the 16-bit Data ID ``type << 8 | node`` (low byte
first) and the remaining bytes; fields follow little-endian. See ``docs/protocol.md``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from canergy.crc import INIT, XOR_OUT, crc8_update
from canergy.messages import (
    AMOUNT_MAX_MJ,
    MAX_NODE,
    MESSAGE_CLASSES,
    MIN_NODE,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    Debit,
    Direction,
    FinalAck,
    Intention,
    Join,
    Message,
    MsgType,
    Return,
    ReturnAck,
    StatusRequest,
    Telemetry,
)

DEFAULT_ID_BASE = 0x0CE00000
"""Default identifier base: 29-bit, so it never meets CANopen (11-bit only) on a shared bus."""

ID_MASK = 0x1FFFF000
MAX_EXTENDED_ID = 0x1FFFFFFF
_FROM_CLIENT = 0x8 << 8
_DIR_MASK = ID_MASK | _FROM_CLIENT


class DecodeErrorReason(Enum):
    """Why a frame was refused; callers count these and drop the frame."""

    FOREIGN = "not a canergy identifier"
    UNKNOWN_TYPE = "unknown message type"
    BAD_NODE = "node id out of range"
    REMOTE_FRAME = "remote frame"
    WRONG_DIRECTION = "message sent the wrong way"
    WRONG_DLC = "wrong data length"
    BAD_CRC = "CRC mismatch"
    OUT_OF_RANGE = "field out of range"


class DecodeError(ValueError):
    """A frame that is not a valid canergy message. ``reason`` says which check failed."""

    def __init__(self, reason: DecodeErrorReason, detail: str = "") -> None:
        self.reason = reason
        super().__init__(f"{reason.value}: {detail}" if detail else reason.value)


@dataclass(frozen=True, slots=True)
class _Layout:
    body: struct.Struct
    fields: Callable[[Message], tuple[int, ...]]
    build: Callable[[int, tuple[int, ...]], Message]
    has_amount: bool

    @property
    def dlc(self) -> int:
        return 1 + self.body.size


def _int_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Intention)
    return (m.tx, m.amount_mj, m.delivered_mj & 0xFFFF, m.delivered_mj >> 16)


def _int_build(node: int, f: tuple[int, ...]) -> Message:
    return Intention(node, f[0], f[1], f[2] | f[3] << 16)


def _tx_amount(cls: type[Commit] | type[Abort]) -> _Layout:
    def fields(m: Message) -> tuple[int, ...]:
        assert isinstance(m, cls)
        return (m.tx, m.amount_mj)

    return _Layout(struct.Struct("<HH"), fields, lambda n, f: cls(n, f[0], f[1]), True)


def _tx_only(cls: type[StatusRequest | FinalAck | Ack | Committed | Aborted]) -> _Layout:
    def fields(m: Message) -> tuple[int, ...]:
        assert isinstance(m, cls)
        return (m.tx,)

    return _Layout(struct.Struct("<H"), fields, lambda n, f: cls(n, f[0]), False)


def _retack_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, ReturnAck)
    return (m.seq,)


def _telemetry_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Telemetry)
    return (m.level_mj & 0xFFFF, m.level_mj >> 16, m.flags, m.return_seq, m.witness)


def _join_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Join)
    return (m.nonce,)


def _admit_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Admit)
    return (m.nonce, m.tx, m.seq)


def _return_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Return)
    return (m.seq, m.amount_mj)


def _debit_fields(m: Message) -> tuple[int, ...]:
    assert isinstance(m, Debit)
    return (m.nonce, m.flags, m.seq, m.amount_mj)


_DEBIT_KINDS = (
    Debit.DRAW,
    Debit.START,
    Debit.START | Debit.DRAW,
    Debit.START | Debit.SYNC,
    Debit.START | Debit.SYNC | Debit.RC_UNKNOWN,
    Debit.BOOKS,
    Debit.BOOKS | Debit.RC_UNKNOWN,
)


def _debit_build(node: int, f: tuple[int, ...]) -> Message:
    """A draw carries a non-zero amount and no nonce; a resume may carry none; the books carry
    24 bits of Rc, or none (0) when it is unknown. No other flags."""
    msg = Debit(node, f[0], f[1], f[2], f[3])
    if (
        msg.flags not in _DEBIT_KINDS
        or (msg.flags == Debit.DRAW and (not msg.amount_mj or msg.nonce))
        or (msg.is_books and msg.amount_mj > 0xFF)
        or (msg.rc_unknown and (msg.seq or msg.amount_mj))
    ):
        raise DecodeError(
            DecodeErrorReason.OUT_OF_RANGE, f"not a draw, a resume nor a SYNC's answer: {msg}"
        )
    return msg


LAYOUTS: dict[MsgType, _Layout] = {
    MsgType.INTENTION: _Layout(struct.Struct("<HHHB"), _int_fields, _int_build, True),
    MsgType.COMMIT: _tx_amount(Commit),
    MsgType.ABORT: _tx_amount(Abort),
    MsgType.RETURN_ACK: _Layout(
        struct.Struct("<H"), _retack_fields, lambda n, f: ReturnAck(n, f[0]), False
    ),
    MsgType.STATUS_REQUEST: _tx_only(StatusRequest),
    MsgType.FINAL_ACK: _tx_only(FinalAck),
    MsgType.ACK: _tx_only(Ack),
    MsgType.COMMITTED: _tx_only(Committed),
    MsgType.ABORTED: _tx_only(Aborted),
    MsgType.RETURN: _Layout(
        struct.Struct("<HH"), _return_fields, lambda n, f: Return(n, f[0], f[1]), True
    ),
    MsgType.ADMIT: _Layout(
        struct.Struct("<HHH"), _admit_fields, lambda n, f: Admit(n, f[0], f[1], f[2]), False
    ),
    MsgType.JOIN: _Layout(struct.Struct("<H"), _join_fields, lambda n, f: Join(n, f[0]), False),
    MsgType.DEBIT: _Layout(struct.Struct("<HBHH"), _debit_fields, _debit_build, False),
    MsgType.TELEMETRY: _Layout(
        struct.Struct("<HBBHB"),
        _telemetry_fields,
        lambda n, f: Telemetry(n, f[0] | f[1] << 16, f[2], f[3], f[4]),
        False,
    ),
}
assert set(LAYOUTS) == set(MESSAGE_CLASSES)


def data_id(msg_type: MsgType, node: int) -> int:
    """The 16-bit E2E Data ID folded into the CRC: type in the high byte, node in the low."""
    return int(msg_type) << 8 | node


def _prefix_register(msg_type: MsgType, node: int) -> int:
    did = data_id(msg_type, node)
    return crc8_update(INIT, bytes((did & 0xFF, did >> 8)))


@dataclass(frozen=True, slots=True)
class _Entry:
    msg_type: MsgType
    node: int
    layout: _Layout
    crc_start: int


class Codec:
    """Encodes and strictly decodes canergy frames for one identifier base."""

    def __init__(self, id_base: int = DEFAULT_ID_BASE) -> None:
        if not 0 <= id_base <= MAX_EXTENDED_ID or id_base & ~ID_MASK:
            raise ValueError(
                f"id base 0x{id_base:X} must be a 29-bit identifier with its low 12 bits clear"
            )
        self.id_base = id_base
        self._by_id: dict[int, _Entry] = {}
        for msg_type, layout in LAYOUTS.items():
            for node in range(MIN_NODE, MAX_NODE + 1):
                entry = _Entry(msg_type, node, layout, _prefix_register(msg_type, node))
                self._by_id[self.arbitration_id(msg_type, node)] = entry

    def arbitration_id(self, msg_type: MsgType, node: int) -> int:
        return self.id_base | int(msg_type) << 8 | node

    def is_canergy_id(self, arbitration_id: int, extended: bool = True) -> bool:
        """True for identifiers inside this codec's 4096-identifier block."""
        return extended and (arbitration_id & ID_MASK) == self.id_base

    def can_filters(self) -> list[dict[str, int | bool]]:
        """python-can acceptance filters that pass only this codec's identifier block."""
        return [{"can_id": self.id_base, "can_mask": ID_MASK, "extended": True}]

    def supervisor_filters(self) -> list[dict[str, int | bool]]:
        """Filters passing every client-to-supervisor frame (type bit 3 set)."""
        return [{"can_id": self.id_base | _FROM_CLIENT, "can_mask": _DIR_MASK, "extended": True}]

    def client_filters(self, node: int) -> list[dict[str, int | bool]]:
        """Filters passing only the supervisor's frames to ``node``."""
        return [{"can_id": self.id_base | node, "can_mask": _DIR_MASK | 0xFF, "extended": True}]

    @staticmethod
    def data_length(msg_type: MsgType) -> int:
        """The classic data length of a message type (CRC byte and fields)."""
        return LAYOUTS[msg_type].dlc

    def supervisor_watch_filters(self) -> list[dict[str, int | bool]]:
        """A supervisor's filters that also pass frames in its own direction: its own never come
        back to it, so one for a node it manages is a second supervisor's or a spoofer's."""
        return self.can_filters()

    def client_watch_filters(self, node: int) -> list[dict[str, int | bool]]:
        """A node's filters that also pass client-to-supervisor frames with its own id: a node
        never receives its own, so such a frame was sent by someone else."""
        return [{"can_id": self.id_base | node, "can_mask": ID_MASK | 0xFF, "extended": True}]

    def accepts(
        self, filters: list[dict[str, int | bool]], arbitration_id: int, extended: bool
    ) -> bool:
        """Software acceptance filtering, as a controller applies ``filters`` in hardware."""
        return any(
            bool(f["extended"]) == extended
            and arbitration_id & int(f["can_mask"]) == int(f["can_id"]) & int(f["can_mask"])
            for f in filters
        )

    def encode(self, msg: Message) -> tuple[int, bytes]:
        """Return ``(arbitration_id, data)`` for ``msg``; ``ValueError`` if a field does not fit."""
        msg_type = msg.TYPE
        node = msg.node
        if not MIN_NODE <= node <= MAX_NODE:
            raise ValueError(f"node {node} outside {MIN_NODE}-{MAX_NODE}")
        layout = LAYOUTS[msg_type]
        fields = layout.fields(msg)
        if layout.has_amount and not 1 <= getattr(msg, "amount_mj", 0) <= AMOUNT_MAX_MJ:
            raise ValueError(f"amount must be 1..{AMOUNT_MAX_MJ} mJ in {msg}")
        try:
            body = layout.body.pack(*fields)
        except struct.error as exc:
            raise ValueError(f"field out of range in {msg}: {exc}") from exc
        arbitration_id = self.arbitration_id(msg_type, node)
        crc = crc8_update(self._by_id[arbitration_id].crc_start, body) ^ XOR_OUT
        return arbitration_id, bytes((crc,)) + body

    def decode(
        self,
        arbitration_id: int,
        data: bytes | bytearray,
        *,
        extended: bool = True,
        remote: bool = False,
        direction: Direction | None = None,
        check_crc: bool = True,
    ) -> Message:
        """Decode one frame or raise ``DecodeError``; ``direction`` is what the caller expects.

        ``check_crc=False`` is for inspection tools that show what a damaged frame claims.
        """
        entry = self._by_id.get(arbitration_id) if extended else None
        if entry is None:
            self._raise_for_unknown_id(arbitration_id, extended)
            raise AssertionError("unreachable")  # pragma: no cover
        if remote:
            raise DecodeError(DecodeErrorReason.REMOTE_FRAME, f"id 0x{arbitration_id:08X}")
        if direction is not None and entry.msg_type.direction is not direction:
            raise DecodeError(DecodeErrorReason.WRONG_DIRECTION, entry.msg_type.name)
        layout = entry.layout
        if len(data) != layout.dlc:
            raise DecodeError(
                DecodeErrorReason.WRONG_DLC,
                f"{entry.msg_type.name} needs {layout.dlc} bytes, got {len(data)}",
            )
        body = bytes(data[1:])
        if check_crc and crc8_update(entry.crc_start, body) ^ XOR_OUT != data[0]:
            raise DecodeError(DecodeErrorReason.BAD_CRC, f"{entry.msg_type.name} node {entry.node}")
        msg = layout.build(entry.node, layout.body.unpack(body))
        if layout.has_amount and getattr(msg, "amount_mj", 0) == 0:
            raise DecodeError(DecodeErrorReason.OUT_OF_RANGE, f"zero amount in {msg}")
        return msg

    def _raise_for_unknown_id(self, arbitration_id: int, extended: bool) -> None:
        if not self.is_canergy_id(arbitration_id, extended):
            kind = "extended" if extended else "standard"
            raise DecodeError(DecodeErrorReason.FOREIGN, f"{kind} id 0x{arbitration_id:X}")
        code = arbitration_id >> 8 & 0xF
        if code not in MsgType._value2member_map_:
            raise DecodeError(DecodeErrorReason.UNKNOWN_TYPE, f"type code 0x{code:X}")
        raise DecodeError(DecodeErrorReason.BAD_NODE, f"id 0x{arbitration_id:08X}")
