"""What one frame on the bus is, as far as canergy can tell: decoded fields, CRC, transaction."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import can

from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.inspect.named import Named
from canergy.messages import (
    QUANTUM_UJ,
    Admit,
    Debit,
    Direction,
    Join,
    Message,
    Return,
    ReturnAck,
    Telemetry,
)


@dataclass(frozen=True, slots=True)
class Described:
    timestamp: float | None
    channel: str
    arbitration_id: int
    extended: bool
    remote: bool
    error_frame: bool
    data: bytes
    message: Message | None
    """The canergy message, also when only the CRC is wrong (then ``crc_ok`` is False)."""
    crc_ok: bool | None
    problem: str | None
    """Why the frame is not a valid canergy frame (decode error reason), or None."""
    mac: str | None = None
    """Authenticated frames: ``ok``, ``BAD`` or ``unverified`` (no key given); None: plain."""
    other: Named | None = None
    """Another protocol's frame, named (``canergy.inspect.others``)."""

    @property
    def ours(self) -> bool:
        return self.problem != DecodeErrorReason.FOREIGN.value and not self.error_frame

    @property
    def transaction(self) -> tuple[int, str, int] | None:
        """(node, "tx", "return" or "join", number) that groups this frame with its exchange."""
        m = self.message
        if m is None or isinstance(m, Telemetry):
            return None
        if isinstance(m, Debit) and m.is_resume:
            return (m.node, "join", m.nonce)
        if isinstance(m, Return | ReturnAck | Debit):
            return (m.node, "return", m.seq)
        if isinstance(m, Join | Admit):
            return (m.node, "join", m.nonce)
        return (m.node, "tx", m.tx)

    def fields(self) -> dict[str, Any]:
        m = self.message
        if m is None:
            return {}
        out: dict[str, Any] = {}
        for name in m.__slots__:
            value = getattr(m, name)
            if name.endswith("_mj"):
                out[name[:-3] + "_j"] = value * QUANTUM_UJ / 1e6
            else:
                out[name] = value
        return out

    def as_json(self) -> dict[str, Any]:
        m = self.message
        return {
            "timestamp": self.timestamp,
            "channel": self.channel,
            "id": f"{self.arbitration_id:08X}" if self.extended else f"{self.arbitration_id:03X}",
            "extended": self.extended,
            "remote": self.remote,
            "error_frame": self.error_frame,
            "dlc": len(self.data),
            "data": self.data.hex().upper(),
            "type": None if m is None else m.TYPE.name,
            "direction": None if m is None else _direction(m),
            **self.fields(),
            "crc_ok": self.crc_ok,
            "problem": self.problem,
            "mac": self.mac,
            "other": None if self.other is None else self.other.as_json(),
        }


def _direction(m: Message) -> str:
    return "to_client" if m.TYPE.direction is Direction.TO_CLIENT else "to_supervisor"


def describe(codec: Codec, frame: can.Message) -> Described:
    data = bytes(frame.data)

    def make(message: Message | None, crc_ok: bool | None, problem: str | None) -> Described:
        return Described(
            frame.timestamp or None,
            "" if frame.channel is None else str(frame.channel),  # ASC/BLF: 0 is a channel
            frame.arbitration_id,
            frame.is_extended_id,
            frame.is_remote_frame,
            frame.is_error_frame,
            data,
            message,
            crc_ok,
            problem,
        )

    if frame.is_error_frame:
        return make(None, None, "error frame")
    ext, remote = frame.is_extended_id, frame.is_remote_frame
    try:
        msg = codec.decode(frame.arbitration_id, data, extended=ext, remote=remote)
    except DecodeError as err:
        if err.reason is DecodeErrorReason.BAD_CRC:
            try:
                claimed = codec.decode(
                    frame.arbitration_id, data, extended=ext, remote=remote, check_crc=False
                )
            except DecodeError:  # damaged beyond what it claims (e.g. a zero amount)
                claimed = None
            return make(claimed, False, err.reason.value)
        return make(None, None, err.reason.value)
    return make(msg, True, None)
