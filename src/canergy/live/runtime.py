"""One receive loop over any python-can bus, driving a sans-IO handler on the monotonic clock.

The loop waits for a frame no longer than the handler's next deadline, decodes it strictly, hands
it over, and sends what comes back. Sending survives a full transmit queue (retried with
backoff); a send that still fails is counted and dropped: for the protocol it is a lost frame.
Error frames and bus-state changes are counted, never fatal.

In authenticated mode a frame in the direction this side sends is checked as the other side
would check it (``OwnDirection``): only one that verifies under the node's key with a freshness
value this side never used reaches ``on_foreign_direction``; the rest are refused and counted like
any frame whose MAC or freshness failed (``on_auth_failure``).
"""

from __future__ import annotations

import errno
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Protocol, cast

import can

from canergy.auth.frames import (
    FV_MASK,
    MAC_TYPE,
    AuthFailure,
    Expected,
    FrameAuth,
    Layout,
    Verdict,
    fv_before,
)
from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.frozen import fast_init
from canergy.live.transports.virtual_alone import ALONE_AFTER_US, alone_on_virtual, explanation
from canergy.messages import Admit, Direction, Join, Message, Return, ReturnAck, Telemetry

Filters = list[dict[str, int | bool]]


@fast_init  # made for every frame the compiled core sends
@dataclass(frozen=True, slots=True)
class RawFrame:
    """A frame encoded already (the compiled core's fast path): sent as it is."""

    arbitration_id: int
    data: bytes
    fd: bool = False
    """A CAN FD frame (sent with bit rate switch): protected already in the FD layout of
    authenticated mode, its FV in its trailer (noted as this side's own, ``OwnDirection``). In
    the classic layout a protected frame is followed by its MAC frame, both classic (the FV
    they carry noted as well)."""
    bus: int = 0
    """Over several buses: the index of the bus it is for (``canergy.live.supervisor.multi_bus``
    sends it there)."""


Outgoing = Message | RawFrame
"""What a pass hands the loop to send."""

FramePath = Callable[[can.Message, int], bool]
"""A core's frame path (``BusRuntime(frame_path=)``): a received frame the loop has not
decoded, taken in one call (True: the frames it answers are held for the pass's end) or left to
the usual path (False: decoded here, then ``Handler.on_message``)."""


class Handler(Protocol):
    """What the loop drives: the supervisor service or a host of firmware nodes."""

    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        """A decoded frame arrived; return the frames to send."""
        ...

    def on_decode_error(self, error: DecodeError, frame: can.Message) -> None:
        """A frame in canergy's identifier block failed to decode (it is dropped)."""
        ...

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        """Authenticated mode: a frame whose MAC or freshness failed (a forgery, a replay of
        an old frame): it moves nothing."""
        ...

    def on_foreign_direction(self, frame: can.Message, now: int) -> Sequence[Message]:
        """A frame in the direction this side sends (its own never come back to it): for a node
        it handles, someone else (a second supervisor, a spoofer) sent it. In authenticated
        mode only one that verified under the node's key with a freshness value this side never
        used (``OwnDirection``): authentic evidence. Return frames to send (none, usually)."""
        ...

    def next_wakeup(self) -> int | None:
        """The earliest monotonic time (µs) at which ``on_wakeup`` must run, or None."""
        ...

    def on_wakeup(self, now: int) -> Sequence[Message]:
        """Deadlines due at ``now`` (and any periodic work); return the frames to send."""
        ...


class PassHandler(Protocol):
    """A handler that takes loop passes: it holds the frames of a whole pass (every frame
    drained in one go and the deadlines then due) and saves its books once before they leave,
    instead of once per frame (the supervisor service)."""

    def begin_pass(self) -> None: ...

    def end_pass(self) -> Sequence[Outgoing]:
        """The frames held since ``begin_pass``, to send now."""
        ...


@dataclass(slots=True)
class BusCounters:
    frames_sent: int = 0
    frames_received: int = 0
    decode_errors: int = 0
    foreign_frames: int = 0
    send_retries: int = 0
    send_failures: int = 0
    receive_errors: int = 0
    error_frames: int = 0
    bus_state: str = "unknown"
    """What the interface reports (python-can's ``BusState``), or ``unknown`` where its driver
    reports nothing (python-can's default answers ``active`` whatever the link does)."""
    link_down: bool = False
    """The last receive or send failed and none has succeeded since: the status then says
    ``bus_state: down`` whatever the driver reports."""
    decode_reasons: dict[str, int] = field(default_factory=dict)
    auth_failures: dict[str, int] = field(default_factory=dict)
    auth: str | None = None
    """The authenticated layout (``fd``, ``classic``); None without a key."""
    bus_note: str | None = None
    """Why nothing is heard, when the loop knows (python-can's virtual bus within one process
    only: ``canergy.live.transports.virtual_alone``); in the status only when set."""

    def receive_failed(self) -> None:
        """A receive raised (the interface went down, a driver's error): counted, and the link
        taken as down until a frame is sent or received."""
        self.receive_errors += 1
        self.link_down = True

    def as_json(self) -> dict[str, Any]:
        return {
            "frames_sent": self.frames_sent,
            "frames_received": self.frames_received,
            "decode_errors": self.decode_errors,
            "decode_error_reasons": dict(self.decode_reasons),
            "foreign_frames": self.foreign_frames,
            "send_retries": self.send_retries,
            "send_failures": self.send_failures,
            "receive_errors": self.receive_errors,
            "error_frames": self.error_frames,
            "bus_state": "down" if self.link_down else self.bus_state,
            "auth_failures": dict(self.auth_failures),
            "auth": self.auth,
            **({"bus_note": self.bus_note} if self.bus_note else {}),
        }


_BUS_STATES = ("error", "passive", "active")
"""python-can's bus states, worst first."""

_LINK_DOWN = (errno.ENETDOWN, errno.ENODEV, errno.ENXIO)
"""What a send fails with when the interface itself is gone (``ip link set vcan0 down``)."""


def total_counters(counters: Iterable[BusCounters]) -> BusCounters:
    """Several buses' counters summed (counts by reason too); the bus state is the worst one."""
    total = BusCounters()
    states = set()
    layouts: set[str] = set()
    for c in counters:
        if c.auth is not None:
            layouts.add(c.auth)
        for f in fields(BusCounters):
            mine, theirs = getattr(total, f.name), getattr(c, f.name)
            if isinstance(theirs, int):
                setattr(total, f.name, mine + theirs)
            elif isinstance(theirs, dict):
                for reason, count in theirs.items():
                    mine[reason] = mine.get(reason, 0) + count
        states.add(c.bus_state)
        total.link_down = total.link_down or c.link_down
    total.bus_state = next((s for s in _BUS_STATES if s in states), "unknown")
    total.auth = min(layouts, default=None)
    return total


CLOCK: int | None = getattr(time, "CLOCK_BOOTTIME", getattr(time, "CLOCK_MONOTONIC", None))
"""The clock ``monotonic_us`` reads: Linux's ``CLOCK_BOOTTIME`` (it never goes back and keeps
counting while the host is suspended), else ``CLOCK_MONOTONIC`` (which stops meanwhile); None
where there is no ``clock_gettime`` (``time.monotonic``)."""


def monotonic_us() -> int:
    """The live stack's clock, in µs (``CLOCK``): time the host spent suspended counts, so a
    guarded drive that ran on meanwhile is charged it and every deadline then due fires."""
    if CLOCK is None:
        return time.monotonic_ns() // 1000
    return time.clock_gettime_ns(CLOCK) // 1000


_UNCOUNTED = frozenset(t.TYPE for t in (Join, Admit, Telemetry))
"""Types whose FV says nothing of this side's counters (``OwnDirection.note_sent``)."""
_RETURN_COUNTED = frozenset(t.TYPE for t in (Return, ReturnAck))
"""Types whose FV is a return number, not a transaction."""

OWN_MAC_WAIT_US = 200_000
"""Classic layout: a message in this side's own direction whose MAC frame has not followed it
within this long is refused as a frame without a MAC (no later message of its node need come:
this side's own frames never come back to it)."""


@dataclass(frozen=True, slots=True)
class OwnFrame:
    """What a frame in this side's own direction came to (authenticated mode)."""

    frame: can.Message
    """The frame to report (for a classic message, its data frame)."""
    refused: Verdict | None
    """Why it was refused; None: authentic evidence (see ``OwnDirection``)."""


class OwnDirection:
    """Authenticated mode: frames in the direction this side sends. Its own never come back to
    it, so each one is someone else's, checked as the other side would check it:

    - refused, counted by reason and never acted on, when it fails there: no MAC, a bad one, a
      MAC frame without its message, a classic message whose MAC frame does not follow within
      ``OWN_MAC_WAIT_US``. Anyone on the bus can send these;
    - refused as stale when it verifies but carries a freshness value this side may have used
      itself: not above both its own counter and the highest it sent for that node (a replay of
      its own frames), or one whose freshness says nothing of that (JOIN, ADMIT, TELEMETRY);
    - authentic evidence otherwise: it verifies under the node's key with a freshness value this
      side never used, so someone else holds the key (a second supervisor with the master key).
      A far newer one (32,768 or more ahead of the side's counter) is refused as stale, as the
      receiving side refuses it too.
    """

    def __init__(self, auth: FrameAuth) -> None:
        other = (
            Direction.TO_CLIENT
            if auth.receives is Direction.TO_SUPERVISOR
            else Direction.TO_SUPERVISOR
        )
        self.auth = auth
        self.mirror = FrameAuth(auth.codec, auth.layout, auth.key_for, other, auth.freshness)
        """The other side's check: its own pending messages, the same keys and counters."""
        self.mirror.join_fv = auth.join_fv  # the JOINs an ADMIT's MAC binds
        self.sent: dict[tuple[int, bool], int] = {}
        """Per node and counter (False: transactions, True: returns) the newest FV sent."""
        self.waiting: dict[int, tuple[int, can.Message]] = {}
        """Classic layout: per node, when a data frame came and the frame, until its MAC frame."""

    def note_sent(self, msg: Message) -> None:
        """This side sent ``msg``: its FV is its own from now on."""
        if isinstance(msg, Join | Admit | Telemetry):
            return
        fv = self.auth.freshness(msg)
        if fv is None:
            return
        self._note(msg.node, isinstance(msg, Return | ReturnAck), fv)

    def note_frame(self, arbitration_id: int, data: bytes) -> None:
        """This side sent an FD frame protected already (the compiled core's frame path: a
        COMMIT or ABORT): its FV, read from its trailer, is its own from now on."""
        kind = arbitration_id >> 8 & 0xF
        if kind in _UNCOUNTED:
            return
        fv = int.from_bytes(data[-12:-8], "big")
        self._note(arbitration_id & 0xFF, kind in _RETURN_COUNTED, fv)

    def note_pair(self, arbitration_id: int, data: bytes, mac: bytes) -> None:
        """``note_frame`` in the classic layout: a transaction's frame the compiled core
        protected (INTENTION, COMMIT, ABORT; its 16-bit counter first after the CRC byte) and
        its MAC frame, which carries the FV's high half."""
        kind = arbitration_id >> 8 & 0xF
        if kind in _UNCOUNTED or len(data) < 3 or len(mac) < 3:
            return
        fv = int.from_bytes(mac[1:3], "big") << 16 | int.from_bytes(data[1:3], "little")
        self._note(arbitration_id & 0xFF, kind in _RETURN_COUNTED, fv)

    def _note(self, node: int, returns: bool, fv: int) -> None:
        key = (node, returns)
        last = self.sent.get(key)
        if last is None or fv_before(last, fv & FV_MASK):
            self.sent[key] = fv & FV_MASK

    def check(self, frame: can.Message, now: int) -> OwnFrame | None:
        """One frame of this side's direction; None when it comes to nothing yet (a classic
        message before its MAC frame) or is for a node this side does not handle.
        ``DecodeError`` for what the codec refuses."""
        node = frame.arbitration_id & 0xFF
        classic = self.auth.layout is Layout.CLASSIC
        if classic and frame.arbitration_id >> 8 & 0xF not in MAC_TYPE.values():
            previous = self.waiting.get(node)
            verdict = self.mirror.accept(frame)
            self.waiting[node] = (now, frame)
            if verdict.failure is not None:  # the one before never got its MAC frame
                return OwnFrame(previous[1] if previous else frame, verdict)
            return None
        shown = frame
        if classic:
            waiting = self.waiting.pop(node, None)
            verdict = self.mirror.accept(frame)
            lone = verdict.failure in (AuthFailure.MALFORMED, AuthFailure.NO_DATA)
            shown = waiting[1] if waiting is not None and not lone else frame
        else:
            verdict = self.mirror.accept(frame)
        if verdict.failure is not None:
            return OwnFrame(shown, verdict)
        msg = verdict.message
        if msg is None:
            return None
        if self._never_sent(msg):
            return OwnFrame(shown, None)
        return OwnFrame(shown, Verdict(failure=AuthFailure.STALE, node=msg.node))

    def _never_sent(self, msg: Message) -> bool:
        """A verified message's FV is above this side's counter and above all it sent."""
        if isinstance(msg, Join | Admit | Telemetry):
            return False
        wanted = self.auth.freshness(msg)
        if not isinstance(wanted, Expected):
            return False
        floor = wanted.counter
        last = self.sent.get((msg.node, isinstance(msg, Return | ReturnAck)))
        if last is not None and fv_before(floor, last):
            floor = last
        return fv_before(floor, wanted & FV_MASK)

    def expire(self, now: int) -> list[OwnFrame]:
        """Classic messages whose MAC frame did not follow in time: refused, without a MAC."""
        if not self.waiting:
            return []
        out: list[OwnFrame] = []
        for node, (since, frame) in list(self.waiting.items()):
            if now - since < OWN_MAC_WAIT_US:
                continue
            del self.waiting[node]
            pending = self.mirror.pending.pop(node, None)
            if pending is not None and self.auth.freshness(pending[0]) is not None:
                refused = Verdict(failure=AuthFailure.UNAUTHENTICATED, node=node)
                out.append(OwnFrame(frame, refused))
        return out


BUS_STATE_PERIOD_US = 100_000
"""How often the loop reads the bus's state (a driver call on some interfaces): reported in
the counters, never acted on, so a change shows within this long."""


@dataclass(frozen=True, slots=True)
class SendPolicy:
    """How hard to push a frame into a full transmit queue before calling it lost."""

    attempts: int = 6
    first_backoff_s: float = 0.001
    max_backoff_s: float = 0.05


class BusRuntime:
    """Receive, decode, dispatch, send: one handler on one bus."""

    def __init__(
        self,
        bus: can.BusABC,
        handler: Handler,
        *,
        codec: Codec | None = None,
        receives: Direction,
        listen_only: bool = False,
        send_policy: SendPolicy | None = None,
        clock: Callable[[], int] = monotonic_us,
        sleep: Callable[[float], None] = time.sleep,
        source: can.BufferedReader | None = None,
        auth: FrameAuth | None = None,
        counters: BusCounters | None = None,
        frame_path: FramePath | None = None,
        max_batch: int = 512,
    ) -> None:
        """``source``: read from this listener instead of ``bus.recv`` when a ``can.Notifier``
        owns the bus (shared with python-canopen: one Notifier per bus). ``counters``: kept in
        this object (the handler's status shows the same one; default a new one).
        ``frame_path``: every received frame goes there first (the compiled core's, from the
        builder); it needs a handler that takes passes (with a key, what the frame path sends
        is protected already)."""
        self.bus = bus
        self.source = source
        self.handler = handler
        self.codec = codec or Codec()
        self.receives = receives
        self.listen_only = listen_only
        self.send_policy = send_policy or SendPolicy()
        self.clock = clock
        self.sleep = sleep
        self.counters = BusCounters() if counters is None else counters
        self._bus_state: can.BusState | None = None
        self._bus_state_due = 0
        self._alone_due: int | None = clock() + ALONE_AFTER_US
        """When to look whether this is a virtual bus no other bus of this process shares."""
        self.max_batch = max_batch
        """The most frames one pass takes (``canergy bench --pace``: 1)."""
        self.auth = auth
        """Authenticated mode: MACs added to what is sent and checked on what is received."""
        self.own = None if auth is None else OwnDirection(auth)
        """Authenticated mode: frames of this side's own direction, checked before they count."""
        if auth is not None:
            self.counters.auth = auth.layout.value
        passes = callable(getattr(handler, "begin_pass", None))
        self._passes = cast(PassHandler, handler) if passes else None
        if frame_path is not None and not passes:
            raise ValueError("a frame path needs a handler that takes passes")
        self._fast = frame_path

    def poll(self, max_wait_s: float = 0.1) -> None:
        """Wait for one frame (at most until the next deadline or ``max_wait_s``) and run
        whatever is due."""
        wait = 0.0
        if max_wait_s > 0:  # wait no longer than until the next deadline
            wakeup, now = self.handler.next_wakeup(), self.clock()
            wait = max_wait_s if wakeup is None else min(max_wait_s, max(0, wakeup - now) / 1e6)
        try:
            frame = self._recv(wait)
        except can.CanError:  # e.g. the interface went down: count, back off, keep going
            self.counters.receive_failed()
            self.sleep(min(wait, 0.1))
            frame = None
        passes = self._passes  # begin_pass and end_pass, written out: every pass runs them
        if passes is not None:
            passes.begin_pass()
        try:
            batch = 0
            while frame is not None:  # drain what is queued before judging any timeout
                self.receive(frame)
                batch += 1
                frame = self._recv_now() if batch < self.max_batch else None
            self.run_due()
        finally:
            if passes is not None:
                self._send_all(passes.end_pass())

    def begin_pass(self) -> None:
        """Tell a handler that takes passes (``PassHandler``) that a loop pass begins."""
        if self._passes is not None:
            self._passes.begin_pass()

    def end_pass(self) -> None:
        """End the pass: send what the handler held back through it (it saved its books
        first)."""
        if self._passes is not None:
            self._send_all(self._passes.end_pass())

    def run_due(self) -> None:
        """Note the bus state (every ``BUS_STATE_PERIOD_US``) and run the handler's deadlines
        that are due."""
        if self.own is not None and self.own.waiting:
            for own in self.own.expire(self.clock()):
                self._own_frame(own)
        wakeup = self.handler.next_wakeup()
        now = self.clock()
        if now >= self._bus_state_due:
            self._bus_state_due = now + BUS_STATE_PERIOD_US
            self._update_bus_state()
        if self._alone_due is not None and now >= self._alone_due:
            self._alone_due = None
            self._say_if_alone()
        if wakeup is not None and wakeup <= now:
            self._send_all(self.handler.on_wakeup(now))

    def _say_if_alone(self) -> None:
        """On a virtual bus that no other bus of this process shares, nothing will ever be
        heard: say why on stderr and in the status (``bus_note``), once."""
        channel = alone_on_virtual(self.bus)
        if channel is not None and self.counters.frames_received == 0:
            self.counters.bus_note = explanation(channel)
            print(f"canergy: {self.counters.bus_note}", file=sys.stderr, flush=True)

    def _recv(self, timeout: float) -> can.Message | None:
        if self.source is not None:
            return self.source.get_message(timeout)
        return self.bus.recv(timeout=timeout)

    def _recv_now(self) -> can.Message | None:
        try:
            return self._recv(0)
        except can.CanError:
            self.counters.receive_failed()
            return None

    def run(self, until: Callable[[], bool], max_wait_s: float = 0.1) -> None:
        while not until():
            self.poll(max_wait_s)

    def send_messages(self, messages: Sequence[Outgoing]) -> None:
        self._send_all(messages)

    def receive(self, frame: can.Message) -> None:
        """One frame read from the bus (by ``poll`` or by a reader thread of ``BusGroup``)."""
        if frame.is_error_frame:
            self.counters.error_frames += 1
            return
        self.counters.frames_received += 1
        self.counters.link_down = False
        if self._fast is not None and self._fast(frame, self.clock()):
            return
        try:
            msg = self._decode(frame)
        except DecodeError as err:
            if err.reason is DecodeErrorReason.FOREIGN:
                self.counters.foreign_frames += 1
                return
            if err.reason is DecodeErrorReason.WRONG_DIRECTION:
                self._foreign_direction(frame)
                return
            self._decode_error(err, frame)
            return
        if msg is not None:
            self._send_all(self.handler.on_message(msg, self.clock()))

    def _decode_error(self, err: DecodeError, frame: can.Message) -> None:
        self.counters.decode_errors += 1
        reasons = self.counters.decode_reasons
        reasons[err.reason.value] = reasons.get(err.reason.value, 0) + 1
        self.handler.on_decode_error(err, frame)

    def _foreign_direction(self, frame: can.Message) -> None:
        """A frame in this side's own direction: someone else's. Without a key, the handler
        judges it; with one, only authentic evidence reaches it (``OwnDirection``)."""
        if self.own is None:
            self._send_all(self.handler.on_foreign_direction(frame, self.clock()))
            return
        try:
            own = self.own.check(frame, self.clock())
        except DecodeError as err:
            self._decode_error(err, frame)
            return
        if own is not None:
            self._own_frame(own)

    def _own_frame(self, own: OwnFrame) -> None:
        if own.refused is None:
            self._send_all(self.handler.on_foreign_direction(own.frame, self.clock()))
        else:
            self._refused(own.refused, own.frame)

    def _refused(self, verdict: Verdict, frame: can.Message) -> None:
        """A frame whose MAC or freshness failed: counted by reason, reported, never acted on."""
        assert verdict.failure is not None
        failures = self.counters.auth_failures
        failures[verdict.failure.value] = failures.get(verdict.failure.value, 0) + 1
        self.handler.on_auth_failure(verdict, frame, self.clock())

    def _decode(self, frame: can.Message) -> Message | None:
        """The message a frame carries; None when it carries none yet (a classic authenticated
        message before its MAC frame) or its MAC or freshness failed (counted, reported)."""
        if self.auth is None or not self.codec.is_canergy_id(
            frame.arbitration_id, frame.is_extended_id
        ):
            return self.codec.decode(
                frame.arbitration_id,
                frame.data,
                extended=frame.is_extended_id,
                remote=frame.is_remote_frame,
                direction=self.receives,
            )
        if frame.is_remote_frame:
            raise DecodeError(DecodeErrorReason.REMOTE_FRAME, f"id 0x{frame.arbitration_id:08X}")
        verdict = self.auth.accept(frame)
        if verdict.failure is not None:
            self._refused(verdict, frame)
        return verdict.message

    def _send_all(self, messages: Sequence[Outgoing]) -> None:
        if self.listen_only:
            return
        before: RawFrame | None = None  # classic: the frame a MAC frame follows
        for msg in messages:
            if isinstance(msg, RawFrame):
                fd = msg.fd
                self._send_frame(
                    can.Message(
                        arbitration_id=msg.arbitration_id,
                        is_extended_id=True,
                        data=msg.data,
                        is_fd=fd,
                        bitrate_switch=fd,
                    )
                )
                if self.own is not None:
                    if fd:
                        self.own.note_frame(msg.arbitration_id, msg.data)
                    elif msg.arbitration_id >> 8 & 0xF == MAC_TYPE[self.own.mirror.receives]:
                        if before is not None:
                            self.own.note_pair(before.arbitration_id, before.data, msg.data)
                    else:
                        before = msg
                        continue
                before = None
            else:
                self._send(msg)

    def _send(self, msg: Message) -> None:
        if self.auth is not None:
            for frame in self.auth.frames(msg):
                self._send_frame(frame)
            if self.own is not None:
                self.own.note_sent(msg)
            return
        arbitration_id, data = self.codec.encode(msg)
        self._send_frame(can.Message(arbitration_id=arbitration_id, is_extended_id=True, data=data))

    def _send_frame(self, frame: can.Message) -> None:
        policy = self.send_policy
        backoff = policy.first_backoff_s
        for attempt in range(policy.attempts):
            try:
                self.bus.send(frame, timeout=backoff)
            except can.CanError as exc:
                if attempt + 1 == policy.attempts or not _retryable(exc):
                    self.counters.send_failures += 1  # lost, as far as the protocol goes
                    if getattr(exc, "error_code", None) in _LINK_DOWN:
                        self.counters.link_down = True
                    return
                self.counters.send_retries += 1
                self.sleep(backoff)
                backoff = min(backoff * 2, policy.max_backoff_s)
            else:
                self.counters.frames_sent += 1
                self.counters.link_down = False
                return

    def _update_bus_state(self) -> None:
        if type(self.bus).state is can.BusABC.state:  # the driver reports none: say unknown
            return
        try:
            state = self.bus.state
        except (NotImplementedError, can.CanError):
            return
        if state is not self._bus_state:  # named once per change, not once per pass
            self._bus_state = state
            self.counters.bus_state = state.name.lower()


def _retryable(exc: can.CanError) -> bool:
    """A full transmit queue (ENOBUFS, timeouts of a busy controller) is worth another try."""
    code = getattr(exc, "error_code", None)
    if code in (errno.ENOBUFS, errno.EAGAIN, errno.EBUSY):
        return True
    return isinstance(exc, can.CanOperationError | can.CanTimeoutError) and code is None
