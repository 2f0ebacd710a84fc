"""Build ``dbc/canergy.dbc`` from the codec's layouts with cantools (one message per node/type),
and the authenticated layouts (``canergy-auth-fd.dbc``, ``canergy-auth-classic.dbc``)."""

from __future__ import annotations

from typing import Any, Literal

import cantools.database
from cantools.database.can import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion

from canergy.auth.frames import MAC_TYPE, fd_length
from canergy.codec import LAYOUTS, Codec
from canergy.messages import MAX_NODE, MIN_NODE, QUANTUM_UJ, Direction, MsgType

_SIGNALS: dict[MsgType, list[tuple[str, int, int, float, str]]] = {
    # name, start bit, length, scale, unit (CRC is byte 0 of every message)
    MsgType.INTENTION: [
        ("TX", 8, 16, 1, ""),
        ("AMOUNT", 24, 16, 0.001, "J"),
        ("DELIVERED", 40, 24, 0.001, "J"),
    ],
    MsgType.COMMIT: [("TX", 8, 16, 1, ""), ("AMOUNT", 24, 16, 0.001, "J")],
    MsgType.ABORT: [("TX", 8, 16, 1, ""), ("AMOUNT", 24, 16, 0.001, "J")],
    MsgType.RETURN_ACK: [("SEQ", 8, 16, 1, "")],
    MsgType.STATUS_REQUEST: [("TX", 8, 16, 1, "")],
    MsgType.FINAL_ACK: [("TX", 8, 16, 1, "")],
    MsgType.ACK: [("TX", 8, 16, 1, "")],
    MsgType.COMMITTED: [("TX", 8, 16, 1, "")],
    MsgType.ABORTED: [("TX", 8, 16, 1, "")],
    MsgType.RETURN: [("SEQ", 8, 16, 1, ""), ("AMOUNT", 24, 16, 0.001, "J")],
    MsgType.TELEMETRY: [
        ("LEVEL", 8, 24, 0.001, "J"),
        ("FLAGS", 32, 8, 1, ""),
        ("RETURN_SEQ", 40, 16, 1, ""),
        ("WITNESS", 56, 8, 1, ""),
    ],
    MsgType.JOIN: [("NONCE", 8, 16, 1, "")],
    MsgType.ADMIT: [("NONCE", 8, 16, 1, ""), ("TX", 24, 16, 1, ""), ("SEQ", 40, 16, 1, "")],
    MsgType.DEBIT: [
        ("NONCE", 8, 16, 1, ""),
        ("DEBIT_FLAGS", 24, 8, 1, ""),
        ("SEQ", 32, 16, 1, ""),
        ("AMOUNT", 48, 16, 0.001, "J"),
    ],
}
assert QUANTUM_UJ == 1000  # the 0.001 J scale above is one wire quantum

_COMMENTS = {
    "CRC": "E2E CRC-8 SAE J1850 over Data ID (type<<8|node, low byte first) and bytes 1..n",
    "TX": "transaction id, 16-bit wrapping",
    "SEQ": "return number, 16-bit wrapping",
    "AMOUNT": "energy in whole millijoules",
    "DELIVERED": "Gs: energy counted as delivered to this node, 24-bit wrapping mJ",
    "LEVEL": "client's usable energy in mJ, saturating at 16777.215 J (information only)",
    "FLAGS": (
        "bit 0: level low; bit 1: actuator halted; bit 2: no books, joining; bit 3: the "
        "witnessed client rules (absent: hardened; a supervisor with other rules grants nothing)"
    ),
    "RETURN_SEQ": "the node's current return number (as its RETURN frames carry it)",
    "WITNESS": "frames the node saw in its own name that it did not send, modulo 256",
    "NONCE": (
        "random number drawn at a start (a node's JOIN or RESUME, a supervisor's SYNC, which "
        "is an ADMIT a node did not ask for); the answer echoes it"
    ),
    "DEBIT_FLAGS": (
        "0x01: a draw for the actuator; 0x02: the node's start (RESUME; 0x03: its pending "
        "debit is a draw); 0x06: a SYNC's counts (SEQ, and ltx in AMOUNT's bits); 0x16: "
        "the counts of a node admitted afresh that has taken no fresh intention since; 0x08: a "
        "SYNC's books (Rc in mJ: low 16 bits in SEQ, high 8 in AMOUNT's bits); 0x18: a SYNC's "
        "books when the node knows no Rc (admitted, no fresh intention since; SEQ and AMOUNT "
        "0); nothing else"
    ),
    "FV": "freshness value: the full 32-bit tx (or return number, or nonce) the MAC covers",
    "MAC": "AES-128-CMAC over Data ID, FV and the classic data, truncated (SecOC-like)",
    "MSG_TYPE": "type code of the message this MAC frame authenticates",
    "FV_HALF": (
        "high 16 bits of the freshness value (the low 16 travel in the message); "
        "for TELEMETRY, which carries no counter, the low 16 bits"
    ),
}


def _signal(
    name: str,
    start: int,
    length: int,
    scale: float,
    unit: str,
    order: Literal["little_endian", "big_endian"] = "little_endian",
) -> Signal:
    conversion = BaseConversion.factory(scale=scale, offset=0, is_float=False)
    return Signal(
        name,
        start,
        length,
        order,
        False,
        conversion=conversion,
        minimum=0,
        maximum=((1 << length) - 1) * scale,
        unit=unit or None,
        comment=_COMMENTS[name],
    )


def _big_endian(name: str, byte: int, length: int) -> Signal:
    """A big-endian signal whose most significant byte is ``byte`` (DBC's Motorola start bit)."""
    return _signal(name, byte * 8 + 7, length, 1, "", "big_endian")


def _sender(msg_type: MsgType, node: int) -> str:
    return "SUPERVISOR" if msg_type.direction is Direction.TO_CLIENT else f"NODE_{node}"


def _message(codec: Codec, msg_type: MsgType, node: int, fd: bool = False) -> Message:
    signals = [_signal("CRC", 0, 8, 1, "")] + [_signal(*s) for s in _SIGNALS[msg_type]]
    length = LAYOUTS[msg_type].dlc
    if fd:  # data, zero padding, FV (4), MAC (8)
        length = fd_length(length + 12)
        signals += [_big_endian("FV", length - 12, 32), _big_endian("MAC", length - 8, 64)]
    return Message(
        frame_id=codec.arbitration_id(msg_type, node),
        name=f"{msg_type.name}_N{node}",
        length=length,
        signals=signals,
        senders=[_sender(msg_type, node)],
        is_extended_frame=True,
        is_fd=fd,
        comment=f"canergy {msg_type.name} for node {node}",
    )


def _mac_message(codec: Codec, direction: Direction, node: int) -> Message:
    """Classic authenticated layout: the MAC frame that follows every message."""
    kind = MAC_TYPE[direction]
    name = "MAC_TO_NODE" if direction is Direction.TO_CLIENT else "MAC_FROM_NODE"
    return Message(
        frame_id=codec.id_base | kind << 8 | node,
        name=f"{name}_N{node}",
        length=8,
        signals=[
            _signal("MSG_TYPE", 0, 8, 1, ""),
            _big_endian("FV_HALF", 1, 16),
            _big_endian("MAC", 3, 40),
        ],
        senders=["SUPERVISOR" if direction is Direction.TO_CLIENT else f"NODE_{node}"],
        is_extended_frame=True,
        comment=f"canergy MAC frame ({direction.name.lower()}) for node {node}",
    )


def build_database(id_base: int, auth: str | None = None) -> Any:
    """``auth``: None (plain), ``fd`` or ``classic`` (the authenticated layouts)."""
    codec = Codec(id_base)
    ids = range(MIN_NODE, MAX_NODE + 1)
    nodes = [Node("SUPERVISOR", None)] + [Node(f"NODE_{n}", None) for n in ids]
    messages = [_message(codec, t, n, fd=auth == "fd") for t in MsgType for n in ids]
    if auth == "classic":
        messages += [_mac_message(codec, d, n) for d in Direction for n in ids]
    version = "canergy 1" if auth is None else f"canergy 1 auth {auth}"
    return Database(messages=messages, nodes=nodes, version=version)


def dbc_text(id_base: int, auth: str | None = None) -> str:
    """The DBC file for ``id_base``; loads back with ``cantools.database.load_file``."""
    text: str = build_database(id_base, auth).as_dbc_string()
    cantools.database.load_string(text, database_format="dbc")  # fail here, not at the user
    return text
