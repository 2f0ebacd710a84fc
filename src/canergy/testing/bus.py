"""A bus for a test and the processes on it: which interface and channel, the flags that name it,
device-under-test processes started with ``{channel}`` filled in, and a capture of its traffic."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can


def free_port() -> int:
    """A TCP port on 127.0.0.1 free now (the system's pick; free until someone takes it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def loopback(port: int) -> str:
    """The Zenoh endpoint of ``port`` on 127.0.0.1: nothing leaves this machine."""
    return f"tcp/127.0.0.1:{port}"


@dataclass(frozen=True, slots=True)
class TestBus:
    """``interface`` and ``channel`` as python-can takes them; ``fd``: open it for CAN FD;
    ``endpoint``: for ``zenoh``, the loopback endpoint the test's process listens on (``open``)
    and node processes connect to (``flags``)."""

    __test__ = False  # not a test class, whatever pytest collects

    interface: str = "virtual"
    channel: str = ""
    fd: bool = False
    endpoint: str = ""

    @classmethod
    def virtual(cls, fd: bool = False) -> TestBus:
        """python-can's virtual bus on a channel of its own (it connects only the buses of one
        process: the supervisor, the bridge and in-process nodes, never another process)."""
        return cls("virtual", f"canergy-{uuid.uuid4().hex[:12]}", fd)

    @classmethod
    def zenoh(cls, fd: bool = False) -> TestBus:
        """A bus that node processes reach without SocketCAN: canergy's ``zenoh`` interface
        (``canergy[zenoh]``) on a fresh site, over TCP on 127.0.0.1 at a free port. One bus of
        the test's process listens there (``open``, e.g. the bridge's side); processes connect
        (``flags``): two buses of the test's process cannot both open it."""
        return cls("zenoh", f"canergy-{uuid.uuid4().hex[:12]}", fd, loopback(free_port()))

    def sibling(self, channel: str | None = None) -> TestBus:
        """Another bus of the same interface: a fresh virtual channel (or Zenoh site and
        port), or ``channel``."""
        if channel is None:
            if self.interface == "zenoh" and self.endpoint:
                return TestBus.zenoh(self.fd)
            if self.interface != "virtual":
                raise ValueError(f"a second {self.interface} bus needs its channel name")
            return TestBus.virtual(self.fd)
        return TestBus(self.interface, channel, self.fd)

    @property
    def flags(self) -> list[str]:
        """The bus flags of a canergy command or the node emulator: ``-i ... -c ...``."""
        connect = ["--bus-kwargs", f"connect={self.endpoint}"] if self.endpoint else []
        return ["-i", self.interface, "-c", self.channel, *(["--fd"] if self.fd else []), *connect]

    def fill(self, text: str, **more: object) -> str:
        """``text`` with ``{interface}``, ``{channel}`` (and ``more``) filled in."""
        return text.format(interface=self.interface, channel=self.channel, **more)

    def open(self, **kwargs: Any) -> can.BusABC:
        """A python-can bus on this channel (the caller shuts it down)."""
        if self.endpoint:
            kwargs.setdefault("listen", self.endpoint)
        return can.Bus(interface=self.interface, channel=self.channel, fd=self.fd, **kwargs)


class Process:
    """A process of the test (a node under test), its stderr in ``log``; ``status``: the status
    file it writes, if any (``wait_started`` watches it)."""

    def __init__(
        self, name: str, argv: Sequence[str], cwd: Path, status: Path | None = None
    ) -> None:
        self.name, self.argv, self.cwd, self.status = name, list(argv), cwd, status
        self.started_at = 0.0
        self.log = cwd / f"{name}.stderr"
        self.log.write_bytes(b"")
        self.starts = 0
        """How many times it was started: 1, plus one per ``restart``."""
        self.popen = self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        self.starts += 1
        self.started_at = time.time()
        with open(self.log, "ab") as err:
            return subprocess.Popen(self.argv, stdout=subprocess.DEVNULL, stderr=err, cwd=self.cwd)

    def restart(self) -> None:
        """Start it again with the same command (after ``stop`` or ``power_cut``): a node
        coming back from what its NV file kept. Its stderr goes on in the same file."""
        if self.popen.poll() is None:
            raise RuntimeError(f"{self.name} is still running: stop or power_cut it first")
        self.popen = self._start()

    def wait_started(self, timeout_s: float = 30) -> None:
        """Wait until it has written its status file since it was last started (it is up: a
        SIGTERM now finds its handler), it ended, or ``timeout_s``; at once without a file."""
        deadline = time.monotonic() + timeout_s
        while self.status is not None and self.popen.poll() is None:
            with contextlib.suppress(FileNotFoundError):
                if self.status.stat().st_mtime >= self.started_at:
                    return
            if time.monotonic() > deadline:
                return
            time.sleep(0.02)

    def stderr(self) -> str:
        return self.log.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 60) -> int:
        """Ask it to stop (``sig``) and wait; killed when it will not. Its exit status."""
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                return self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
        return self.popen.wait(timeout_s)

    def power_cut(self) -> int:
        """SIGKILL: what survives is what it wrote (its NV file)."""
        return self.stop(signal.SIGKILL)


class Capture:
    """Every frame on ``bus`` logged to ``path`` (any python-can format by extension) while
    open; ``close`` ends it."""

    def __init__(self, bus: TestBus, path: Path) -> None:
        from canergy.inspect.candump import open_log

        self.path = path
        self._bus = bus.open()
        self._log, _ = open_log(path, bus.channel)
        self._notifier = can.Notifier(self._bus, [self._on_frame])

    def _on_frame(self, frame: can.Message) -> None:
        self._log.on_message_received(frame)

    def close(self) -> None:
        self._notifier.stop()
        self._log.stop()
        self._bus.shutdown()
