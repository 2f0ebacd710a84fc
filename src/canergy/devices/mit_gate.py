"""One MIT-mode motor in line: what the application sends it passes only through here. Sans-IO.

A motor in MIT mode takes no limits: it applies the last command it received until the next. So
the guard is in line: every frame the application addresses to the motor comes to ``from_app``,
which forwards it, clamped (``canergy.devices.mit.clamp``) under the cap in force, or refuses it,
and counts both. The budget is a ``DeviceGuard[MitLimits]`` (a proxy client of the supervisor,
charged by the clock at the envelope of the cap in force); its commands are carried out here:

- ``WriteLimits``: the cap changes; the command in force is sent again, clamped under the new
  cap (refused under it: exit motor mode); taken as read back at once (this process enforces it);
- ``Stop``: exit motor mode (``FF×7 FD``); the motor counts as powerless once a reply shows no
  torque (within one step) out of motor mode; the guard takes only replies received later than
  the stop plus the reaction and latency it allows.

While no budget is granted, commands and enter-motor-mode are refused; exit motor mode always
passes. Every ``hold_us`` the gate sends the command in force again, clamped from the newest reply
(position drift is bounded only over ``horizon`` = hold + the reaction and latency allowed), or,
out of motor mode, exit motor mode again: the motor answers every frame, so its replies keep the
guard's feedback fresh. A frame to the motor from anyone else (seen on the bus) refuses the motor
for good: what it asked for is unbounded; so does a reply that no frame of the gate's asked for
(the motor answers each frame once): its position and torque cannot be trusted.

A frame unanswered after ``REPLY_WINDOW_US`` is taken as lost, but kept for ``LATE_WINDOW_US``:
a reply that finds no frame waiting takes one of those as *late* (counted, its round trip raises
the latency the guard allows), not as forged. A host or motor stalled for 200 ms (a loaded
machine, a GC pause) thus slows the motor instead of refusing it for good; a forger still has to
send more replies than the gate sent frames within 2 s, which the gate counts.

A Damiao motor's own watchdog, its CAN Timeout register (``TIMEOUT_RID``), is read over 0x7FF
when the policy reads it (``--mit-max-watchdog``): at set-up and again every ``REREAD_US`` while
the motor is not refused (a USB tool, or another master on another bus, can change it behind
the gate; one read in flight at a time). A value the policy refuses, or a read not answered
within ``LATE_WINDOW_US``, refuses the motor for good (``DeviceGuard.on_watchdog``: the stop of
every refusal). The answer comes from the master id, as the replies do, and a reply of the same
motor out of motor mode near −12.5 rad can look like it (``register_reply``). So every frame
shaped as the answer within ``LATE_WINDOW_US`` of a read is judged as one (the first answers
the read, a later one counts as a periodic read-back): a look-alike taken first does not hide
the real answer behind it, and a look-alike whose bytes the policy refuses stops the motor
(failing safe). A look-alike is not counted as a reply; the frame it answered is taken as lost.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

from canergy.devices.guard import REREAD_US, DeviceConfig, DeviceGuard, GuardPhase
from canergy.devices.mit import (
    CLEAR_ERROR,
    ENTER,
    EXIT,
    SPECIAL,
    TIMEOUT_RID,
    TIMEOUT_UNIT_US,
    ZERO,
    Command,
    MitLimits,
    MitModel,
    MitProfile,
    clamp,
    read_register,
    register_reply,
    unpack_reply,
)
from canergy.devices.profile import Stop, WriteLimits
from canergy.devices.watchdog import WatchdogReading
from canergy.messages import Message, ToClient

REPLY_WINDOW_US = 200_000
"""A frame not answered within this is taken as lost (its answer no longer expected)."""
LATE_WINDOW_US = 2_000_000
"""A lost frame's answer is still taken (as late) within this."""
LATE_KEPT = 256
"""At most this many lost frames wait for a late answer (the oldest go first)."""


@dataclass
class MitCounts:
    """What the gate did with the application's frames to the motor (the application reads
    these: nothing it sent is dropped without being counted here)."""

    forwarded: int = 0
    """Sent to the motor as they were."""
    clamped: int = 0
    """Sent with lower gains, feed-forward torque or velocity."""
    refused: int = 0
    """Not sent (no budget, a cap below the smallest step, a malformed frame)."""
    refused_why: dict[str, int] = field(default_factory=dict)
    resent: int = 0
    """Commands the gate sent again (re-clamped, hold expired or cap changed)."""
    exits: int = 0
    """Exit motor mode sent by the gate (stops, refused re-clamps, keep-alives)."""
    replies: int = 0
    bad_replies: int = 0
    late: int = 0
    """Replies to frames taken as lost (beyond ``REPLY_WINDOW_US``)."""
    unasked: int = 0
    """Replies with no frame of the gate's left unanswered: forged, or someone else's frame."""
    foreign: int = 0


@dataclass(frozen=True, slots=True)
class Verdict:
    """What became of one frame of the application."""

    frame: bytes | None
    """What to send to the motor (None: refused)."""
    clamped: bool = False
    why: str | None = None


class MitGate:
    """The in-line guard of motor ``motor_id`` (module doc)."""

    def __init__(
        self,
        motor_id: int,
        node: int,
        model: MitModel,
        config: DeviceConfig[MitLimits],
        now: int,
        nonce: int,
        *,
        resistance: Fraction | None = None,
        hold_us: int = 20_000,
    ) -> None:
        self.motor_id = motor_id
        self.model = model
        self.hold_us = hold_us
        self.guard = DeviceGuard(node, MitProfile(model, resistance), config, now, nonce)
        self.counts = MitCounts()
        self.cap = MitLimits(0, 0)
        """The cap in force (the guard's closed limits until it has budget)."""
        self.motor_mode = False
        self.last_cmd: Command | None = None
        """The application's last command (as it sent it)."""
        self.theta: Fraction | None = None
        """The last reply's position (None: not known, or saturated, or zeroed since)."""
        self.theta_at = now
        self.next_send = now
        self.to_motor: list[bytes] = [EXIT]  # a known state: the power stage off
        self.asked: deque[int] = deque([now])
        """When each frame not answered yet went to the motor (it answers every frame)."""
        self.lost: deque[int] = deque(maxlen=LATE_KEPT)
        """When each frame taken as lost went (a late answer may still come)."""
        self.exit_at: int | None = now
        self.counts.exits += 1
        ft = model.fields()[4]
        self.torque_step = 2 * ft.span / ft.top
        closed = MitProfile(model, resistance).closed(config.limits)
        self.guard.on_ready(now, now, config.limits, closed)
        self.parameters: list[bytes] = []
        """Frames for Damiao's parameter identifier 0x7FF (``take_parameter_frames``)."""
        self.register_asked: int | None = None
        """When the CAN Timeout register was asked (None: not, or answered)."""
        self.register_periodic = False
        """The read in flight is a periodic one (not the set-up's)."""
        self.register_until: int | None = None
        """Frames shaped as the register's answer received until then are judged as one."""
        self.register_next: int | None = None
        """When the register is read again (None: never)."""
        policy = config.watchdog
        if model.damiao and policy is not None and policy.read:
            self._read_register(now, periodic=False)

    # -- the application's side ------------------------------------------------------------
    def from_app(self, data: bytes, now: int) -> Verdict:
        """One frame of the application to the motor."""
        verdict = self._judge(bytes(data), now)
        c = self.counts
        if verdict.frame is None:
            return self.refuse(verdict.why or "refused")
        if verdict.clamped:
            c.clamped += 1
        else:
            c.forwarded += 1
        self.asked.append(now)
        return verdict

    def refuse(self, why: str) -> Verdict:
        """A frame of the application's for this motor that is never sent (counted)."""
        self.counts.refused += 1
        self.counts.refused_why[why] = self.counts.refused_why.get(why, 0) + 1
        return Verdict(None, why=why)

    def _running(self) -> bool:
        return self.guard.phase is GuardPhase.RUNNING and self.cap.torque_unm > 0

    def _judge(self, data: bytes, now: int) -> Verdict:
        if data == EXIT:
            self.motor_mode, self.exit_at, self.last_cmd = False, now, None
            return Verdict(data)
        if len(data) != 8:
            return Verdict(None, why=f"{len(data)} bytes, not an MIT frame")
        if not self._running():
            return Verdict(None, why=f"no budget ({self.guard.stop_reason or 'closed'})")
        if data in (ENTER, CLEAR_ERROR):
            self.motor_mode = True
            return Verdict(data)
        if data == ZERO:
            self.theta = None  # the origin moves: the next reply says where the motor is
            return Verdict(data)
        if data in SPECIAL:
            return Verdict(None, why="unknown special frame")
        cmd = Command.unpack(data)
        out = self._clamp(cmd, now)
        if out.command is None:
            return Verdict(None, why=out.why)
        self.last_cmd = cmd
        self.next_send = now + self.hold_us
        return Verdict(out.command.pack(), clamped=out.clamped)

    def _horizon(self) -> int:
        return self.hold_us + self.guard.reaction_us() + self.guard.latency_us()

    def _clamp(self, cmd: Command, now: int) -> Any:
        theta, age = self.theta, max(0, now - self.theta_at)
        if theta is None:  # no position to bound kp's term: no stiffness
            cmd = Command(cmd.p, cmd.v, 0, cmd.kd, cmd.t)
            theta, age = Fraction(0), 0
        return clamp(self.model, cmd, self.cap, theta, age, self._horizon())

    # -- the motor's side ------------------------------------------------------------------
    def from_motor(self, data: bytes, at: int, now: int) -> list[Message]:
        """A reply of the motor, received at ``at``."""
        if (answer := self._register_answer(data, at, now)) is not None:
            return answer
        try:
            reply = unpack_reply(self.model, data)
        except ValueError:
            self.counts.bad_replies += 1
            return []
        if reply.node != self.motor_id & (0xF if self.model.damiao else 0xFF):
            return []
        self.counts.replies += 1
        while self.asked and self.asked[0] < at - REPLY_WINDOW_US:
            self.lost.append(self.asked.popleft())  # not answered in time: lost, or late
        while self.lost and self.lost[0] < at - LATE_WINDOW_US:
            self.lost.popleft()
        if self.asked:
            sent = self.asked.popleft()
        elif self.lost:
            sent = self.lost.popleft()
            self.counts.late += 1
        else:  # the position and torque it shows cannot be trusted
            self.counts.unasked += 1
            why = "a reply no frame of the guard's asked for (forged, or another sender's frame)"
            return self.guard.on_foreign_write(now, why) + self._carry_out(now)
        self.guard.watch(0, max(0, at - sent))  # the round trip: latency
        p_max = self.model.fields()[0]
        saturated = abs(reply.p) >= p_max.span - 2 * p_max.span / p_max.top
        self.theta, self.theta_at = (None if saturated else reply.p), at
        torque = abs(reply.torque) > self.torque_step
        powered = self.motor_mode or torque  # the guard takes it only from a stop's notice on
        state = "motor mode" if self.motor_mode else "exited"
        if reply.state is not None and reply.state > 1:
            state += f", fault {reply.state}"
        out = self.guard.on_feedback(now, at, powered, state)
        return out + self._carry_out(now)

    def _register_answer(self, data: bytes, at: int, now: int) -> list[Message] | None:
        """``data`` judged as the CAN Timeout register's answer (None: not shaped as one, or
        not within ``LATE_WINDOW_US`` of a read; module doc)."""
        if self.register_until is None or at > self.register_until:
            return None
        value = register_reply(self.motor_id, TIMEOUT_RID, data)
        if value is None:
            return None
        # none in flight: a second answer within the window (the first a look-alike, or this)
        periodic = self.register_periodic or self.register_asked is None
        self.register_asked = None
        reading = WatchdogReading(value > 0, value * TIMEOUT_UNIT_US / 1e6)
        return self.guard.on_watchdog(now, reading, periodic) + self._carry_out(now)

    def _read_register(self, now: int, periodic: bool) -> None:
        """Ask the CAN Timeout register (unless the motor is refused: stopped for good, or a
        read is still in flight: its own deadline holds), and again ``REREAD_US`` on."""
        self.register_next = now + REREAD_US
        if self.guard.refused is not None:
            self.register_next = None
            return
        if self.register_asked is not None:
            return
        self.parameters.append(read_register(self.motor_id, TIMEOUT_RID))
        self.register_asked, self.register_periodic = now, periodic
        self.register_until = now + LATE_WINDOW_US

    def on_foreign(self, data: bytes, now: int) -> list[Message]:
        """A frame to the motor from someone else."""
        self.counts.foreign += 1
        out = self.guard.on_foreign_write(now, f"MIT frame {data.hex()} from another sender")
        return out + self._carry_out(now)

    def on_unseen(self, why: str, now: int) -> list[Message]:
        """Frames to or from the motor may have been lost unseen (``why``): stopped for good."""
        return self.guard.on_unseen(now, why) + self._carry_out(now)

    # -- the supervisor's side and the clock ----------------------------------------------
    def on_message(self, msg: ToClient, now: int) -> list[Message]:
        return self.guard.on_message(msg, now) + self._carry_out(now)

    def next_wakeup(self) -> int:
        times = [self.guard.next_wakeup(), self.next_send]
        if self.register_asked is not None:
            times.append(self.register_asked + LATE_WINDOW_US)
        if self.register_next is not None:
            times.append(self.register_next)
        return min(times)

    def on_wakeup(self, now: int) -> list[Message]:
        self.guard.watch(max(0, now - self.next_wakeup()), 0)  # how late the host woke
        out = self.guard.on_wakeup(now) if self.guard.next_wakeup() <= now else []
        out += self._carry_out(now)
        if self.register_asked is not None and now >= self.register_asked + LATE_WINDOW_US:
            # unanswered: at set-up the policy refuses the motor (or says so); a periodic
            # read-back, stopped for good
            periodic, self.register_asked = self.register_periodic, None
            out += self.guard.on_watchdog(now, None, periodic, alone=True)
            out += self._carry_out(now)
        if self.register_next is not None and now >= self.register_next:
            self._read_register(now, periodic=True)
        if now >= self.next_send:
            self._resend(now)
        return out

    def halt(self, now: int) -> list[Message]:
        self.guard.halt(now)
        return self._carry_out(now)

    def take_parameter_frames(self) -> list[bytes]:
        """Frames the gate sends to Damiao's parameter identifier 0x7FF (a register read)."""
        out, self.parameters = self.parameters, []
        return out

    def take_frames(self) -> list[bytes]:
        """Frames the gate itself sends to the motor (in order)."""
        out, self.to_motor = self.to_motor, []
        return out

    def _resend(self, now: int) -> None:
        self.next_send = now + self.hold_us
        if not self.motor_mode:
            self._exit(now)
            return
        if self.last_cmd is None:
            self._send(ENTER, now)  # the state, without a command to re-clamp
            return
        out = self._clamp(self.last_cmd, now)
        if out.command is None:
            self._exit(now)
            return
        self.counts.resent += 1
        self._send(out.command.pack(), now)

    def _exit(self, now: int) -> None:
        self.motor_mode, self.exit_at = False, now
        self.counts.exits += 1
        self._send(EXIT, now)

    def _send(self, data: bytes, now: int) -> None:
        self.to_motor.append(data)
        self.asked.append(now)

    def _carry_out(self, now: int) -> list[Message]:
        out: list[Message] = []
        while self.guard.commands:
            out += self.execute(self.guard.commands.pop(0), now)
        return out

    def carry_out(self, now: int) -> list[Message]:
        """Carry out the guard's commands left by a message handed to it directly (the
        supervisor's in-process leg)."""
        return self._carry_out(now)

    def execute(self, cmd: Any, now: int) -> list[Message]:
        """One command of the guard's (``Stop``, ``WriteLimits``)."""
        if isinstance(cmd, Stop):
            self._exit(now)
        elif isinstance(cmd, WriteLimits):
            self.cap = cmd.limits
            self.next_send = now  # the command in force, under the new cap, at once
            self._resend(now)
            return self.guard.on_limits(now, cmd.limits, cmd.limits, cmd.at)
        return []

    def status(self, now: int) -> dict[str, Any]:
        """The guard's status (as a guarded ODrive axis's), the model, the cap in force and
        what became of the application's frames (``commands``)."""
        return {**self.guard.status(now), **self.details()}

    def details(self) -> dict[str, Any]:
        """What the gate adds to its guard's status."""
        c = self.counts
        return {
            "model": self.model.name,
            "motor_id": self.motor_id,
            "motor_mode": self.motor_mode,
            "cap": self.guard.profile.fields(self.cap),
            "commands": {
                "forwarded": c.forwarded,
                "clamped": c.clamped,
                "refused": c.refused,
                "refused_why": dict(c.refused_why),
                "resent": c.resent,
                "exits": c.exits,
                "replies": c.replies,
                "late_replies": c.late,
                "unasked_replies": c.unasked,
                "foreign": c.foreign,
            },
        }
