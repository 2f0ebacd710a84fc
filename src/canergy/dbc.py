"""Build ``dbc/canergy.dbc`` from the codec's layouts with cantools (one message per node/type)."""

from __future__ import annotations

from typing import Any

import cantools.database
from cantools.database.can import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion

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
    MsgType.TELEMETRY: [("LEVEL", 8, 24, 0.001, "J"), ("FLAGS", 32, 8, 1, "")],
    MsgType.JOIN: [("NONCE", 8, 16, 1, "")],
    MsgType.ADMIT: [("NONCE", 8, 16, 1, ""), ("TX", 24, 16, 1, ""), ("SEQ", 40, 16, 1, "")],
}
assert QUANTUM_UJ == 1000  # the 0.001 J scale above is one wire quantum

_COMMENTS = {
    "CRC": "E2E CRC-8 SAE J1850 over Data ID (type<<8|node, low byte first) and bytes 1..n",
    "TX": "transaction id, 16-bit wrapping",
    "SEQ": "return number, 16-bit wrapping",
    "AMOUNT": "energy in whole millijoules",
    "DELIVERED": "Gs: energy counted as delivered to this node, 24-bit wrapping mJ",
    "LEVEL": "client's usable energy in mJ, saturating at 16777.215 J (information only)",
    "FLAGS": "bit 0: level low; bit 1: actuator halted; bit 2: no books, joining",
    "NONCE": "random number drawn by a node that starts without books; ADMIT echoes it",
}


def _signal(name: str, start: int, length: int, scale: float, unit: str) -> Signal:
    conversion = BaseConversion.factory(scale=scale, offset=0, is_float=False)
    return Signal(
        name,
        start,
        length,
        "little_endian",
        False,
        conversion=conversion,
        minimum=0,
        maximum=((1 << length) - 1) * scale,
        unit=unit or None,
        comment=_COMMENTS[name],
    )


def _message(codec: Codec, msg_type: MsgType, node: int) -> Message:
    sender = "SUPERVISOR" if msg_type.direction is Direction.TO_CLIENT else f"NODE_{node}"
    signals = [_signal("CRC", 0, 8, 1, "")] + [_signal(*s) for s in _SIGNALS[msg_type]]
    return Message(
        frame_id=codec.arbitration_id(msg_type, node),
        name=f"{msg_type.name}_N{node}",
        length=LAYOUTS[msg_type].dlc,
        signals=signals,
        senders=[sender],
        is_extended_frame=True,
        comment=f"canergy {msg_type.name} for node {node}",
    )


def build_database(id_base: int) -> Any:
    codec = Codec(id_base)
    nodes = [Node("SUPERVISOR", None)] + [
        Node(f"NODE_{n}", None) for n in range(MIN_NODE, MAX_NODE + 1)
    ]
    messages = [_message(codec, t, n) for t in MsgType for n in range(MIN_NODE, MAX_NODE + 1)]
    return Database(messages=messages, nodes=nodes, version="canergy 1")


def dbc_text(id_base: int) -> str:
    """The DBC file for ``id_base``; loads back with ``cantools.database.load_file``."""
    text: str = build_database(id_base).as_dbc_string()
    cantools.database.load_string(text, database_format="dbc")  # fail here, not at the user
    return text
