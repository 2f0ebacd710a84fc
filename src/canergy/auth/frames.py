"""Authenticated frames: a truncated AES-128-CMAC over Data ID, freshness value and payload, as
AUTOSAR SecOC does.

MAC input: Data ID ``type << 8 | node`` (2 bytes, big-endian) || freshness value FV (4 bytes,
big-endian) || the classic frame's data (CRC-8 byte and fields). FV never repeats for a key: the
full 32-bit transaction number for transaction frames, the full return number for RETURN,
RETURN_ACK and a DEBIT's draw (numbered as a return), the sender's last resolved transaction for
TELEMETRY, the nonce for JOIN, RESUME (a DEBIT's start), a SYNC's books and counts, and ADMIT; a
JOIN's and a RESUME's FV has a random high half the ADMIT's MAC binds (32 bits for a replayed
ADMIT to match, not 16).
The wire carries 16-bit counters; a receiver extends them from its own counters, and a frame
whose FV is not the one it expects (a replay from 65,536 transactions ago, say) is refused. So
is, once the side's freshness gives an ``Expected`` (``expected_freshness``), a frame whose FV
is older than its own counter: a replay of an earlier transaction or return, refused as stale
(``STALE``) and counted, never handed to the protocol; a current duplicate (the FV at the
counter) passes, as the protocol tolerates duplicates.

A node without books binds its TELEMETRY to its JOIN (the JOIN's FV, whose ADMIT it awaits);
the supervisor takes one only with the FV of the JOIN it took last, and ignores any other (it
moves nothing: a JOIN not seen yet, or a replay). Otherwise TELEMETRY is
fresh from the last transaction the receiver knows the node resolved (its
COMMITTED or ABORTED, its ACK of the next, its last TELEMETRY taken) up to the receiver's own
transaction. A node's level only rises when it resolves a transaction, so a TELEMETRY replayed
within that window reports at least what the node holds: it can make the supervisor grant
less, never more. One from before the window is refused as stale.

Two layouts:

- **fd** (CAN FD): one frame, ``data || zero padding || FV (4) || MAC (8)``, padded to the next
  CAN FD length (16 or 20 bytes). A 64-bit MAC: a forgery succeeds with probability 2^-64 per
  attempt.
- **classic**: the unchanged classic frame followed by a MAC frame on type code 0x0 (supervisor
  to node) or 0x8 (node to supervisor) of the same node: ``type (1) || FV high 16 bits (2) ||
  MAC (5)``; TELEMETRY, which carries no counter, puts the FV's low 16 bits there instead. A
  40-bit MAC: 2^-40 per attempt (at 2,000 forged frames/s, one success expected in about 17
  years). A message counts only once its MAC frame followed it; one whose MAC frame never came
  is dropped, and counted as a frame without a MAC when the next message arrives.
"""

from __future__ import annotations

import functools
import hmac
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import TypeGuard

import can
from cryptography.hazmat.primitives import cmac
from cryptography.hazmat.primitives.ciphers import algorithms

from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.messages import (
    SEQ_BITS,
    TX_BITS,
    Admit,
    Debit,
    Direction,
    Join,
    Message,
    MsgType,
    Return,
    ReturnAck,
    Telemetry,
)
from canergy.seqnum import unwrap

FD_MAC = 8
CLASSIC_MAC = 5
FV_MASK = 0xFFFF_FFFF
FD_LENGTHS = (12, 16, 20, 24, 32, 48, 64)
MAC_TYPE = {Direction.TO_CLIENT: 0x0, Direction.TO_SUPERVISOR: 0x8}
"""The two type codes no message uses carry the classic layout's MAC frames."""


def frame_direction(arbitration_id: int) -> Direction | None:
    """Which way a frame travels, by its type: a message's direction, or a classic MAC frame's
    (0x0 to a node, 0x8 to the supervisor); None for a type no frame uses."""
    kind = arbitration_id >> 8 & 0xF
    for direction, mac_kind in MAC_TYPE.items():
        if kind == mac_kind:
            return direction
    try:
        return MsgType(kind).direction
    except ValueError:
        return None


class Layout(Enum):
    FD = "fd"
    CLASSIC = "classic"


class AuthFailure(Enum):
    MAC_BAD = "MAC BAD"
    STALE = "freshness not the expected one"
    NO_DATA = "MAC frame without its message"
    MALFORMED = "malformed authenticated frame"
    UNAUTHENTICATED = "frame without a MAC"


class Expected(int):
    """The FV a side expects for a message (an ``int``, as ``FrameAuth.freshness`` returns it),
    with ``counter``: the side's own counter it was extended next to (its transaction for
    transaction frames, its return number for RETURN and RETURN_ACK; 32 bits). A verified frame
    whose FV is older than ``counter`` is refused as stale; a plain ``int`` checks the FV
    alone."""

    counter: int

    def __new__(cls, fv: int, counter: int) -> Expected:
        made = super().__new__(cls, fv)
        made.counter = counter & FV_MASK
        return made


def fv_before(a: int, b: int) -> bool:
    """FV ``a`` comes before ``b`` (serial-number order on 32 bits)."""
    return a != b and (b - a) & FV_MASK < 1 << 31


@functools.lru_cache(maxsize=256)
def _keyed(key: bytes) -> cmac.CMAC:
    """A CMAC with the key schedule done once; each MAC starts from a copy (~5x cheaper)."""
    return cmac.CMAC(algorithms.AES(key))


def mac(key: bytes, data_id: int, fv: int, data: bytes, join_fv: int | None = None) -> bytes:
    """The CMAC over Data ID || FV || data, and for ADMIT || the FV of the JOIN it answers
    (``join_fv``: both sides know it, so it is bound without travelling)."""
    c = _keyed(key).copy()
    c.update(data_id.to_bytes(2, "big") + (fv & 0xFFFF_FFFF).to_bytes(4, "big") + data)
    if join_fv is not None:
        c.update((join_fv & FV_MASK).to_bytes(4, "big"))
    return c.finalize()


def fd_length(n: int) -> int:
    return next(length for length in FD_LENGTHS if length >= n)


@dataclass
class Verdict:
    """What one received frame came to: a message to act on, a failure, or nothing yet."""

    message: Message | None = None
    failure: AuthFailure | None = None
    node: int | None = None


@dataclass
class FrameAuth:
    """Builds and checks authenticated frames for one side. ``key_for(node)`` gives a node's key;
    ``freshness(msg)`` the FV the side expects for a message (its own counters), None for a
    node it does not handle (such frames are left alone, as without a key)."""

    codec: Codec
    layout: Layout
    key_for: Callable[[int], bytes]
    receives: Direction
    freshness: Callable[[Message], int | None]
    pending: dict[int, tuple[Message, bytes]] = field(default_factory=dict)
    """Classic layout: per node, the message waiting for its MAC frame."""
    telemetry_floor: dict[int, int] = field(default_factory=dict)
    """Per node, the oldest TELEMETRY FV still fresh: the last transaction the node is known to
    have resolved (until one is known, the one before the side's own)."""
    join_fv: dict[int, int] = field(default_factory=dict)
    """Per node, the FV of its JOIN: a node sets its own (random high half, the JOIN's nonce
    below) before it joins; the supervisor keeps the one it received and echoes it in ADMIT.
    A replayed ADMIT of an earlier life then fails unless 32 bits, not 16, happen to match."""
    resume_fv: dict[int, int] = field(default_factory=dict)
    """Per node, the FV of its RESUME (witnessed rules), as ``join_fv`` for a JOIN: a random
    high half over the nonce, bound into the ADMIT that answers it. Kept until a JOIN or the
    next RESUME replaces it (an ADMIT is sent again for each copy of a RESUME)."""

    def frames(self, msg: Message) -> list[can.Message]:
        fv: int | None
        if isinstance(msg, Join):
            fv = self.join_fv[msg.node] = self._join_fv(msg)  # JOINING TELEMETRY is bound to it
        elif _resume(msg):
            fv = self.resume_fv.get(msg.node, msg.nonce)
            if fv & 0xFFFF != msg.nonce:
                fv = msg.nonce
        elif _joining(msg) and msg.node in self.join_fv:
            fv = self.join_fv[msg.node]  # a node without books: bound to its JOIN
        else:
            fv = self.freshness(msg)
        if fv is None:
            raise ValueError(f"no freshness for node {msg.node}: not one this side handles")
        arbitration_id, data = self.codec.encode(msg)
        bound = self._join_fv(msg) if isinstance(msg, Admit) else None
        tag = mac(self.key_for(msg.node), msg.TYPE << 8 | msg.node, fv, data, bound)
        if self.layout is Layout.FD:
            body = data + bytes(fd_length(len(data) + 12) - len(data) - 12)
            body += (fv & 0xFFFF_FFFF).to_bytes(4, "big") + tag[:FD_MAC]
            return [
                can.Message(
                    arbitration_id=arbitration_id, data=body, is_fd=True, bitrate_switch=True
                )
            ]
        mac_id = self.codec.id_base | MAC_TYPE[msg.TYPE.direction] << 8 | msg.node
        trailer = bytes([msg.TYPE]) + wire_half(msg, fv).to_bytes(2, "big") + tag[:CLASSIC_MAC]
        return [
            can.Message(arbitration_id=arbitration_id, data=data),
            can.Message(arbitration_id=mac_id, data=trailer),
        ]

    def accept(self, frame: can.Message) -> Verdict:
        """Check one frame. ``DecodeError`` for what the codec refuses, as without a key (a
        frame of the other direction: ``WRONG_DIRECTION``, for intrusion detection)."""
        kind = frame.arbitration_id >> 8 & 0xF
        data = bytes(frame.data)
        if self.layout is Layout.CLASSIC and kind in MAC_TYPE.values():
            if kind != MAC_TYPE[self.receives]:
                raise DecodeError(DecodeErrorReason.WRONG_DIRECTION, "MAC frame")
            return self._mac_frame(frame)
        if self.layout is Layout.CLASSIC:
            msg = self._decode(frame.arbitration_id, data)
            displaced = self.pending.get(msg.node)  # it never got its MAC frame: dropped, counted
            self.pending[msg.node] = (msg, data)
            if displaced is not None:
                return Verdict(failure=AuthFailure.UNAUTHENTICATED, node=msg.node)
            return Verdict(node=msg.node)  # nothing until its MAC frame
        try:
            length = self.codec.data_length(MsgType(kind))
        except (ValueError, KeyError):
            length = 0
        if not length or len(data) != fd_length(length + 12) or any(data[length:-12]):
            msg = self._decode(frame.arbitration_id, data)  # the codec's own error, if any
            return Verdict(failure=AuthFailure.UNAUTHENTICATED, node=msg.node)
        msg = self._decode(frame.arbitration_id, data[:length])
        fv = int.from_bytes(data[-12:-8], "big")
        return self._verdict(msg, data[:length], fv, data[-8:])

    def _decode(self, arbitration_id: int, data: bytes) -> Message:
        return self.codec.decode(arbitration_id, data, direction=self.receives)

    def _mac_frame(self, frame: can.Message) -> Verdict:
        node, data = frame.arbitration_id & 0xFF, bytes(frame.data)
        waiting = self.pending.pop(node, None)
        if len(data) != 1 + 2 + CLASSIC_MAC:
            return Verdict(failure=AuthFailure.MALFORMED, node=node)
        if waiting is None or data[0] != waiting[0].TYPE:
            return Verdict(failure=AuthFailure.NO_DATA, node=node)
        msg, body = waiting
        half = int.from_bytes(data[1:3], "big")
        if isinstance(msg, Telemetry):  # the low half, next to this side's own transaction
            wanted = self.join_fv.get(msg.node) if _joining(msg) else None
            wanted = self.freshness(msg) if wanted is None else wanted
            if wanted is None:
                return Verdict(node=msg.node)
            return self._verdict(msg, body, unwrap(half, int(wanted), 16) & FV_MASK, data[3:])
        return self._verdict(msg, body, half << 16 | low_counter(msg), data[3:])

    def _join_fv(self, msg: Join | Admit) -> int:
        """The FV of the JOIN (or, for an ADMIT, first the RESUME) a message goes with."""
        fv = self.resume_fv.get(msg.node) if isinstance(msg, Admit) else None
        if fv is None or fv & 0xFFFF != msg.nonce:
            fv = self.join_fv.get(msg.node)
        return fv if fv is not None and fv & 0xFFFF == msg.nonce else msg.nonce

    def _verdict(self, msg: Message, body: bytes, fv: int, tag: bytes) -> Verdict:
        wanted = self.freshness(msg)
        if wanted is None:  # another supervisor's node, say: not ours to judge
            return Verdict(node=msg.node)
        bound = None
        if isinstance(msg, Join) or _resume(msg):  # any fresh nonce: kept for the ADMIT
            wanted = fv if fv & 0xFFFF == msg.nonce else -1
        elif isinstance(msg, Admit):  # any high half, for the JOIN this side took or sent
            wanted = fv if fv & 0xFFFF == msg.nonce else -1
            bound = self._join_fv(msg)
        expected = mac(self.key_for(msg.node), msg.TYPE << 8 | msg.node, fv, body, bound)
        good = hmac.compare_digest(expected[: len(tag)], tag)
        if _joining(msg) and (good or self.layout is Layout.CLASSIC):
            # bound to the node's JOIN: taken for the JOIN this side took last; another one
            # (a JOIN not seen yet, as when this side started after it; a classic frame then
            # fails its MAC, extended next to another JOIN) moves nothing and proves nothing
            if good and self.join_fv.get(msg.node) == fv:
                return Verdict(message=msg, node=msg.node)
            return Verdict(node=msg.node)
        if not good:
            return Verdict(failure=AuthFailure.MAC_BAD, node=msg.node)
        if isinstance(msg, Telemetry):
            if self._stale_telemetry(msg.node, wanted, fv):
                return Verdict(failure=AuthFailure.STALE, node=msg.node)
        elif wanted & FV_MASK != fv or _older(wanted, fv):
            return Verdict(failure=AuthFailure.STALE, node=msg.node)
        if isinstance(msg, Join):
            self.join_fv[msg.node] = fv
            self.resume_fv.pop(msg.node, None)
        elif _resume(msg):
            self.resume_fv[msg.node] = fv
        if isinstance(msg, Admit):  # the full counters: the FV's high half above the wire's
            high = fv & 0xFFFF_0000
            msg = Admit(msg.node, msg.nonce, high | msg.tx, high | msg.seq)
        self._resolved(msg, fv)
        return Verdict(message=msg, node=msg.node)

    def _stale_telemetry(self, node: int, wanted: int, fv: int) -> bool:
        """Outside the window: older than the node is known to have resolved, or past this
        side's own transaction (``wanted``: a plain FV, a sender's, is not judged)."""
        if not isinstance(wanted, Expected):
            return False
        floor = self.telemetry_floor.get(node, (wanted.counter - 1) & FV_MASK)
        return fv_before(fv, floor) or fv_before(wanted.counter, fv)

    def _resolved(self, msg: Message, fv: int) -> None:
        """A verified frame that shows how far the node has resolved: TELEMETRY up to its FV,
        ACK to the transaction before, COMMITTED and ABORTED to theirs. Any but a JOIN shows
        the node has its books."""
        self.took(msg.TYPE, msg.node, fv)

    def took_waiting(self, node: int, fv: int) -> None:
        """The classic layout: the message waiting for ``node``'s MAC frame was verified with
        FV ``fv`` and taken elsewhere (the compiled core's frame path): it waits no more, and
        what it shows is noted (``took``)."""
        msg, _ = self.pending.pop(node)
        self.took(msg.TYPE, node, fv)

    def took(self, kind: MsgType, node: int, fv: int) -> None:
        """A verified frame of type ``kind`` from ``node`` with FV ``fv`` was taken (here, or
        by the compiled core's frame path, which verifies in C): what it shows (``_resolved``)
        is noted."""
        if self.receives is not Direction.TO_SUPERVISOR:
            return
        if kind != MsgType.JOIN:  # admitted: no TELEMETRY without books is fresh now
            self.join_fv.pop(node, None)
        if kind in (MsgType.TELEMETRY, MsgType.COMMITTED, MsgType.ABORTED):
            resolved = fv
        elif kind == MsgType.ACK:
            resolved = (fv - 1) & FV_MASK
        else:
            return
        floor = self.telemetry_floor.get(node)
        if floor is None or fv_before(floor, resolved):
            self.telemetry_floor[node] = resolved


def _resume(msg: Message) -> TypeGuard[Debit]:
    """A DEBIT that is a node's start (RESUME): its FV is a random high half over its nonce."""
    return isinstance(msg, Debit) and msg.is_resume


def _joining(msg: Message) -> bool:
    """A TELEMETRY of a node without books (JOIN sent, no ADMIT yet): its FV is its JOIN's."""
    return isinstance(msg, Telemetry) and bool(msg.flags & Telemetry.JOINING)


def _older(wanted: int, fv: int) -> bool:
    """A verified FV below the receiver's own counter: a replay of an earlier transaction or
    return (at the counter: a current duplicate, which the protocol tolerates)."""
    return isinstance(wanted, Expected) and fv_before(fv, wanted.counter)


def _started(msg: Message) -> TypeGuard[Debit]:
    """A DEBIT whose FV is its nonce: a node's start (RESUME), or the books or counts answering
    a supervisor's SYNC (bound to that SYNC by its nonce; the books' ``seq`` is Rc, no debit
    number, so a count would refuse them as stale once Rc's low 16 bits fall below it)."""
    return isinstance(msg, Debit) and (msg.is_resume or msg.is_books)


def low_counter(msg: Message) -> int:
    """The FV's low half, which the frame itself carries (TELEMETRY's is 0)."""
    return freshness(msg, 0, 0) & 0xFFFF


def wire_half(msg: Message, fv: int) -> int:
    """The half of the FV a classic MAC frame carries: the high half, which the message does
    not; TELEMETRY carries no counter, so its MAC frame carries the low half."""
    return fv & 0xFFFF if isinstance(msg, Telemetry) else fv >> 16 & 0xFFFF


def freshness(msg: Message, tx: int, seq: int) -> int:
    """The FV of ``msg`` for a side whose own counters are ``tx`` and ``seq``: the wire's 16-bit
    counter extended next to them (serial-number arithmetic), 32 bits."""
    if isinstance(msg, Join) or _started(msg):
        return msg.nonce
    if isinstance(msg, Admit):  # the high half its counters share: k's, extended next to tx
        return unwrap(msg.tx, tx, TX_BITS) & 0xFFFF_0000 | msg.nonce
    if isinstance(msg, Telemetry):
        return tx & FV_MASK
    if isinstance(msg, Return | ReturnAck | Debit):  # a draw is numbered as a return
        return unwrap(msg.seq, seq, SEQ_BITS) & 0xFFFF_FFFF
    return unwrap(msg.tx, tx, TX_BITS) & 0xFFFF_FFFF


def expected_freshness(msg: Message, tx: int, seq: int) -> int:
    """``freshness``, for a side whose frames a ``FrameAuth`` checks: for the frames of a
    transaction or a return an ``Expected`` that knows the side's counter, so that a verified
    frame older than it is refused as stale; for TELEMETRY, the side's transaction ``tx``, the
    newest FV it takes (JOIN and ADMIT: the plain FV)."""
    fv = freshness(msg, tx, seq)
    if isinstance(msg, Join | Admit) or _started(msg):
        return fv
    return Expected(fv, seq if isinstance(msg, Return | ReturnAck | Debit) else tx)
