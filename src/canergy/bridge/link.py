"""A bridge between two python-can buses: each frame received on one is sent on the other as
its ``FaultSchedule`` decides (lost, duplicated, delayed, reordered, corrupted, or cut off by a
partition), on the monotonic clock.

A reader thread per bus queues what it receives; ``poll`` (one thread) decides each frame's
fate, sends what falls due and logs both buses' traffic as the bridge sees it to an optional
capture (each frame under its bus's name as channel: what it received there and what it sent
there).

Given node processes by name (anything with ``power_cut()`` and ``restart()``, such as the pytest
plugin's ``Process``), it also cuts their power when the schedule's power cuts (``PowerCut``)
say, counted per process.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import can

from canergy.bridge.schedule import FaultSchedule, Held
from canergy.inspect.candump import FrameLog
from canergy.live.runtime import monotonic_us

log = logging.getLogger(__name__)

QUEUE_FRAMES = 8192
"""Frames received and not yet decided, both buses; beyond, a frame is dropped and counted."""


def copy_frame(msg: can.Message, data: bytes, channel: str | None = None) -> can.Message:
    """``msg`` with ``data`` (a bit may be flipped), its identifier, CAN FD flags and remote
    flag kept, for sending on another bus."""
    return can.Message(
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_fd=msg.is_fd,
        bitrate_switch=msg.bitrate_switch,
        error_state_indicator=msg.error_state_indicator,
        dlc=msg.dlc if msg.is_remote_frame else None,
        data=None if msg.is_remote_frame else data,
        channel=channel,
    )


class Switchable(Protocol):
    """A node process whose power a bridge cuts: killed, then started again."""

    def power_cut(self) -> object: ...

    def restart(self) -> None: ...


class Bridge:
    """Carries frames between ``buses`` (first, second) through ``schedule``; ``names`` are
    the buses' channels in the capture and the status; ``processes``: the node processes the
    schedule's power cuts switch, by name (read when a cut falls due, so it may fill later).
    ``close`` stops the readers, not the buses (their owner shuts them down)."""

    def __init__(
        self,
        buses: tuple[can.BusABC, can.BusABC],
        schedule: FaultSchedule,
        *,
        names: tuple[str, str] = ("bus1", "bus2"),
        capture: FrameLog | None = None,
        clock: Callable[[], int] = monotonic_us,
        processes: Mapping[str, Switchable] | None = None,
    ) -> None:
        if schedule.power_cuts and processes is None:
            raise ValueError("the faults cut the power of node processes: give the bridge them")
        self.buses, self.schedule, self.names = buses, schedule, names
        self.processes: Mapping[str, Switchable] = processes if processes is not None else {}
        self.power: dict[str, dict[str, int]] = {}
        """Per node process: ``cuts`` (killed) and ``restarts`` (started again)."""
        self.power_errors: list[str] = []
        """Power cuts that could not be made (no process of that name, or it failed)."""
        self._off: dict[str, int] = {}  # cuts now on, per process (they may overlap)
        self._power_lock = threading.Lock()
        self._power_restored = False
        self.capture, self.clock = capture, clock
        self.start_us = clock()
        self.dropped = 0
        """Frames received while the queue was full (never decided: lost to both sides)."""
        self.receive_errors = 0
        self.error_frames = 0
        """Error frames received: not forwarded (the other bus has errors of its own)."""
        self._held: Held[tuple[int, can.Message]] = Held()
        self._frames: queue.Queue[tuple[int, int, can.Message]] = queue.Queue(QUEUE_FRAMES)
        self._running = True
        self._readers = [
            threading.Thread(target=self._read, args=(i,), name=f"bridge-{i}", daemon=True)
            for i in (0, 1)
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, side: int) -> None:
        bus = self.buses[side]
        while self._running:
            try:
                frame = bus.recv(timeout=0.1)
            except Exception:  # a bus going down, or closed under us at shutdown
                if self._running:
                    log.exception("bridge: receive on %s failed; retrying", self.names[side])
                    self.receive_errors += 1
                    time.sleep(0.1)
                continue
            if frame is None:
                continue
            try:
                self._frames.put_nowait((side, self.clock(), frame))
            except queue.Full:
                self.dropped += 1

    def poll(self, max_wait_s: float = 0.05) -> None:
        """Wait for a frame (at most until the next held copy falls due, or ``max_wait_s``),
        decide every frame received, send every copy due."""
        due = self._held.next_due()
        switch = self.schedule.next_power_event()
        if switch is not None:
            due = min(due, switch + self.start_us) if due is not None else switch + self.start_us
        if due is not None:
            max_wait_s = max(0.0, min(max_wait_s, (due - self.clock()) / 1e6))
        try:
            first = self._frames.get(timeout=max_wait_s) if max_wait_s > 0 else None
        except queue.Empty:
            first = None
        if first is not None:
            self._decide(*first)
        while True:
            try:
                self._decide(*self._frames.get_nowait())
            except queue.Empty:
                break
        now = self.clock()
        self._release(now)
        self._switch_power(now)

    def _decide(self, side: int, t_us: int, frame: can.Message) -> None:
        self._log(frame, side)
        if frame.is_error_frame:
            self.error_frames += 1
            return
        for due, data in self.schedule.fate(side, bytes(frame.data), t_us - self.start_us):
            self._held.push(due + self.start_us, (1 - side, copy_frame(frame, data)))

    def _release(self, now_us: int) -> None:
        for side, frame in self._held.pop_due(now_us):
            counts = self.schedule.counts[1 - side]
            try:
                self.buses[side].send(frame, timeout=0.1)
            except can.CanError as exc:
                counts.send_errors += 1
                log.warning("bridge: send on %s failed: %s", self.names[side], exc)
                continue
            counts.forwarded += 1
            frame.timestamp = time.time()
            self._log(frame, side)

    def _switch_power(self, now_us: int) -> None:
        """Make the power cuts due: kill a process when its first cut starts, start it again
        when its last one ends."""
        with self._power_lock:
            if self._power_restored:
                return
            for on, node in self.schedule.power_events(now_us - self.start_us):
                if not node and not on and not self.processes:
                    self.power_errors.append("power cut of every node process: there is none")
                for name in [node] if node else list(self.processes):
                    self._switch(name, on)

    def _switch(self, name: str, on: bool) -> None:
        off = self._off.get(name, 0)
        if on and off == 0:  # never cut: not there then (or a cut of every process before it)
            return
        process = self.processes.get(name)
        if process is None:
            have = ", ".join(self.processes) or "none"
            self.power_errors.append(
                f"power cut of {name!r}: no such node process ({have}); start it before its "
                "cut falls due"
            )
            return
        counts = self.power.setdefault(name, {"cuts": 0, "restarts": 0})
        if off != (1 if on else 0):  # still off under another cut, or off already
            self._off[name] = off - 1 if on else off + 1
            return
        try:
            if on:
                process.restart()
            else:
                process.power_cut()
        except Exception as exc:  # the bridge goes on; the error is reported
            log.exception("bridge: power %s of %s failed", "on" if on else "off", name)
            self.power_errors.append(f"power {'on' if on else 'off'} of {name!r}: {exc!r}")
            if not on:
                return  # not cut: nothing to restart
        else:
            counts["restarts" if on else "cuts"] += 1
        self._off[name] = off - 1 if on else off + 1

    def restore_power(self) -> None:
        """End every power cut now (the processes off are started again) and make no more: a
        test's teardown does this before it stops the supervisor, so every node settles."""
        with self._power_lock:
            self._power_restored = True
            for name, off in list(self._off.items()):
                if off > 0:
                    self._off[name] = 1
                    self._switch(name, True)

    def _log(self, frame: can.Message, side: int) -> None:
        if self.capture is not None:
            frame.channel = self.names[side]
            self.capture.on_message_received(frame)

    def run(self, stop: Callable[[], bool], each: Callable[[int], None] | None = None) -> None:
        """Poll until ``stop()``; ``each(now_us)`` after every poll (status lines, files)."""
        while not stop():
            self.poll()
            if each is not None:
                each(self.clock())

    def status(self) -> dict[str, Any]:
        """Counts so far, per direction named ``FROM>TO``, and the seed and faults."""
        schedule = self.schedule.as_json()
        directions = schedule.pop("directions")
        assert isinstance(directions, list)
        a, b = self.names
        return {
            "role": "bridge",
            "uptime_s": round((self.clock() - self.start_us) / 1e6, 3),
            "buses": list(self.names),
            **schedule,
            "directions": {f"{a}>{b}": directions[0], f"{b}>{a}": directions[1]},
            "held": len(self._held),
            "dropped": self.dropped,
            "receive_errors": self.receive_errors,
            "error_frames": self.error_frames,
            **self._power_status(),
        }

    def _power_status(self) -> dict[str, Any]:
        with self._power_lock:
            power = {n: {**c, "off": self._off.get(n, 0) > 0} for n, c in self.power.items()}
            return {"power": power, "power_errors": list(self.power_errors)}

    def close(self) -> None:
        """Stop the readers (the buses stay open)."""
        self._running = False
        for reader in self._readers:
            reader.join(timeout=1.0)
