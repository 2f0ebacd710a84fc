"""Names for the frames of the drives and motors canergy guards: ODrive's CAN Simple, moteus's
register protocol (CAN FD) and MIT-mode motors, decoded by the profiles' own codecs
(``canergy.devices``). The caller knows which ids are whose (``--odrive-names``,
``--moteus-names``, ``--mit-names``). A frame of a known kind whose data does not decode keeps
its name and says why (``Named.problem``); nothing here raises on a frame's data.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any

from canergy.devices import mit as mitdev
from canergy.devices import moteus as moteusdev
from canergy.devices.odrive import Cmd, split_id
from canergy.inspect.named import Named

# -- ODrive CAN Simple --------------------------------------------------------------------------

_TWO_FLOATS = {
    Cmd.ENCODER_ESTIMATES: ("pos_rev", "vel_rev_s"),
    Cmd.SET_LIMITS: ("vel_limit_rev_s", "current_limit_a"),
    Cmd.GET_IQ: ("iq_setpoint_a", "iq_measured_a"),
    Cmd.BUS_VOLTAGE_CURRENT: ("bus_voltage_v", "bus_current_a"),
    Cmd.POWERS: ("electrical_w", "mechanical_w"),
}
_LEAST: dict[int, int] = {Cmd.HEARTBEAT: 5, Cmd.SET_AXIS_STATE: 4}
"""The fewest bytes of the other commands whose fields are shown."""


def odrive(arbitration_id: int, data: bytes, remote: bool) -> Named:
    """A CAN Simple frame (the caller knows the node is an ODrive's)."""
    node, cmd = split_id(arbitration_id)
    try:
        name = Cmd(cmd).name.lower()
    except ValueError:
        name = f"command 0x{cmd:02X}"
    if remote:
        return Named("odrive", name, node, {"request": True})
    fields: dict[str, Any] = {}
    least = 8 if cmd in _TWO_FLOATS else _LEAST.get(cmd, 0)
    if len(data) < least:
        return Named("odrive", name, node, problem=f"dlc {len(data)}, {least} expected")
    if cmd in _TWO_FLOATS:
        first, second = struct.unpack_from("<ff", data)
        fields = dict(zip(_TWO_FLOATS[Cmd(cmd)], (first, second), strict=True))
    elif cmd == Cmd.HEARTBEAT:
        fields = {"axis_error": f"0x{struct.unpack_from('<I', data)[0]:08X}", "state": data[4]}
    elif cmd == Cmd.SET_AXIS_STATE:
        fields = {"state": struct.unpack_from("<I", data)[0]}
    return Named("odrive", name, node, fields)


# -- moteus -------------------------------------------------------------------------------------


def _register(number: int) -> str:
    try:
        return moteusdev.Reg(number).name.lower()
    except ValueError:
        return f"0x{number:03x}"


def _value(register: int, value: float) -> float | str:
    """A register's value; the mode register's by the mode's name."""
    if register == moteusdev.Reg.MODE and value.is_integer():
        try:
            return moteusdev.Mode(int(value)).name.lower()
        except ValueError:
            pass
    return value


def _put(fields: dict[str, Any], key: str, value: Any) -> None:
    """``fields[key] = value``; a key already there gets ``value`` joined to it."""
    fields[key] = value if key not in fields else f"{fields[key]}, {value}"


def _subframe(fields: dict[str, Any], s: moteusdev.Subframe) -> None:
    if isinstance(s, moteusdev.Write | moteusdev.Reply):
        for i, v in enumerate(s.values):
            _put(fields, _register(s.start + i), _value(s.start + i, v))
    elif isinstance(s, moteusdev.Read):
        last = f"..{_register(s.start + s.count - 1)}" if s.count > 1 else ""
        _put(fields, "read", f"{_register(s.start)}{last} ({s.kind.name.lower()})")
    elif isinstance(s, moteusdev.Error):
        _put(fields, "read error" if s.read else "write error", f"{_register(s.register)} {s.code}")
    elif isinstance(s, moteusdev.Stream):
        _put(fields, f"channel {s.channel}", repr(s.data)[2:-1])
    else:
        _put(fields, f"poll channel {s.channel}", s.most)


def moteus(arbitration_id: int, data: bytes, controllers: frozenset[int]) -> Named | None:
    """A frame from or to one of the moteus ``controllers`` (ids), its subframes named: the
    registers written, read or replied with their names and values in units, errors, diagnostic
    stream text (None: neither end is one of them)."""
    if arbitration_id & 0x80:
        return None  # between the two 7-bit ids: a bit moteus never sets
    source, destination, reply, prefix = moteusdev.split_id(arbitration_id)
    node: int | None
    fields: dict[str, Any]
    if source in controllers and destination not in controllers:
        name, node, fields = "reply", source, {"to": destination}
    elif destination in controllers or (destination == moteusdev.BROADCAST and controllers):
        node = None if destination == moteusdev.BROADCAST else destination
        name, fields = "command", {"from": source}
        if node is None:
            fields["to"] = "all"
        if reply:
            fields["reply asked"] = True
    else:
        return None
    if prefix:
        fields["prefix"] = f"0x{prefix:04X}"
    subframes, why = moteusdev.decode(data)
    for s in subframes:
        _subframe(fields, s)
    return Named("moteus", name, node, fields, None if why is None else f"not decoded: {why}")


# -- MIT-mode motors ----------------------------------------------------------------------------


class MitNames:
    """Names frames to and from MIT-mode motors, each by its own model's ranges: commands in
    units (p rad, v rad/s, kp N·m/rad, kd N·m·s/rad, t_ff N·m), the special frames, and replies
    (position, velocity, torque; Damiao: the state) on each motor's default reply identifier
    (``canergy.devices.mit.default_master``)."""

    def __init__(self, models: Mapping[int, mitdev.MitModel]) -> None:
        self.models = dict(models)
        self.motors = frozenset(self.models)
        self.masters: dict[int, list[int]] = {}
        for m in sorted(self.motors):
            self.masters.setdefault(mitdev.default_master(self.models[m], m), []).append(m)

    def name(self, arbitration_id: int, extended: bool, data: bytes) -> Named | None:
        if not extended and arbitration_id in self.motors:
            return self._command(arbitration_id, data)
        if not extended and arbitration_id in self.masters and len(data) >= 6:
            for m in self.masters[arbitration_id]:
                model = self.models[m]
                reply = mitdev.unpack_reply(model, data)
                if (m & 0xF if model.damiao else m) == reply.node:
                    return self._reply(m, reply)
        for m in sorted(self.motors):  # frames that reach a motor outside MIT mode
            why = mitdev.side_channel(self.models[m], m, arbitration_id, extended)
            if why is not None:
                return Named("mit", "not MIT", m, {"frame": why})
        return None

    def _command(self, motor: int, data: bytes) -> Named:
        if len(data) != 8:
            return Named("mit", "command", motor, problem=f"dlc {len(data)}, 8 expected")
        if data in mitdev.SPECIAL:
            return Named("mit", mitdev.SPECIAL[data], motor)
        v = mitdev.decode(self.models[motor], mitdev.Command.unpack(data))
        fields = {"p_rad": v.p, "v_rad_s": v.v, "kp": v.kp, "kd": v.kd, "t_ff_nm": v.t}
        return Named("mit", "command", motor, {k: float(x) for k, x in fields.items()})

    def _reply(self, motor: int, reply: mitdev.Reply) -> Named:
        fields: dict[str, Any] = {
            "p_rad": float(reply.p),
            "v_rad_s": float(reply.v),
            "torque_nm": float(reply.torque),
        }
        if reply.state is not None:
            fields["state"] = reply.state
        return Named("mit", "reply", motor, fields)
