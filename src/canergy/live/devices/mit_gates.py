"""The gates of a set of MIT-mode motors and how a frame reaches them: one piece, used by
``MitBus`` (in the application's process, ``canergy inline``) and by the supervisor that hosts
the gates itself (``canergy.live.devices.mit_host``). Not thread-safe: the caller serialises.

``from_app`` judges a frame of the application's (a guarded motor's id: its gate forwards,
clamps or refuses it; a frame that reaches a guarded motor outside MIT mode, or a remote frame to
one, is refused; anything else passes); ``from_bus`` hands a frame heard on the motors' bus to
the gates it concerns (a reply, a frame to the motor from someone else); ``outgoing`` is what the
gates themselves send to the motors. Refusals are counted by the gate and logged (the first of a
motor and every 100th, with the reason).

Every frame ``from_app`` judges is counted (``taken``): it is then one of a gate's forwarded,
clamped or refused, or ``passed`` (not for a guarded motor), so that they add up.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import can

from canergy.core import Timing
from canergy.devices.mit import PARAMETER_ID, default_master, reply_collision, side_channel
from canergy.devices.mit_gate import MitGate
from canergy.live.devices.mit_motor import MitMotor, gate_for
from canergy.messages import Message

log = logging.getLogger("canergy.live.devices.mit_bus")


class MitGates:
    """The gates of ``motors``, by motor id, with their replies' identifiers."""

    def __init__(
        self,
        motors: Sequence[MitMotor],
        now: int,
        timing: Timing | None = None,
        guard_config: dict[str, Any] | None = None,
    ) -> None:
        self.gates: dict[int, MitGate] = {}
        self.master: dict[int, int] = {}
        """Each motor's replies' identifier."""
        for m in motors:
            gate = gate_for(m, now, timing or Timing(), guard_config)
            if m.motor_id in self.gates or m.node in {g.guard.node for g in self.gates.values()}:
                raise ValueError(f"motor {m.motor_id} or node {m.node} given twice")
            self.gates[m.motor_id] = gate
            master = m.master_id
            self.master[m.motor_id] = (
                default_master(gate.model, m.motor_id) if master is None else master
            )
        if (why := reply_collision(self.master)) is not None:
            raise ValueError(why)
        self.by_node = {g.guard.node: g for g in self.gates.values()}
        self.taken = 0
        """Frames of the application's judged by ``from_app``."""
        self.passed = 0
        """Of those, frames for no guarded motor (sent unchanged)."""

    def side(self, frame: can.Message, gate: MitGate | None = None) -> tuple[MitGate, str] | None:
        """The motor (of all, or ``gate``) a frame reaches outside MIT mode, and how."""
        for g in self.gates.values() if gate is None else (gate,):
            why = side_channel(g.model, g.motor_id, frame.arbitration_id, frame.is_extended_id)
            if why is not None:
                return g, why
        return None

    def from_app(self, frame: can.Message, now: int) -> tuple[can.Message | None, str | None]:
        """What to send for a frame of the application's: itself or clamped, or None and why
        (refused, counted by the motor's gate)."""
        self.taken += 1
        if (side := self.side(frame)) is not None and not frame.is_error_frame:
            return None, self.refused(side[0], side[1])
        gate = None if frame.is_extended_id else self.gates.get(frame.arbitration_id)
        if gate is None or frame.is_error_frame:
            self.passed += 1
            return frame, None
        if frame.is_remote_frame:  # what a firmware makes of one is not documented: not sent
            return None, self.refused(gate, "remote frame")
        verdict = gate.from_app(bytes(frame.data), now)
        if verdict.frame is None:
            return None, self.refused(gate, verdict.why or "refused", counted=True)
        out = can.Message(
            arbitration_id=frame.arbitration_id, data=verdict.frame, is_extended_id=False
        )
        return out, None

    def refused(self, gate: MitGate, why: str, counted: bool = False) -> str:
        """A frame of the application's for ``gate``'s motor not sent: counted and logged; the
        refusal in words."""
        if not counted:
            gate.refuse(why)
        n = gate.counts.refused
        if n == 1 or n % 100 == 0:
            log.warning(
                "MIT motor %d: command refused (%s); %d refused so far", gate.motor_id, why, n
            )
        return f"MIT motor {gate.motor_id}: command refused ({why})"

    def from_bus(self, frame: can.Message, now: int, gate: MitGate | None = None) -> list[Message]:
        """A frame heard on the motors' bus (not canergy's), for every gate it concerns (or
        ``gate`` alone): what the gates' guards send the supervisor."""
        if frame.is_error_frame:
            return []
        out: list[Message] = []
        if (side := self.side(frame, gate)) is not None:
            out += side[0].on_foreign(bytes(frame.data), now)
        if frame.is_extended_id:
            return out
        at = now
        if frame.timestamp > 0:
            at -= max(0, min(round((time.time() - frame.timestamp) * 1e6), 1_000_000))
        for g in self.gates.values() if gate is None else (gate,):
            if frame.arbitration_id == self.master[g.motor_id]:
                out += g.from_motor(bytes(frame.data), at, now)
            if frame.arbitration_id == g.motor_id:
                out += g.on_foreign(bytes(frame.data), now)
        return out

    def unseen(self, why: str, now: int) -> list[Message]:
        """Frames of the motors' bus were lost before the gates saw them (``why``): every
        motor stopped for good, as for a frame from another sender."""
        out: list[Message] = []
        for g in self.gates.values():
            out += g.on_unseen(why, now)
        return out

    def outgoing(self, gate: MitGate | None = None) -> list[can.Message]:
        """The frames the gates (or ``gate``) send the motors themselves, in order (a
        register read to Damiao's 0x7FF first)."""
        gates = list(self.gates.values() if gate is None else (gate,))
        return [
            can.Message(arbitration_id=PARAMETER_ID, data=data, is_extended_id=False)
            for g in gates
            for data in g.take_parameter_frames()
        ] + [
            can.Message(arbitration_id=g.motor_id, data=data, is_extended_id=False)
            for g in gates
            for data in g.take_frames()
        ]
