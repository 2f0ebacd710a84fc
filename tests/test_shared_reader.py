"""``SharedReader``, the bus loop's end of a shared Notifier: a wait on it ends by its timeout
whatever happens meanwhile. On CPython 3.11 ``can.BufferedReader``'s ``SimpleQueue.get`` waited
without end once its time ran out while it looped: a ``canergy supervisor --mit`` then never
ended on SIGTERM (test_vcan_mit_hosted; faulthandler showed its loop in ``get_message``)."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator

import can
import pytest

from canergy.live.canopen.shared_bus import SharedReader

RESCUE_S = 5.0
"""A frame put in after this ends a wait that would not end by itself."""


@pytest.fixture
def alarm() -> Iterator[None]:
    """SIGALRM's handler takes 0.3 s: longer than what is left of the wait it interrupts."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers run in the main thread only")
    old = signal.signal(signal.SIGALRM, lambda signum, frame: time.sleep(0.3))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _timed_wait(reader: SharedReader, timeout_s: float) -> tuple[can.Message | None, float]:
    """``get_message(timeout_s)`` with a rescue frame after ``RESCUE_S``; what it returned and
    how long it took."""
    rescue = threading.Timer(RESCUE_S, reader.on_message_received, (can.Message(data=b"r"),))
    rescue.start()
    started = time.monotonic()
    try:
        got = reader.get_message(timeout_s)
    finally:
        rescue.cancel()
    return got, time.monotonic() - started


def test_a_wait_a_signal_handler_outlasts_ends_at_its_timeout(alarm: None) -> None:
    reader = SharedReader()
    # a wait a wake ended: SimpleQueue's lock is then held, so the next wait blocks in it
    threading.Timer(0.05, reader.wake).start()
    assert reader.get_message(2) is None
    signal.setitimer(signal.ITIMER_REAL, 0.05)  # in the wait below, 0.15 s before its end
    got, took = _timed_wait(reader, 0.2)
    assert got is None and took < 2, f"waited {took:.2f} s (got {got})"


def test_tiny_waits_end_when_nothing_comes() -> None:
    """The loop's waits as short as its next deadline makes them, after frames taken without
    waiting (SimpleQueue's lock then left free)."""
    reader = SharedReader()
    for _ in range(1000):
        reader.on_message_received(can.Message(data=b"f"))
        reader.wake()
        assert reader.get_message(0) is not None and reader.get_message(0) is None
        got, took = _timed_wait(reader, 1e-7)
        assert got is None and took < 2, f"waited {took:.2f} s"


def test_frames_and_wakes_in_order_none_after_a_stop() -> None:
    reader = SharedReader()
    first, second = can.Message(data=b"1"), can.Message(data=b"2")
    reader.on_message_received(first)
    reader.wake()
    reader.on_message_received(second)
    assert reader.get_message(0.1) is first
    assert reader.get_message(0.1) is None  # the wake
    assert reader.get_message(0) is second
    started = time.monotonic()
    assert reader.get_message(0.05) is None and time.monotonic() - started >= 0.04
    reader.stop()
    started = time.monotonic()
    assert reader.get_message(5) is None and time.monotonic() - started < 1
    with pytest.raises(RuntimeError):
        reader.on_message_received(first)
