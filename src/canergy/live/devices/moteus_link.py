"""One moteus controller over CAN FD: set-up, feedback in, limits and stops out.

As ``canergy.live.devices.odrive_link``: a ``can.Listener`` on the supervisor's Notifier takes the
controller's frames and the frames others send it, stamped with the host's clock; a worker thread
carries out the guard's commands, so a controller that does not answer never blocks the loop:

- ``WriteLimits``: ``conf set`` of each limit on diagnostic channel 1, then ``conf get`` of each
  (the round trip is the latency measured), answers polled with 0x42;
- ``ReadLimits`` (the periodic read-back): ``conf get`` of each alone;
- ``Stop``: mode 0 (stopped).

A moteus sends nothing unasked: the worker queries mode, position, velocity, torque, q current,
power, voltage, temperature and fault every ``poll_s`` (reply bit set). Frames from others are
read by the profile (``canergy.devices.moteus.watch_register`` and ``watch_line``): ``conf set``
of a limit is charged as written, then written over; mode writes of PWM or voltage modes, the
fixed voltage or current override, ``conf set`` of the configuration the envelope rests on,
``conf load``, ``conf default``, ``d raw``, ``d pwm``, ``d cal`` and ``d flash`` stop the
controller for good. A frame that does not parse is counted; the subframes before the bad one
count (the controller acts on them).
"""

from __future__ import annotations

import collections
import functools
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import can

from canergy.devices.guard import DeviceGuard
from canergy.devices.moteus import (
    BROADCAST,
    CONF,
    DIAGNOSTIC_CHANNEL,
    FEEDBACK,
    UNPOWERED_MODES,
    Mode,
    MoteusLimits,
    Poll,
    Reg,
    Reply,
    Stream,
    Subframe,
    Write,
    can_id,
    conf_get,
    conf_set,
    decode,
    encode,
    extended,
    mode_name,
    split_id,
    stream_lines,
    watch_line,
    watch_register,
    whole,
    write_mode,
)
from canergy.devices.profile import Foreign, LimitsWritten, ReadLimits, Stop
from canergy.live.devices.device_link import GuardLink
from canergy.live.devices.device_link import limits_event as _limits
from canergy.live.devices.device_link import read_event as _read
from canergy.live.devices.device_link import ready_event as _ready
from canergy.messages import Message

log = logging.getLogger(__name__)


def _watched(
    at: int, seen: Foreign[MoteusLimits], guard: DeviceGuard[MoteusLimits], now: int
) -> list[Message]:
    return guard.on_watched(now, at, seen)


@dataclass(frozen=True, slots=True)
class MoteusLinkConfig:
    source: int = 0x7E
    """The guard's own source id (its queries' answers come back to it)."""
    prefix: int = 0
    """``can.prefix`` of the controller (the identifier's top 13 bits)."""
    answer_timeout_s: float = 0.2
    """How long one ``conf`` line may take to be answered."""
    poll_s: float = 0.02
    sampled: bool = False


class MoteusLink(GuardLink[MoteusLimits]):
    """The controller ``node`` on ``bus`` (see the module doc); ``clock`` gives host µs."""

    def __init__(
        self,
        bus: can.BusABC,
        node: int,
        config: MoteusLinkConfig,
        limits: MoteusLimits | None,
        clock: Callable[[], int],
    ) -> None:
        super().__init__(bus, node, limits, clock, "moteus")
        self.config = config
        self.held = limits
        """What the controller holds as far as the bus shows: the limits the guard last began
        to write, with the values others set since (a foreign ``conf set`` changes one)."""
        self.lines: queue.Queue[str] = queue.Queue()
        self.answers = bytearray()
        self.foreign_stream = bytearray()
        self.stream_lock = threading.Lock()
        self.late = False
        """A line went unanswered in time: its answer may still come (drained first)."""
        self.drained = threading.Event()
        self.sent: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=64)
        """What the guard sent lately, for ``_own`` (python-can loops nothing back by default:
        ``receive_own_messages``)."""
        self.mode: str | None = None
        self.fault: int | None = None

    # -- the listener (Notifier thread) ---------------------------------------------------
    def on_message_received(self, frame: can.Message) -> None:
        if frame.is_error_frame or frame.is_remote_frame:
            return
        source, destination, _, prefix = split_id(frame.arbitration_id)
        if prefix != self.config.prefix or (prefix and not frame.is_extended_id):
            return
        # the controller acts on what is addressed to it, whatever the source: a frame to it
        # in its own name is a command (its replies go to the asker, never to itself)
        addressed = destination in (self.node, BROADCAST)
        from_device = source == self.node and not addressed
        to_device = addressed and not self._own(frame)
        if not (from_device or to_device):
            return
        at = self.received_at(frame)
        subframes, error = decode(bytes(frame.data))
        try:
            if from_device:
                self._from_device(subframes, destination, at)
            else:
                self._to_device(subframes, at)
                if error is not None:  # the controller may read what follows: not bounded
                    self._foreign_write(f"a frame the guard cannot read ({error})")
        finally:
            if error is not None:
                with self.lock:
                    self.bad_frames += 1

    def _own(self, frame: can.Message) -> bool:
        """The guard's own frame, looped back (an interface that echoes what it sends): its
        source id alone says nothing, anyone can use it."""
        key = (frame.arbitration_id, bytes(frame.data))
        with self.lock:
            if key in self.sent:
                self.sent.remove(key)
                return True
        return False

    def on_error(self, exc: Exception) -> None:
        with self.lock:
            self.bad_frames += 1

    def _from_device(self, subframes: list[Subframe], destination: int, at: int) -> None:
        values: dict[int, float] = {}
        for s in subframes:
            if isinstance(s, Reply):
                values.update(s.items())
            elif (
                isinstance(s, Stream)
                and s.server
                and destination == self.config.source
                and s.channel == DIAGNOSTIC_CHANNEL
            ):
                for line in stream_lines(self.answers, s.data):
                    self.lines.put(line)
                if not s.data:
                    self.drained.set()  # the controller has nothing more to say
        if Reg.MODE not in values:
            return
        mode = values[Reg.MODE]
        powered = whole(mode) not in UNPOWERED_MODES
        name = mode_name(mode)
        self.mode = name
        fault = values.get(Reg.FAULT)
        self.fault = None if fault is None else whole(fault)
        volts = values.get(Reg.VOLTAGE)
        measured = None
        if volts is not None and volts == volts:
            self.voltage = volts
            measured = {"bus_voltage_v": volts}
        power = values.get(Reg.POWER) if self.config.sampled else None
        power = None if power is None or power != power else max(0.0, power)
        self._event(lambda g, now: g.on_feedback(now, at, powered, name, power, measured))

    def _to_device(self, subframes: list[Subframe], at: int) -> None:
        for s in subframes:
            if isinstance(s, Write):
                for register, value in enumerate(s.values, start=s.start):
                    if (seen := watch_register(register, value)) is not None:
                        self._foreign_write(seen.what)
            elif isinstance(s, Stream) and not s.server and s.channel == DIAGNOSTIC_CHANNEL:
                with self.stream_lock:
                    lines = stream_lines(self.foreign_stream, s.data)
                for line in lines:
                    self._foreign_line(line, at)

    def _foreign_write(self, what: str) -> None:
        self._event(lambda g, now: g.on_foreign_write(now, what))

    def _foreign_line(self, line: str, at: int) -> None:
        for seen in watch_line(line, self.held):  # the profile reads it
            if isinstance(seen, LimitsWritten):
                # the values others set add up on the controller until the guard writes its own
                self.held = seen.limits
            self._event(functools.partial(_watched, at, seen))

    # -- the loop's side ------------------------------------------------------------------
    def status(self) -> dict[str, object]:
        extra = {"source_id": self.config.source, "mode": self.mode, "fault": self.fault}
        return {**extra, **super().status()}

    # -- the worker -----------------------------------------------------------------------
    def _send(self, data: bytes, reply: bool = False) -> bool:
        arbitration_id = can_id(self.config.source, self.node, reply, self.config.prefix)
        frame = can.Message(
            arbitration_id=arbitration_id,
            data=data,
            is_extended_id=extended(arbitration_id),
            is_fd=True,
            bitrate_switch=True,
        )
        with self.lock:
            self.sent.append((arbitration_id, data))
        try:
            self.bus.send(frame)
            return True
        except can.CanError:
            self.send_failures += 1
            return False

    def _work(self) -> None:
        if self.limits is not None:
            self._setup(self.limits)
        else:
            started = self.clock()
            self._event(lambda g, now: _ready(g, now, started, None, None))
        next_poll = 0.0
        while not self.closing.is_set():
            wait = max(0.0, next_poll - time.monotonic())
            try:
                cmd = self.work.get(timeout=wait)
            except queue.Empty:
                next_poll = time.monotonic() + self.config.poll_s
                self._send(encode(*FEEDBACK), reply=True)
                continue
            if cmd is None:
                return
            if isinstance(cmd, Stop):
                self._send(write_mode(Mode.STOPPED))
                self.reaction_max_us = max(self.reaction_max_us, self.clock() - cmd.at)
            elif isinstance(cmd, ReadLimits):
                self._event(functools.partial(_read, self._read_limits()))
            else:
                read = self._write(cmd.limits)
                self._event(functools.partial(_limits, cmd.limits, read, cmd.at))

    def _setup(self, limits: MoteusLimits) -> None:
        started = self.clock()
        full = self._write(limits)
        closed = self._write(replace(limits, power_w=0.0, current_a=0.0))
        self._event(lambda g, now: _ready(g, now, started, full, closed))

    def _write(self, limits: MoteusLimits) -> MoteusLimits | None:
        """``conf set`` each limit, then the values ``conf get`` reads back (None: not all
        answered)."""
        self.held = limits  # others' values set after this add up on these
        for _, name, value in limits.items():
            if not self._answered(conf_set(name, value), lambda answer: answer == "OK"):
                return None
        return self._read_limits()

    def _read_limits(self) -> MoteusLimits | None:
        """``conf get`` of each limit (None: not all answered)."""
        got: list[float] = []
        for name in CONF.values():
            start = self.clock()
            if not self._answered(conf_get(name), lambda answer: got.append(float(answer))):
                return None
            self.latency_max_us = max(self.latency_max_us, self.clock() - start)
        return MoteusLimits(*got)

    def _answered(self, line: bytes, take: Callable[[str], object]) -> bool:
        """Ask ``line``; True when answered as such a line is (``take`` neither raises nor
        returns False). Another answer means the controller read something else: a line someone
        left unfinished on the stream ran with the guard's (it sees the stream's bytes, not
        their senders), with effects the read-back may not show: stopped for good."""
        answer = self._ask(line)
        if answer is None:
            return False  # no answer in time: not read back (written again later)
        try:
            if take(answer) is not False:
                return True
        except ValueError:
            pass
        said = line.decode(errors="replace").strip()
        self._foreign_write(f"the controller answered {answer[:40]!r} to '{said}'")
        return False

    def _ask(self, line: bytes) -> str | None:
        """Send one diagnostic line, poll for its one-line answer (None: none in time)."""
        if self.late and not self._drain():
            return None
        if not self._send(encode(Stream(False, DIAGNOSTIC_CHANNEL, line))):
            return None
        deadline = time.monotonic() + self.config.answer_timeout_s
        while (left := deadline - time.monotonic()) > 0:
            self._send(encode(Poll(DIAGNOSTIC_CHANNEL, 48)), reply=True)
            try:
                return self.lines.get(timeout=min(left, 0.005))
            except queue.Empty:
                continue
        self.late = True  # its answer may still come: not to be taken for the next line's
        return None

    def _drain(self) -> bool:
        """Poll until the controller has nothing more to say, and drop what it said (answers to
        lines given up on); False if it kept talking."""
        deadline = time.monotonic() + self.config.answer_timeout_s
        while time.monotonic() < deadline:
            self.drained.clear()
            self._send(encode(Poll(DIAGNOSTIC_CHANNEL, 48)), reply=True)
            if self.drained.wait(0.005):
                break
        else:
            return False
        while not self.lines.empty():
            self.lines.get_nowait()
        self.late = False
        return True
