"""Where the vcan suite runs, and the timeouts it sizes from what it measures there.

A test of separate processes on SocketCAN cannot drive time: the kernel schedules them. Inside
user-mode Linux every process shares one virtual CPU behind ptrace, and a process can be held off
for hundreds of milliseconds (a 20 ms TPDO stream showed 385-488 ms gaps); on a host kernel it is
rarely more than a few. So the CiA 402 tests do not take their PDO timeout, heartbeat consumer time
and SDO timeout from constants: ``venue()`` measures once per run how long a process of this venue
can be held off (a 20 ms frame stream from a child process, read here while another child burns
the CPU) and sizes them from that, with a floor per venue. The pytest summary line prints the venue
and the figures used (``report``), so a failing run says what it assumed.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import can

PERIOD_S = 0.02
PROBE_S = 2.0
_SENDER = """
import sys, time, can
bus = can.Bus(interface="socketcan", channel=sys.argv[1])
start = time.monotonic()
n = 0
while time.monotonic() - start < float(sys.argv[2]):
    bus.send(can.Message(arbitration_id=0x7F0, data=n.to_bytes(4, "little"), is_extended_id=False))
    n += 1
    time.sleep(float(sys.argv[3]))
bus.shutdown()
"""
_HOG = """
import sys, time
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    pass
"""


def user_mode_linux() -> bool:
    """Whether this kernel is user-mode Linux (its /proc/cpuinfo names it)."""
    try:
        return "User Mode Linux" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@dataclass(frozen=True)
class Venue:
    name: str
    stall_ms: int
    """The longest gap seen in a 20 ms frame stream from another process, less its period."""
    start_s: float
    """How long a child Python with python-can took to send its first frame."""

    @property
    def floor_ms(self) -> int:
        return 1000 if self.name == "user-mode Linux" else 300

    @property
    def pdo_timeout_ms(self) -> int:
        """The guard's PDO timeout: four stalls, at least the venue's floor, at most 2 s."""
        raw = max(self.floor_ms, 4 * self.stall_ms)
        return min(2000, -(-raw // 50) * 50)

    @property
    def consumer_timeout_s(self) -> float:
        """The drive's heartbeat consumer time: beyond the PDO timeout, at least 1 s."""
        return max(1.0, 2 * self.pdo_timeout_ms / 1000)

    @property
    def sdo_timeout_s(self) -> float:
        """A python-canopen application's SDO response timeout (the library's default is 0.3 s)."""
        return max(2.0, 10 * self.stall_ms / 1000, 4 * self.start_s)

    def report(self) -> str:
        return (
            f"vcan venue: {self.name}; measured: a process held off up to {self.stall_ms} ms, "
            f"a child's first frame after {self.start_s:.2f} s; timeouts used: PDO "
            f"{self.pdo_timeout_ms} ms, heartbeat consumer {self.consumer_timeout_s:g} s, "
            f"SDO {self.sdo_timeout_s:g} s"
        )


def measure(channel: str) -> Venue:
    """Read a child's 20 ms frame stream on ``channel`` for 2 s while another child hogs the
    CPU: the longest gap, and the time to its first frame."""
    name = "user-mode Linux" if user_mode_linux() else "host kernel"
    with can.Bus(interface="socketcan", channel=channel, receive_own_messages=False) as bus:
        bus.set_filters([{"can_id": 0x7F0, "can_mask": 0x7FF, "extended": False}])
        began = time.monotonic()
        hog = subprocess.Popen([sys.executable, "-c", _HOG, str(PROBE_S + 2)])
        sender = subprocess.Popen(
            [sys.executable, "-c", _SENDER, channel, str(PROBE_S), str(PERIOD_S)]
        )
        try:
            arrivals: list[float] = []
            deadline = began + 60
            while sender.poll() is None and time.monotonic() < deadline:
                if bus.recv(timeout=0.2) is not None:
                    arrivals.append(time.monotonic())
            while bus.recv(timeout=0.1) is not None:
                arrivals.append(time.monotonic())
        finally:
            for proc in (sender, hog):
                proc.kill()
                proc.wait(30)
    assert len(arrivals) > 10, f"the venue probe heard {len(arrivals)} frames on {channel}"
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    stall_ms = max(0, round((max(gaps) - PERIOD_S) * 1000))
    return Venue(name, stall_ms, arrivals[0] - began)


MEASURED: dict[str, Venue] = {}
"""The venues measured in this run, by channel (the pytest summary prints them)."""


def venue(channel: str) -> Venue:
    """The venue, measured once per run."""
    if channel not in MEASURED:
        MEASURED[channel] = measure(channel)
    return MEASURED[channel]
