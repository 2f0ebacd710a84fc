"""Pieces of the live stack on their own: send retries, limits, the state file, FaultyBus."""

from __future__ import annotations

import errno
import json
import random
import re
import time
import uuid
from pathlib import Path

import can
import pytest

from canergy.codec import Codec
from canergy.core.state import Decision, Phase, Session, SupervisorState
from canergy.faults import FaultInjector, FaultProfile
from canergy.live.runtime import BusCounters, BusRuntime, monotonic_us, total_counters
from canergy.live.supervisor.policy import Limits, RateLimiter, TopUp, capped_grant, grant_caps
from canergy.live.supervisor.state_file import StateFileError, load_state, save_state
from canergy.live.transports.faulty_bus import FaultyBus
from canergy.messages import USABLE_MAX_UJ, Ack, Direction


class _FullQueueBus(can.BusABC):
    """Refuses the first ``refusals`` sends with ENOBUFS, as a full socketcan queue does."""

    def __init__(self, refusals: int, error: can.CanError | None = None) -> None:
        super().__init__(channel="full")
        self.refusals, self.sent = refusals, []
        self.error = error or can.CanOperationError("No buffer space", error_code=errno.ENOBUFS)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.refusals:
            self.refusals -= 1
            raise self.error
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        return None, False


class _Quiet:
    def on_message(self, msg, now):  # type: ignore[no-untyped-def]
        return ()

    def on_decode_error(self, error, frame):  # type: ignore[no-untyped-def]
        pass

    def next_wakeup(self) -> None:
        return None

    def on_wakeup(self, now):  # type: ignore[no-untyped-def]
        return ()


@pytest.mark.parametrize(("refusals", "sent", "failures"), [(0, 1, 0), (3, 1, 0), (6, 0, 1)])
def test_a_full_transmit_queue_is_retried_then_counted_as_lost(
    refusals: int, sent: int, failures: int
) -> None:
    bus = _FullQueueBus(refusals)
    sleeps: list[float] = []
    runtime = BusRuntime(bus, _Quiet(), receives=Direction.TO_SUPERVISOR, sleep=sleeps.append)
    runtime.send_messages([Ack(1, 1)])
    bus.shutdown()
    assert len(bus.sent) == sent and runtime.counters.send_failures == failures
    assert runtime.counters.send_retries == min(refusals, 5)
    assert sleeps == sorted(sleeps)  # backing off, never hurrying


def test_a_permanent_send_error_is_not_retried() -> None:
    bus = _FullQueueBus(1, can.CanOperationError("bus off", error_code=errno.ENETDOWN))
    runtime = BusRuntime(bus, _Quiet(), receives=Direction.TO_SUPERVISOR, sleep=lambda s: None)
    runtime.send_messages([Ack(1, 1), Ack(1, 2)])
    bus.shutdown()
    assert runtime.counters.send_failures == 1 and len(bus.sent) == 1


def test_limits_cap_every_grant() -> None:
    limits = Limits(max_grant=500_000, max_node_level=1_000_000, max_total=2_000_000)
    grant = dict(limits=limits, usable=10**9, granted_total=0, rate_tokens=None)
    assert capped_grant(2_000_000, level=0, **grant) == 500_000  # type: ignore[arg-type]
    assert capped_grant(2_000_000, level=800_000, **grant) == 200_000  # type: ignore[arg-type]
    assert capped_grant(400_400, level=0, **grant) == 400_000  # type: ignore[arg-type]
    spent = {**grant, "granted_total": 1_900_000}
    assert capped_grant(2_000_000, level=0, **spent) == 100_000  # type: ignore[arg-type]
    unknown = {**grant, "level": None}
    assert capped_grant(2_000_000, **unknown) == 0  # type: ignore[arg-type]  # fails closed
    poor = {**grant, "usable": 999}
    assert capped_grant(2_000_000, level=0, **poor) == 0  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        Limits(max_grant=0)


def test_each_cap_says_what_it_is_with_its_energies() -> None:
    limits = Limits(max_grant=500_000, max_node_level=1_000_000, max_total=2_000_000)
    caps = grant_caps(
        limits=limits, level=800_000, usable=3_000_000, granted_total=2_100_000, rate_tokens=-5
    )
    assert dict(caps) == {
        3_000_000: "the supervisor has 3.000000 J left",
        500_000: "--max-grant 0.500000 J",
        65_535_000: "one transaction carries at most 65.535 J",
        USABLE_MAX_UJ - 800_000: "the node's record holds no more",
        200_000: "--max-node-level 1.000000 J",
        -100_000: "--max-total 2.000000 J (0.000000 J left)",
        -5: "--rate (0.000000 J available now)",
    }


def test_rate_limiter_refills_at_its_rate() -> None:
    bucket = RateLimiter(1_000_000, burst=500_000)  # 1 W
    assert bucket.available(0) == 1_000_000
    bucket.take(1_000_000)
    assert bucket.available(250_000) == 250_000
    assert bucket.available(10_000_000) == 1_000_000
    assert RateLimiter(None, 1).available(5) is None
    assert TopUp(1_000_000, minimum=100_000).wanted(950_000) == 0
    assert TopUp(1_000_000).wanted(400_000) == 600_000


def _state() -> SupervisorState:
    sessions = (
        Session(1, Phase.WAIT_CONFIRM, 7, 500_000, 3_000_000, Decision.COMMIT, 2, 100_000, 2, 99),
        Session(4),
    )
    return SupervisorState(10_000_000, 6_600_000, 0, sessions)


def test_the_state_file_keeps_only_the_persistent_record(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    save_state(path, _state(), "hardened", fsync=True)
    loaded = load_state(path, "hardened", (1, 4, 9))
    assert loaded.sessions[0] == Session(
        1, Phase.WAIT_CONFIRM, 7, 500_000, 3_000_000, Decision.COMMIT, 2, 100_000
    )
    assert loaded.sessions[2] == Session(9) and loaded.usable == 6_600_000
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary was renamed into place


@pytest.mark.parametrize(
    ("content", "nodes", "message"),
    [
        ("{not json", (1, 4), "unreadable"),
        ('{"format": "x"}', (1, 4), "not a canergy-supervisor-state"),
        (None, (1,), "node(s) [4] not in --nodes"),
    ],
)
def test_a_bad_state_file_is_a_clear_error(
    tmp_path: Path, content: str | None, nodes: tuple[int, ...], message: str
) -> None:
    path = tmp_path / "s.json"
    save_state(path, _state(), "hardened")
    if content is not None:
        path.write_text(content)
    with pytest.raises(StateFileError, match=re.escape(message)):
        load_state(path, "hardened", nodes)


def test_a_state_file_of_another_variant_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    save_state(path, _state(), "hardened")
    assert json.loads(path.read_text())["variant"] == "hardened"
    with pytest.raises(StateFileError, match="variant"):
        load_state(path, "paper", (1, 4))


def test_faulty_bus_loses_duplicates_and_delays_on_the_wall_clock() -> None:
    channel = f"faulty-{uuid.uuid4().hex}"
    profile = FaultProfile(loss=0.3, duplicate=0.2, reorder=0.2, delay_us=1000, jitter_us=1000)
    injector = FaultInjector(profile, random.Random(1))
    sender = FaultyBus(can.Bus(interface="virtual", channel=channel), injector)
    with can.Bus(interface="virtual", channel=channel) as receiver:
        codec = Codec()
        for tx in range(200):
            arbitration_id, data = codec.encode(Ack(1, tx))
            sender.send(can.Message(arbitration_id=arbitration_id, data=data))
        for _ in range(50):  # 0.5 s: every held copy falls due and is released
            sender.recv(0.01)
        frames = iter(lambda: receiver.recv(0.1), None)
        got = [codec.decode(f.arbitration_id, f.data).tx for f in frames]  # type: ignore[union-attr]
    sender.shutdown()
    c = injector.counters
    assert len(got) == 200 - c.lost + c.duplicated and c.lost > 30 and c.duplicated > 10
    assert got != sorted(got)  # reordered


class _FlakyReceiveBus(_FullQueueBus):
    """Every receive fails, as a socket on an interface that went down does."""

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        raise can.CanOperationError("Network is down", error_code=errno.ENETDOWN)


def test_receive_errors_are_counted_not_fatal() -> None:
    bus = _FlakyReceiveBus(0)
    runtime = BusRuntime(bus, _Quiet(), receives=Direction.TO_SUPERVISOR, sleep=lambda s: None)
    for _ in range(3):
        runtime.poll(0.01)
    bus.shutdown()
    assert runtime.counters.receive_errors == 3


class _LinkBus(_FullQueueBus):
    """An interface the test takes down and back up (``ip link set vcan0 down``): while down,
    every receive and send fails with ENETDOWN; up, a frame is waiting."""

    def __init__(self) -> None:
        super().__init__(0, can.CanOperationError("Network is down", error_code=errno.ENETDOWN))
        self.down = False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.refusals = int(self.down)
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.down:
            raise self.error
        return can.Message(arbitration_id=0x123, data=b"\x01"), False


@pytest.mark.parametrize("sees", ["receive", "send"])
def test_a_link_down_is_in_the_status_until_a_frame_passes_again(sees: str) -> None:
    """python-can's default ``state`` says ``active`` whatever the link does (vcan0 down for 4 s
    showed ``bus_state: active``): the status says ``down`` from the first receive or send that
    fails with the interface gone, and what the driver reports once a frame passes again."""
    bus = _LinkBus()
    runtime = BusRuntime(bus, _Quiet(), receives=Direction.TO_SUPERVISOR, sleep=lambda s: None)
    frame = can.Message(arbitration_id=0x1, data=b"")

    def try_the_link() -> None:
        if sees == "receive":
            runtime.poll(0)
        else:
            runtime._send_frame(frame)

    runtime.poll(0)
    assert runtime.counters.as_json()["bus_state"] == "unknown"  # the driver reports none
    bus.down = True
    try_the_link()
    assert runtime.counters.as_json()["bus_state"] == "down"
    assert total_counters([BusCounters(), runtime.counters]).as_json()["bus_state"] == "down"
    bus.down = False
    try_the_link()
    assert runtime.counters.as_json()["bus_state"] == "unknown"
    bus.shutdown()


class _StatefulBus(_FullQueueBus):
    """A bus whose state the test sets (as a controller going error-passive would)."""

    def __init__(self) -> None:
        super().__init__(0)
        self.now_state = can.BusState.ACTIVE
        self.reads = 0

    @property
    def state(self) -> can.BusState:
        self.reads += 1
        return self.now_state


def test_a_bus_state_change_is_counted_within_its_period() -> None:
    from canergy.live.runtime import BUS_STATE_PERIOD_US

    bus, now = _StatefulBus(), [1_000]
    runtime = BusRuntime(bus, _Quiet(), receives=Direction.TO_SUPERVISOR, clock=lambda: now[0])
    runtime.poll(0)
    assert runtime.counters.bus_state == "active" and bus.reads == 1
    bus.now_state = can.BusState.PASSIVE
    for _ in range(50):  # many passes within one period: the driver is asked once
        now[0] += BUS_STATE_PERIOD_US // 100
        runtime.poll(0)
    assert runtime.counters.bus_state == "active" and bus.reads == 1
    now[0] += BUS_STATE_PERIOD_US
    runtime.poll(0)
    assert runtime.counters.bus_state == "passive" and bus.reads == 2
    bus.shutdown()


@pytest.mark.skipif(not hasattr(time, "CLOCK_BOOTTIME"), reason="Linux's clock")
def test_time_the_host_spent_suspended_counts(monkeypatch: pytest.MonkeyPatch) -> None:
    """review rv3 (F7): the live clock stopped while the host was suspended (CLOCK_MONOTONIC),
    so a drive that ran on meanwhile (an ODrive without its watchdog) was never charged for it.
    A suspend of 60 s, as the two clocks then differ, moves the live clock by 60 s."""
    read = time.clock_gettime_ns
    slept = 60 * 10**9

    def after_a_suspend(clock: int) -> int:
        return read(clock) + (slept if clock == time.CLOCK_BOOTTIME else 0)

    before = monotonic_us()
    monkeypatch.setattr(time, "clock_gettime_ns", after_a_suspend)
    monkeypatch.setattr(time, "monotonic_ns", lambda: read(time.CLOCK_MONOTONIC))
    assert monotonic_us() - before >= slept // 1000
