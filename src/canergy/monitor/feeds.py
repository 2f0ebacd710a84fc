"""Where the frames come from: a python-can bus, read by a ``can.Notifier`` thread, or a capture
replayed in its own thread at the capture's pace (times a speed factor) or as fast as it reads.

Either thread feeds the model under the shared lock and nothing else; the screen is drawn by
another thread, so a slow terminal never delays reading. The monitor opens the bus only to
receive: nothing here sends a frame.
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Protocol

import can

from canergy.inspect.captures import CaptureError
from canergy.monitor.model import MonitorModel

BUS_ERROR_PAUSE_S = 0.2
"""After a receive error (an adapter unplugged...) the reader waits this long before retrying."""
_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33 if sys.platform == "linux" else None)
"""Linux's value where Python's socket module does not name it (3.11 does not)."""
RECEIVE_BUFFER = 4 << 20
"""Socket receive buffer asked for (SocketCAN's default holds about 280 frames: 56 ms at
5,000 frames/s)."""


def enlarge_receive_buffer(bus: can.BusABC, size: int = RECEIVE_BUFFER) -> int | None:
    """Ask for a ``size`` byte receive buffer on a bus that reads a socket (SocketCAN), so the
    reader thread may pause longer without losing frames: beyond ``net.core.rmem_max`` only with
    CAP_NET_ADMIN (SO_RCVBUFFORCE). The buffer's size now, or None for a bus without a socket."""
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return None
    for option in (_RCVBUFFORCE, socket.SO_RCVBUF):
        if option is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size)
            break
        except OSError:
            continue
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


class Feed(Protocol):
    """What the screen loop needs of a frame source."""

    def start(self) -> None: ...
    def stop(self) -> None: ...
    def now(self) -> float:
        """The model's clock: frames were fed with times on this scale."""
        ...

    def pause(self, paused: bool) -> None: ...
    def step(self) -> None:
        """While paused, take the next frame (a replay; a bus ignores it)."""
        ...

    def state(self, paused: bool) -> str:
        """For the title's corner: ``live``, ``replay x1 12.3 s in``... The frame count beside
        it is the snapshot's (``MonitorModel.frames``), never the feed's own."""
        ...


class ModelListener(can.Listener):
    """Feeds every received frame to the model, stamped with the monitor's monotonic clock."""

    def __init__(
        self,
        model: MonitorModel,
        lock: threading.Lock,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.model, self.lock, self.clock = model, lock, clock
        self.received = 0
        self.failing = False
        """The latest receive failed: its error is on the screen until a frame arrives."""

    def on_message_received(self, msg: can.Message) -> None:
        t = self.clock()
        with self.lock:
            self.model.feed(msg, t)
            if self.failing:
                self.model.note("bus", None)
                self.failing = False
        self.received += 1

    def on_error(self, exc: Exception) -> None:
        with self.lock:
            self.model.note("bus", f"receive error: {exc}")
            self.failing = True
        time.sleep(BUS_ERROR_PAUSE_S)


class LiveFeed:
    """A bus, read by python-can's ``Notifier`` thread. Pausing freezes only the screen: the
    frames keep being counted."""

    def __init__(self, bus: can.BusABC, model: MonitorModel, lock: threading.Lock) -> None:
        self.bus = bus
        self.listener = ModelListener(model, lock)
        self._notifier: can.Notifier | None = None

    def start(self) -> None:
        enlarge_receive_buffer(self.bus)
        self._notifier = can.Notifier(self.bus, [self.listener], timeout=0.2)

    def stop(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(timeout=2)

    def now(self) -> float:
        return time.monotonic()

    def pause(self, paused: bool) -> None:
        pass

    def step(self) -> None:
        pass

    def state(self, paused: bool) -> str:
        return "PAUSED (still counting)" if paused else "live"


class ReplayFeed:
    """A capture fed at its own pace times ``speed`` (None: as fast as it reads). The clock is
    the capture's: pausing stops it, and a step while paused jumps it to the next frame."""

    def __init__(
        self,
        frames: Iterator[can.Message],
        model: MonitorModel,
        lock: threading.Lock,
        speed: float | None,
    ) -> None:
        self._frames, self.model, self.lock, self.speed = frames, model, lock, speed
        self._cond = threading.Condition()
        self._paused = False
        self._steps = 0
        self._stopped = False
        self.fed = 0
        """Frames handed to the model, for ``step``: the screen counts them in the model."""
        self.done = False
        self.first: float | None = None
        self.last = 0.0
        """Time of the latest frame fed."""
        self.position = 0.0
        """Capture time of the clock when it was last anchored (start, pause, step)."""
        self._anchor = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="canergy-replay", daemon=True)

    # -- the clock -----------------------------------------------------------------------------
    def now(self) -> float:
        with self._cond:
            return self._clock()

    def _clock(self) -> float:
        """Stopped while paused, before the first frame and after the last (at its time)."""
        if self._paused or self.speed is None or self.first is None or self.done:
            return self.position
        return self.position + (time.monotonic() - self._anchor) * self.speed

    def _set(self, position: float) -> None:
        self.position, self._anchor = position, time.monotonic()

    # -- control -------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._thread.join(timeout=5)

    def pause(self, paused: bool) -> None:
        with self._cond:
            if paused != self._paused:
                self._set(self._clock())
                self._paused = paused
                self._cond.notify_all()

    def step(self) -> None:
        """Feed the next frame (while paused) and return once the model has it."""
        with self._cond:
            if not self._paused or self.done:
                return
            target = self.fed + 1
            self._steps += 1
            self._cond.notify_all()
            self._cond.wait_for(lambda: self.fed >= target or self.done, timeout=2.0)

    def state(self, paused: bool) -> str:
        with self._cond:
            elapsed = self._clock() - (self.first or 0.0) if self.first is not None else 0.0
            done = self.done
        if done:
            return "replay done"
        pace = "fast" if self.speed is None else f"x{self.speed:g}"
        return f"replay {pace}{' PAUSED' if paused else ''} {elapsed:.1f} s in"

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            for frame in self._frames:
                t = self._wait_for(frame.timestamp)
                if t is None:
                    return
                with self.lock:
                    self.model.feed(frame, t)
                with self._cond:
                    self.fed += 1
                    self.last = max(self.last, t)
                    self._cond.notify_all()
        except CaptureError as exc:
            with self.lock:
                self.model.note("capture", str(exc))
        finally:
            with self._cond:
                self._set(max(self.last, self.first or 0.0))
                self.done = True
                self._cond.notify_all()

    def _wait_for(self, stamp: float | None) -> float | None:
        """Block until the clock reaches ``stamp`` (or a step); its time on the clock, or None
        when stopped. A frame without a timestamp, or earlier than the clock, goes at once."""
        with self._cond:
            if self.first is None:
                self.first = stamp or 0.0
                self._set(self.first)
            if not stamp:
                return self._clock()
            while not self._stopped:
                if self._paused and self._steps:
                    self._steps -= 1
                    self._set(max(stamp, self.position))
                    return stamp
                if self._paused:
                    self._cond.wait()
                    continue
                ahead = stamp - self._clock()
                if self.speed is None or ahead <= 0:
                    if self.speed is None:
                        self.position = max(self.position, stamp)
                    return stamp
                self._cond.wait(ahead / self.speed)
            return None
