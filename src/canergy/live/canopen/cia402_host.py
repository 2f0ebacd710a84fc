"""The supervisor with guarded CiA 402 drives: one loop, one core, proxies in the same books.

``GuardedDevices`` holds the guards, their links and the host's heartbeat; it is made before the
service, which takes its liveness and status through its constructor
(``canergy.live.supervisor.build``).
``GuardedSupervisor`` wraps the service as the bus loop's ``Handler``. Frames the
service sends to a guarded drive's id go to that drive's proxy client in this process, and the
proxy's answers come back to the service, each encoded and decoded by the codec exactly as on the
bus (and written to ``capture`` when given, so ``canergy audit`` reads them). Every loop pass
drains the drives' TPDO samples into their guards, hands the guards' commands to the links, and
produces the host's heartbeat (and SYNC, when asked) that the drives' consumers watch: a host
whose loop stops, or whose process dies, goes silent and its drives fault on their own.

Devices of other profiles (``devices``: ODrive axes, ``canergy.devices``) are proxied the same
way; their links are pumped in the same pass and their status is under ``devices``, by profile.
With no CiA 402 drive there is no host heartbeat (``beat`` None): on a CAN Simple bus its
identifier is some axis's command (0x77F is node 59's Enter_DFU_Mode).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import can

from canergy.auth.frames import MAC_TYPE, FrameAuth, Verdict
from canergy.cia402.guard import DriveGuard
from canergy.codec import Codec, DecodeError
from canergy.devices.guard import DeviceGuard
from canergy.live.canopen.cia402_link import DriveLink
from canergy.live.devices.device_link import Device, DeviceLink
from canergy.live.devices.on_stuck import DeviceNews, OnStuck
from canergy.live.runtime import FramePath, Outgoing, RawFrame
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import SupervisorService
from canergy.messages import Direction, Message, MsgType, ToClient

NMT_OPERATIONAL = 0x05


def _name(guard: DriveGuard | DeviceGuard[Any]) -> str:
    """How the host's reports name a guarded drive or device (``moteus axis 1``, ``drive 9``)."""
    if isinstance(guard, DeviceGuard):
        noun = "motor" if guard.profile.name == "mit" else "axis"
        return f"{guard.profile.name} {noun} {guard.node}"
    return f"drive {guard.node}"


SYNC_ID = 0x080


@dataclass(frozen=True, slots=True)
class HostBeat:
    """The host's heartbeat (0x700 + host id, state OPERATIONAL) and optional SYNC."""

    host_id: int = 127
    heartbeat_us: int = 100_000
    sync_us: int | None = None


GuardedDevice = Device
"""A guarded device of another profile than CiA 402: its guard and its link."""


class GuardedDevices:
    """The guarded drives and devices of one host, their links and the host's heartbeat: made
    before the service, which takes their liveness and status (``alive``, ``status``);
    ``GuardedSupervisor`` then puts them in front of it."""

    def __init__(
        self,
        drives: dict[int, tuple[DriveGuard, DriveLink]],
        bus: can.BusABC | None,
        beat: HostBeat | None,
        now: int,
        *,
        devices: dict[int, GuardedDevice] | None = None,
        capture: can.Listener | None = None,
        report: Callable[[str], None] | None = None,
        liveness: Callable[[int, int], bool] | None = None,
        on_stuck: OnStuck | None = None,
        top_up: TopUp | None = None,
    ) -> None:
        """``liveness``: the test of the other nodes (the CANopen heartbeat watchdog);
        ``on_stuck``: ``--on-stuck``, run when a device becomes STUCK; ``top_up``: the
        supervisor's grant policy (``--target``): a guard whose stop threshold it never tops
        its proxy above holds its device with budget in hand (said at the start, when it
        happens, and in the status's ``stop_reason``, ``ProxyBooks.parked``)."""
        self.on_stuck = on_stuck
        self.report = report
        """Told in one line whenever a guard stops or releases its drive."""
        self.top_up = top_up
        self.parked_said: set[int] = set()
        """The nodes whose parking was reported (until the guard releases them)."""
        self.reported: dict[int, tuple[str, str | None]] = {}
        self.news = DeviceNews(report, on_stuck)
        """What is said of the guarded devices (and ``--on-stuck``)."""
        self.drives = drives
        self.devices = devices or {}
        self.bus = bus
        self.beat = beat
        self.capture = capture
        self.next_beat = now
        self.next_sync = now if beat is not None and beat.sync_us else None
        self.beat_failures = 0
        self.other_liveness = liveness
        self.links_closed = False
        self._warn_target()

    def _guards(self) -> list[DriveGuard | DeviceGuard[Any]]:
        return [g for g, _ in self.drives.values()] + [d for d, _ in self.devices.values()]

    def _warn_target(self) -> None:
        """A guard that stops at or above ``--target`` at its full limits: the supervisor's
        top-up never releases it (said once, at the start)."""
        if self.top_up is None or self.report is None:
            return
        target = self.top_up.target
        for guard in self._guards():
            if (needed := guard.release_uj()) >= target:
                self.report(
                    f"{_name(guard)}: --target {target / 1e6:.3f} J is not above where its guard "
                    f"stops it ({needed / 1e6:.3f} J: the bound at its limits, the reserve and "
                    "the margin above it to release it): "
                    "the top-up alone never releases it; raise --target above that, or lower "
                    "the limits"
                )

    def _parked(self, guard: DriveGuard | DeviceGuard[Any]) -> str | None:
        """``ProxyBooks.parked`` under this supervisor's top-up (None: no top-up)."""
        if self.top_up is None:
            return None
        return guard.parked(guard.stop_reason, self.top_up.target, self.top_up.minimum)

    def _tell_parked(self, guard: DriveGuard | DeviceGuard[Any]) -> None:
        """One line when the top-up leaves a stopped guard holding budget (again after each
        release)."""
        why = self._parked(guard)
        if why is None:
            if guard.stop_reason is None:
                self.parked_said.discard(guard.node)
            return
        if guard.node in self.parked_said:
            return
        self.parked_said.add(guard.node)
        if self.report is not None:
            self.report(f"{_name(guard)}: parked ({why})")

    def guards(self, node: int) -> bool:
        """Only the proxy in this process speaks for ``node``."""
        return node in self.drives or node in self.devices

    def alive(self, node: int, now: int) -> bool:
        if node in self.drives:
            return self.drives[node][0].alive(now)
        if node in self.devices:
            return self.devices[node][0].alive(now)
        return self.other_liveness is None or bool(self.other_liveness(node, now))

    def next_wakeup(self) -> int | None:
        """The next time ``pump`` has work; 0: at once."""
        times = [self.next_beat] if self.beat is not None else []
        if self.next_sync is not None:
            times.append(self.next_sync)
        for guard, link in self.drives.values():
            if link.pending() or (link.ready_at is not None and guard.ready_at is None):
                return 0
            times.append(guard.next_wakeup())
        for device, device_link in self.devices.values():
            if device_link.pending():
                return 0
            times.append(device.next_wakeup())
            if (own := device_link.next_wakeup()) is not None:
                times.append(own)
        return min(times) if times else None

    def pump(self, now: int, stopping: bool) -> list[Message]:
        """The links' news into the guards, their commands to the links (every guard halted
        when the supervisor is ``stopping``); what the guards send the supervisor."""
        up: list[Message] = []
        for guard, link in self.drives.values():
            if stopping and not guard.halted:
                guard.halt(now)
            if link.ready_at is not None and guard.ready_at is None:
                guard.on_ready(link.ready_at, link.setup)
            guard.watch(link.reaction_max_us, link.latency_max_us)
            for limits, taken, detail in link.drain_limits():
                up += guard.on_limits(now, limits, taken, detail)
            for at, write, age in link.drain_writes():
                up += guard.on_write(at, write, age)
            for seq, read in link.drain_verified():
                up += guard.on_verified(now, seq, read)
            for at, values, state, age in link.drain():
                up += guard.on_values(at, values, state, age)
            if guard.next_wakeup() <= now:
                up += guard.on_wakeup(now)
            self._hand_over(guard, link)
            self._tell(guard)
            self._tell_parked(guard)
        for device, device_link in self.devices.values():
            if stopping and not device.halted:
                device.halt(now)
            up += device_link.pump(device, now)
            if device.next_wakeup() <= now:
                up += device.on_wakeup(now)
            self._hand_over_device(device, device_link)
            self._tell(device)
            self._tell_parked(device)
        return up

    def guard(self, node: int) -> DriveGuard | DeviceGuard[Any]:
        return self.drives[node][0] if node in self.drives else self.devices[node][0]

    def produce(self, now: int) -> None:
        """The host's heartbeat and SYNC, when due (none without a bus)."""
        if self.beat is None:
            return
        if now >= self.next_beat:
            self.next_beat = now + self.beat.heartbeat_us
            self._send(0x700 + self.beat.host_id, bytes([NMT_OPERATIONAL]))
        if self.next_sync is not None and self.beat.sync_us and now >= self.next_sync:
            self.next_sync = max(self.next_sync + self.beat.sync_us, now)
            self._send(SYNC_ID, b"")

    def _send(self, arbitration_id: int, data: bytes) -> None:
        if self.bus is None:
            return
        try:
            frame = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
            self.bus.send(frame)
        except can.CanError:
            self.beat_failures += 1

    def status(self, now: int) -> dict[str, Any]:
        devices: dict[str, dict[str, Any]] = {}
        for n, (device, device_link) in self.devices.items():
            profile = devices.setdefault(device.profile.name, {})
            profile[str(n)] = {**device.status(now), **device_link.status()}
            if (why := self._parked(device)) is not None:
                profile[str(n)]["stop_reason"] = why
            if self.on_stuck is not None:
                profile[str(n)]["on_stuck"] = self.on_stuck.status(n)
        return {
            "host_id": None if self.beat is None else self.beat.host_id,
            "heartbeat_failures": self.beat_failures,
            "drives": {
                str(n): {**guard.status(now), **link.status(), **self._parked_reason(guard)}
                for n, (guard, link) in self.drives.items()
            },
            "devices": devices,
        }

    def _parked_reason(self, guard: DriveGuard) -> dict[str, str]:
        why = self._parked(guard)
        return {} if why is None else {"stop_reason": why}

    def halt_all(self, now: int) -> None:
        """Quick stop every drive that may still run (the supervisor is exiting); the links
        write it before they close."""
        for guard, link in self.drives.values():
            if not guard.halted:
                guard.halt(now)
            self._hand_over(guard, link)
        for device, device_link in self.devices.values():
            if not device.halted:
                device.halt(now)
            self._hand_over_device(device, device_link)

    def _tell(self, guard: DriveGuard | DeviceGuard[Any]) -> None:
        if isinstance(guard, DeviceGuard):
            self.news(guard)
            return
        seen = (guard.phase.value, guard.stop_reason)
        if self.report is None or self.reported.get(guard.node, seen) == seen:
            self.reported[guard.node] = seen
            return
        self.reported[guard.node] = seen
        left = f"{guard.usable / 1e6:.3f} J left"
        if guard.stop_reason is None:
            self.report(f"drive {guard.node}: released ({left})")
        else:
            self.report(f"drive {guard.node}: {guard.phase.value} ({guard.stop_reason}; {left})")

    @staticmethod
    def _hand_over(guard: DriveGuard, link: DriveLink) -> None:
        for cmd in guard.commands:
            link.command(cmd)
        guard.commands.clear()

    @staticmethod
    def _hand_over_device(device: DeviceGuard[Any], link: DeviceLink) -> None:
        for cmd in device.commands:
            link.command(cmd)
        device.commands.clear()

    def exit(self, clock: Callable[[], int]) -> list[Message]:
        """The supervisor exits, before its last status: every guard halted and its stop handed
        to its link; the links closed (each carries out what it holds first: the stops are on
        the bus); then what they heard until then taken in, each guard charged up to its
        device's latency past that moment, and booked. What the guards send the supervisor,
        each one's last TELEMETRY (HALTED, its level) at the end."""
        self.halt_all(clock())
        self._close_links()
        now = clock()
        up = self.pump(now, stopping=True)  # commands it makes now are not carried out
        for guard in self._guards():
            up += [*guard.on_exit(now), guard.telemetry(now)]
        return up

    def _close_links(self) -> None:
        if self.links_closed:
            return
        self.links_closed = True
        for _, link in self.drives.values():
            link.close()
        for _, device_link in self.devices.values():
            device_link.close()

    def close(self) -> None:
        self._close_links()
        if self.capture is not None:
            self.capture.stop()


class GuardedSupervisor:
    """Implements ``canergy.live.runtime.Handler``: the service behind the guarded devices."""

    def __init__(
        self,
        service: SupervisorService,
        guarded: GuardedDevices,
        *,
        codec: Codec | None = None,
    ) -> None:
        self.service = service
        self.guarded = guarded
        self.codec = codec or Codec()
        self._now = service.now
        """The time of the pass's last frame or deadline: a pass's end routes at it."""

    # -- Handler ---------------------------------------------------------------------------
    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        self._now = now
        # only the proxy, in this process, speaks for a drive
        if self.guarded.guards(msg.node):
            kind = "a drive's frame from the bus"
            if self.service.authenticated:  # it verified: only a key holder could send it
                self.service.authentic_intrusion(msg.node, repr(msg), kind, now)
            else:
                self.service.intrusion(msg.node, repr(msg), kind, now, stop=True)
            return ()
        return self._route(list(self.service.on_message(msg, now)), now)

    def on_decode_error(self, error: DecodeError, frame: can.Message) -> None:
        self.service.on_decode_error(error, frame)

    def on_foreign_direction(self, frame: can.Message, now: int) -> Sequence[Message]:
        return self.service.on_foreign_direction(frame, now)

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        self.service.on_auth_failure(verdict, frame, now)

    def next_wakeup(self) -> int | None:
        times = [
            t for t in (self.guarded.next_wakeup(), self.service.next_wakeup()) if t is not None
        ]
        return min(times) if times else None

    # -- PassHandler and the frame path -------------------------------------------------------
    def begin_pass(self) -> None:
        self.service.begin_pass()

    def end_pass(self) -> list[Outgoing]:
        """The service's frames of the pass (its books saved first): a proxy's go to it,
        encoded ones (the compiled core's) decoded for it; the rest to the bus."""
        out: list[Outgoing] = []
        messages: list[Message] = []
        for item in self.service.end_pass():
            if isinstance(item, RawFrame) and self.guarded.guards(item.arbitration_id & 0xFF):
                if item.arbitration_id >> 8 & 0xF == MAC_TYPE[Direction.TO_CLIENT]:
                    continue  # protected in C (--auth, classic): the message alone goes on
                to, data = Direction.TO_CLIENT, item.data
                if item.fd:  # protected in C (--auth, FD layout): the message, MAC left off
                    data = data[: self.codec.data_length(MsgType(item.arbitration_id >> 8 & 0xF))]
                messages.append(self.codec.decode(item.arbitration_id, data, direction=to))
            elif isinstance(item, RawFrame):
                out.append(item)
            else:
                messages.append(item)
        return out + self._route(messages, self._now)

    def frame_path(self, off: str | None = None, auth: FrameAuth | None = None) -> FramePath | None:
        """The service's frame path, behind the rule above: a frame in a guarded drive's name
        never reaches the compiled core (the usual path reports it as an intrusion)."""
        path = self.service.frame_path(off, auth)
        if path is None:
            return None
        take = path

        def frame(msg: can.Message, now: int) -> bool:
            self._now = now
            return not self.guarded.guards(msg.arbitration_id & 0xFF) and take(msg, now)

        return frame

    def on_wakeup(self, now: int) -> Sequence[Message]:
        self._now = now
        out = self._deliver(self.guarded.pump(now, self.service.stopping), now)
        wakeup = self.service.next_wakeup()
        if wakeup is not None and wakeup <= now:
            out += self.service.on_wakeup(now)
        self.guarded.produce(now)
        return self._route(out, now)

    # -- the in-process leg ----------------------------------------------------------------
    def _route(self, frames: list[Message], now: int) -> list[Message]:
        """Send on the bus what is not for a proxy; feed proxies until nothing is left."""
        to_bus: list[Message] = []
        queue = deque(frames)
        while queue:
            msg = queue.popleft()
            if not self.guarded.guards(msg.node) or not isinstance(msg, ToClient):
                to_bus.append(msg)
                continue
            down = self._loop_back(msg, Direction.TO_CLIENT, now)
            if isinstance(down, ToClient):
                guard = self.guarded.guard(msg.node)
                queue.extend(self._deliver(guard.on_message(down, now), now))
        return to_bus

    def _deliver(self, up: list[Message], now: int) -> list[Message]:
        out: list[Message] = []
        for msg in up:
            out += self.service.on_message(self._loop_back(msg, Direction.TO_SUPERVISOR, now), now)
        return out

    def _loop_back(self, msg: Message, direction: Direction, now: int) -> Message:
        arbitration_id, data = self.codec.encode(msg)
        if (capture := self.guarded.capture) is not None:
            frame = can.Message(
                timestamp=now / 1e6, arbitration_id=arbitration_id, data=data, channel="proxy"
            )
            capture.on_message_received(frame)
        return self.codec.decode(arbitration_id, data, direction=direction)

    def halt_all(self, now: int) -> None:
        self.guarded.halt_all(now)

    def exit(self, clock: Callable[[], int]) -> list[Message]:
        """``GuardedDevices.exit``, what the guards send taken by the service (the proxies'
        books end in its books); what is left for the bus."""
        up = self.guarded.exit(clock)
        now = clock()
        return self._route(self._deliver(up, now), now)

    def close(self) -> None:
        self.guarded.close()
