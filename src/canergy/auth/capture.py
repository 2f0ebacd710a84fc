"""MACs in a capture: what ``canergy dump``, ``decode`` and ``audit`` show with ``--auth``.

A capture needs no counters to be checked: an FD frame carries its whole freshness value, and a
classic message's MAC frame carries the high half (the message, the low half). A classic
TELEMETRY's MAC frame carries the low half of its FV, the node's last transaction: the high half
is taken from the node's transaction frames seen before it (none yet: the FV is taken to be
below 32,768, and a MAC that fails so is ``unverified``); a JOINING one's, and an ADMIT's MAC,
from the node's JOIN seen before it (none: ``unverified``). So each
authenticated frame is split into the message it carries and a verdict: ``ok``, ``BAD``, or
``unverified`` without the key. Replays verify (they are genuine frames); the receiver's
freshness check and the audit see them for what they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import can

from canergy.auth.frames import (
    CLASSIC_MAC,
    FD_MAC,
    FV_MASK,
    MAC_TYPE,
    fd_length,
    low_counter,
    mac,
)
from canergy.auth.keys import Key
from canergy.codec import Codec
from canergy.inspect.frames import Described, describe
from canergy.messages import Admit, Debit, Direction, Join, MsgType, Telemetry
from canergy.seqnum import unwrap

_DIRECTION = {kind: direction for direction, kind in MAC_TYPE.items()}
TRANSACTION_TYPES = frozenset(
    {
        MsgType.INTENTION,
        MsgType.COMMIT,
        MsgType.ABORT,
        MsgType.ACK,
        MsgType.COMMITTED,
        MsgType.ABORTED,
    }
)
"""Messages whose FV is their transaction's number."""


@dataclass
class CaptureAuth:
    """Splits authenticated frames and checks their MACs, frame by frame in capture order."""

    codec: Codec
    key: Key | None
    pending: dict[tuple[str, int, Direction], tuple[Described, bytes]] = field(default_factory=dict)
    """Classic layout: per channel, node and direction, the message whose MAC frame is still
    to come."""
    join_fv: dict[tuple[str, int], int] = field(default_factory=dict)
    """Per channel and node, the FV of its last JOIN (an ADMIT's MAC binds it)."""
    last_tx: dict[tuple[str, int], int] = field(default_factory=dict)
    """Per channel and node, the FV of its last transaction frame (a classic TELEMETRY's FV
    is extended next to it)."""

    def describe(self, frame: can.Message) -> Described:
        data = bytes(frame.data)
        kind = frame.arbitration_id >> 8 & 0xF
        ours = frame.is_extended_id and self.codec.is_canergy_id(frame.arbitration_id)
        if not ours or frame.is_error_frame or frame.is_remote_frame:
            return describe(self.codec, frame)
        if kind in _DIRECTION:
            return self._mac_frame(frame, _DIRECTION[kind], data)
        try:
            length = self.codec.data_length(MsgType(kind))
        except (ValueError, KeyError):
            return describe(self.codec, frame)
        if len(data) == fd_length(length + 12) and len(data) > 8:
            inner = describe(self.codec, _with_data(frame, data[:length]))
            fv = int.from_bytes(data[-12:-8], "big")
            return replace(inner, data=data, mac=self._check(inner, data[:length], fv, data[-8:]))
        d = describe(self.codec, frame)
        if d.message is not None:
            self.pending[(d.channel, d.message.node, d.message.TYPE.direction)] = (d, data)
        return d

    def _mac_frame(self, frame: can.Message, direction: Direction, data: bytes) -> Described:
        node = frame.arbitration_id & 0xFF
        plain = describe(self.codec, frame)
        waiting = self.pending.pop((plain.channel, node, direction), None)
        if len(data) != 3 + CLASSIC_MAC or waiting is None or waiting[0].message is None:
            return replace(plain, problem="MAC frame without its message", mac="BAD")
        d, body = waiting
        assert d.message is not None
        if data[0] != d.message.TYPE:
            return replace(plain, problem="MAC frame for another message", mac="BAD")
        half = int.from_bytes(data[1:3], "big")
        if isinstance(d.message, Telemetry):
            joining = d.message.flags & Telemetry.JOINING
            ref = (self.join_fv if joining else self.last_tx).get((d.channel, node))
            fv = unwrap(half, ref or 0, 16) & FV_MASK
            verdict = self._check(d, body, fv, data[3:])
            if ref is None and verdict == "BAD":  # past transaction 32,767: not known here
                verdict = "unverified"
            return replace(plain, problem="MAC frame of TELEMETRY", mac=verdict)
        else:
            fv = half << 16 | low_counter(d.message)
        verdict = self._check(d, body, fv, data[3:])
        return replace(plain, problem=f"MAC frame of {d.message.TYPE.name}", mac=verdict)

    def _check(self, d: Described, body: bytes, fv: int, tag: bytes) -> str:
        if d.message is None:
            return "BAD"
        node = d.message.node
        if self.key is None or (self.key.kind == "node" and self.key.node != node):
            verdict = "unverified"  # no key, or a node's own key and another node's frame
        else:
            bound = join = None
            if isinstance(d.message, Admit):  # its MAC binds the JOIN it answers
                join = self.join_fv.get((d.channel, node))
                known = join is not None and join & 0xFFFF == d.message.nonce
                bound = join if known else d.message.nonce
            expected = mac(self.key.node_key(node), d.message.TYPE << 8 | node, fv, body, bound)
            ok = expected[: len(tag)] == tag and len(tag) in (FD_MAC, CLASSIC_MAC)
            verdict = "ok" if ok else "BAD"
            if not ok and isinstance(d.message, Admit) and bound != join:
                verdict = "unverified"  # its JOIN is not in the capture
        if verdict != "BAD" and d.message.TYPE in TRANSACTION_TYPES:
            self.last_tx[(d.channel, node)] = fv
        if verdict != "BAD" and (
            isinstance(d.message, Join) or (isinstance(d.message, Debit) and d.message.is_resume)
        ):
            self.join_fv[(d.channel, node)] = fv  # a RESUME's ADMIT binds it as a JOIN's does
        return verdict


def _with_data(frame: can.Message, data: bytes) -> can.Message:
    return can.Message(
        timestamp=frame.timestamp,
        arbitration_id=frame.arbitration_id,
        is_extended_id=frame.is_extended_id,
        data=data,
        channel=frame.channel,
    )


def verified(frames: list[Described]) -> list[Described]:
    """For the audit: each message as the receivers took it. A message whose MAC failed or never
    came is kept out (``damaged``); a classic message counts where it stood in the capture."""
    verdicts: dict[int, str] = {}
    waiting: dict[tuple[str, int, Direction], int] = {}
    for i, d in enumerate(frames):
        if d.message is not None and d.mac is None:  # classic: waits for its MAC frame
            waiting[(d.channel, d.message.node, d.message.TYPE.direction)] = i
        elif d.message is not None:
            verdicts[i] = d.mac or "BAD"
        elif d.mac is not None:
            kind = d.arbitration_id >> 8 & 0xF
            direction = _DIRECTION.get(kind, Direction.TO_CLIENT)
            j = waiting.pop((d.channel, d.arbitration_id & 0xFF, direction), -1)
            if j >= 0:
                verdicts[j] = d.mac
    return [
        d if d.message is None or verdicts.get(i) == "ok" else replace(d, message=None, crc_ok=None)
        for i, d in enumerate(frames)
    ]
