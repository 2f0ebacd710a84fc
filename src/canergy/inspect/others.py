"""Names for the frames on a bench bus that are not canergy's: a user's DBC files, the drives'
and motors' protocols (ODrive CAN Simple, moteus, MIT mode: ``canergy.inspect.drives``) and
CANopen (the CiA 402 drives' NMT, SYNC, EMCY, PDOs, SDOs and heartbeats), so that ``canergy
dump``, ``decode``, ``audit`` and ``monitor`` read a bus with nodes, drives and motors as one
stream.

Order: a DBC that defines the identifier names the frame (the user's word wins); then CAN
Simple for the ODrive node ids given; then MIT mode for the motor ids given (commands to them,
replies on their reply identifiers); then moteus for the controller ids given (frames from or
to them); then CANopen by its predefined connection set (11-bit identifiers only). A frame none
of them knows stays unnamed. Data that does not decode (too short, a subframe that does not
parse, a multiplexer value a DBC lacks) gives the message's name with the reason, never an
error, and is counted apart (``protocol_of``).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from canergy.devices.mit import MitModel
from canergy.devices.odrive import split_id
from canergy.inspect.drives import MitNames, moteus, odrive
from canergy.inspect.named import Named

__all__ = ["Dbc", "DbcError", "Named", "Namer", "canopen", "protocol_of", "tally"]


class DbcError(ValueError):
    """A ``--dbc`` file that cantools cannot read."""


@dataclass(frozen=True, slots=True)
class Dbc:
    """One DBC file, loaded by cantools."""

    path: Path
    database: Any

    @classmethod
    def load(cls, text: str) -> Dbc:
        """The argparse type of ``--dbc FILE``."""
        import cantools.database  # only where a DBC is given

        path = Path(text)
        named = text if len(text) <= 60 else "..." + text[-57:]
        try:
            database = cantools.database.load_file(str(path), database_format="dbc")
        except OSError as exc:
            raise DbcError(f"{named}: {exc.strerror or exc}") from None
        except Exception as exc:  # cantools raises its parsers' own errors
            why = str(exc).splitlines()[0][:80] if str(exc) else type(exc).__name__
            raise DbcError(f"{named}: not a DBC cantools reads ({why})") from None
        return cls(path, database)

    def name(self, arbitration_id: int, extended: bool, data: bytes) -> Named | None:
        try:
            message = self.database.get_message_by_frame_id(arbitration_id)
        except KeyError:
            return None
        if bool(message.is_extended_frame) != extended:
            return None
        protocol = f"dbc:{self.path.name}"
        try:
            signals = message.decode(data, decode_choices=True, allow_truncated=False)
        except Exception as exc:  # cantools: DecodeError, ValueError, KeyError by version
            return Named(protocol, message.name, problem=f"not decoded: {exc}")
        return Named(protocol, message.name, fields=dict(signals))


# -- CANopen: the predefined connection set -----------------------------------------------------

_NMT = {0x01: "start", 0x02: "stop", 0x80: "pre-operational", 0x81: "reset", 0x82: "reset comm"}
_STATES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
_PDO_BASES = {
    0x180: "TPDO1",
    0x200: "RPDO1",
    0x280: "TPDO2",
    0x300: "RPDO2",
    0x380: "TPDO3",
    0x400: "RPDO3",
    0x480: "TPDO4",
    0x500: "RPDO4",
}
_REQUESTS = {0: "download segment", 1: "download", 2: "upload", 3: "upload segment", 4: "abort"}
_ANSWERS = {0: "upload segment", 1: "download segment ok", 2: "upload", 3: "download ok"}
_ANSWERS[4] = "abort"


def _object(data: bytes) -> str:
    index, sub = struct.unpack_from("<HB", data, 1)
    return f"0x{index:04X}:{sub:02X}"


def _sdo(data: bytes, request: bool) -> tuple[str, dict[str, Any]]:
    """An SDO's command and, where the frame carries them, its object and expedited value."""
    if len(data) != 8:
        return "SDO", {"dlc": len(data)}
    command = data[0] >> 5
    fields: dict[str, Any] = {"command": (_REQUESTS if request else _ANSWERS).get(command, command)}
    initiate = (request and command in (1, 2)) or (not request and command in (2, 3))
    if initiate or command == 4:
        fields["object"] = _object(data)
    expedited = data[0] & 0x02 and ((request and command == 1) or (not request and command == 2))
    if expedited:
        size = 4 - (data[0] >> 2 & 0x03) if data[0] & 0x01 else 4
        fields["value"] = f"0x{int.from_bytes(data[4 : 4 + size], 'little'):0{2 * size}X}"
    if command == 4:
        fields["code"] = f"0x{struct.unpack_from('<I', data, 4)[0]:08X}"
    return f"SDO {'request' if request else 'answer'}", fields


def canopen(arbitration_id: int, data: bytes) -> Named | None:
    """The frame by CiA 301's predefined connection set, or None."""
    cob, node = arbitration_id & 0x780, arbitration_id & 0x07F
    if arbitration_id == 0x000:
        if len(data) < 2:
            return Named("canopen", "NMT", problem=f"dlc {len(data)}")
        target = "all" if data[1] == 0 else data[1]
        return Named("canopen", "NMT", fields={"command": _NMT.get(data[0], data[0]), "to": target})
    if arbitration_id == 0x080:
        return Named("canopen", "SYNC", fields={"counter": data[0]} if data else {})
    if arbitration_id == 0x100:
        return Named("canopen", "TIME")
    if node == 0:
        return None
    if cob == 0x080:
        if len(data) < 3:
            return Named("canopen", "EMCY", node, problem=f"dlc {len(data)}")
        fields = {"code": f"0x{data[0] | data[1] << 8:04X}", "register": f"0x{data[2]:02X}"}
        return Named("canopen", "EMCY", node, fields)
    if cob in _PDO_BASES:
        return Named("canopen", _PDO_BASES[cob], node)
    if cob in (0x580, 0x600):
        name, fields = _sdo(data, request=cob == 0x600)
        return Named("canopen", name, node, fields)
    if cob == 0x700:
        state = _STATES.get(data[0] & 0x7F, data[0]) if data else "?"
        return Named("canopen", "heartbeat", node, {"state": state})
    return None


def protocol_of(named: Named | None) -> str:
    """The protocol a count of foreign frames puts the frame under: ``canopen``, ``odrive``,
    ``moteus``, ``mit``, ``dbc`` (any DBC's), each with `` undecodable`` for its frames whose
    data does not decode, or ``unknown``."""
    if named is None:
        return "unknown"
    protocol = named.protocol.split(":")[0]
    return protocol if named.problem is None else f"{protocol} undecodable"


def tally(counts: dict[str, int]) -> str:
    """``(canopen 1,000, unknown 34)``: the counts by protocol, largest first ("" if none)."""
    if not counts:
        return ""
    parts = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    return " (" + ", ".join(f"{k} {v:,}" for k, v in parts) + ")"


class Namer:
    """Names the frames canergy's codec does not claim (see the module doc)."""

    def __init__(
        self,
        dbcs: Iterable[Dbc] = (),
        *,
        odrive_nodes: Iterable[int] = (),
        moteus_nodes: Iterable[int] = (),
        mit_nodes: Iterable[int] = (),
        mit_model: MitModel | None = None,
        mit_models: Mapping[int, MitModel] | None = None,
        canopen_names: bool = True,
    ) -> None:
        """MIT-mode motors: ``mit_models`` (each id's model), or ``mit_nodes`` all of
        ``mit_model``."""
        self.dbcs = tuple(dbcs)
        self.odrive_nodes = frozenset(odrive_nodes)
        self.moteus_nodes = frozenset(moteus_nodes)
        models = dict(mit_models or {})
        mit = frozenset(mit_nodes)
        if mit and mit_model is None:
            raise ValueError("--mit-names needs --mit-model (the motors' ranges)")
        if mit_model is not None:
            models.update((m, mit_model) for m in mit)
        self.mit = MitNames(models) if models else None
        self.canopen_names = canopen_names

    def named(self, frame: Any) -> Named | None:
        """``name`` of a described frame (``canergy.inspect.frames.Described``)."""
        return self.name(frame.arbitration_id, frame.extended, frame.remote, frame.data)

    def name(self, arbitration_id: int, extended: bool, remote: bool, data: bytes) -> Named | None:
        for dbc in () if remote else self.dbcs:
            named = dbc.name(arbitration_id, extended, data)
            if named is not None:
                return named
        if not extended and split_id(arbitration_id)[0] in self.odrive_nodes:
            return odrive(arbitration_id, data, remote)
        if remote:
            return None if extended or not self.canopen_names else canopen(arbitration_id, data)
        if self.mit is not None and (named := self.mit.name(arbitration_id, extended, data)):
            return named
        if self.moteus_nodes and (named := moteus(arbitration_id, data, self.moteus_nodes)):
            return named
        return canopen(arbitration_id, data) if self.canopen_names and not extended else None
