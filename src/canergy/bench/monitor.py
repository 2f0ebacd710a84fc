"""``canergy monitor`` at a given frame rate: does its reader keep up?

A sender thread paces canergy traffic (nominal transactions, returns and telemetry of 16 nodes,
encoded by the codec) onto python-can's virtual bus at ``rate`` frames/s; the monitor reads the
same bus through the very path its screen uses (``LiveFeed``: a ``can.Notifier`` thread feeding
the model under the lock) while the main thread renders the screen four times a second, as the
curses loop does. Reported: frames sent and counted, the sender's achieved rate, the reader
thread's CPU per frame (receive and model), the render's CPU per screen, and the latency from
send to counted.
"""

from __future__ import annotations

import statistics
import threading
import time
import uuid
from typing import Any

import can

from canergy.codec import Codec
from canergy.messages import (
    Ack,
    Commit,
    Committed,
    Intention,
    Message,
    Return,
    ReturnAck,
    Telemetry,
)
from canergy.monitor.feeds import LiveFeed, ModelListener
from canergy.monitor.model import MonitorModel
from canergy.monitor.render import Context, screen
from canergy.monitor.view import View

NODES = 16
RATE = 5000
RENDER_PERIOD_S = 0.25


def traffic(count: int) -> list[can.Message]:
    """``count`` frames: per node in turn, a committed transaction, a telemetry report and
    every fourth time a return, with growing transaction and return numbers."""
    codec = Codec()
    messages: list[Message] = []
    tx = 0
    while len(messages) < count:
        tx += 1
        for node in range(1, NODES + 1):
            gs = (tx - 1) * 10 % (1 << 24)
            messages += [
                Intention(node, tx & 0xFFFF, 10, gs),
                Ack(node, tx & 0xFFFF),
                Commit(node, tx & 0xFFFF, 10),
                Committed(node, tx & 0xFFFF),
                Telemetry(node, 500 + tx % 100),
            ]
            if tx % 4 == 0:
                seq = tx // 4 & 0xFFFF
                messages += [Return(node, seq, 5), ReturnAck(node, seq)]
    frames = []
    for m in messages[:count]:
        ident, data = codec.encode(m)
        frames.append(can.Message(arbitration_id=ident, data=data, is_extended_id=True))
    return frames


class _Measured(ModelListener):
    """The screen's listener, also keeping its thread's CPU time and each frame's latency."""

    def __init__(self, model: MonitorModel, lock: threading.Lock) -> None:
        super().__init__(model, lock)
        self.cpu_first: float | None = None
        self.cpu_last = 0.0
        self.latencies: list[float] = []

    def on_message_received(self, msg: can.Message) -> None:
        if self.cpu_first is None:
            self.cpu_first = time.thread_time()
        super().on_message_received(msg)
        self.latencies.append(time.time() - msg.timestamp)
        self.cpu_last = time.thread_time()


def _send(bus: can.BusABC, frames: list[can.Message], rate: float, done: list[float]) -> None:
    start = time.perf_counter()
    for i, frame in enumerate(frames):
        due = start + i / rate
        ahead = due - time.perf_counter()
        if ahead > 0:
            time.sleep(ahead)
        bus.send(frame)
    done.append(time.perf_counter() - start)


def throughput(frames: int, rate: float = RATE, timeout_s: float = 30.0) -> dict[str, Any]:
    """Send ``frames`` at ``rate`` and count them in the monitor."""
    channel = f"bench-monitor-{uuid.uuid4().hex}"
    sent = traffic(frames)
    model, lock = MonitorModel(Codec(), bitrate=1_000_000), threading.Lock()
    with (
        can.Bus(interface="virtual", channel=channel) as monitor_bus,
        can.Bus(interface="virtual", channel=channel) as sender_bus,
    ):
        feed = LiveFeed(monitor_bus, model, lock)
        listener = feed.listener = _Measured(model, lock)
        feed.start()
        took: list[float] = []
        sender = threading.Thread(target=_send, args=(sender_bus, sent, rate, took))
        render_cpu: list[float] = []
        view, ctx = View(), Context("bench", "live")
        try:
            sender.start()
            deadline = time.monotonic() + frames / rate + timeout_s
            while listener.received < frames and time.monotonic() < deadline:
                time.sleep(RENDER_PERIOD_S)
                before = time.thread_time()
                with lock:
                    snap = model.snapshot(time.monotonic())
                screen(snap, view, ctx, 160, 50)
                render_cpu.append(time.thread_time() - before)
            sender.join()
        finally:
            feed.stop()
    counted = listener.received
    cpu = listener.cpu_last - (listener.cpu_first or 0.0)
    latencies = sorted(listener.latencies)
    return {
        "rate_target": rate,
        "frames_sent": len(sent),
        "frames_counted": counted,
        "model_frames": model.frames,
        "kept_up": counted == len(sent),
        "sent_per_s": len(sent) / took[0] if took and took[0] > 0 else None,
        "reader_cpu_us_per_frame": cpu / (counted - 1) * 1e6 if counted > 1 else None,
        "reader_cpu_share": cpu / took[0] if took and took[0] > 0 else None,
        "render_ms_per_screen": statistics.median(render_cpu) * 1e3 if render_cpu else None,
        "latency_p50_ms": latencies[len(latencies) // 2] * 1e3 if latencies else None,
        "latency_max_ms": latencies[-1] * 1e3 if latencies else None,
    }


def lines(r: dict[str, Any]) -> list[str]:
    """The monitor's rows of ``canergy bench``'s table."""

    def n(value: float | None, spec: str) -> str:
        return "n/a" if value is None else format(value, spec)

    return [
        "",
        f"canergy monitor reading python-can virtual at {r['rate_target']:,} frames/s "
        "(16 nodes of canergy traffic, screen drawn 4 times a second)",
        f"  frames sent {r['frames_sent']:,} (at {n(r['sent_per_s'], ',.0f')}/s), counted "
        f"{r['frames_counted']:,}: {'kept up' if r['kept_up'] else 'FELL BEHIND'}; reader "
        f"{n(r['reader_cpu_us_per_frame'], '.1f')} us CPU per frame "
        f"({n(r['reader_cpu_share'], '.0%')} of a core), screen "
        f"{n(r['render_ms_per_screen'], '.2f')} ms; latency p50 "
        f"{n(r['latency_p50_ms'], '.2f')} ms, max {n(r['latency_max_ms'], '.1f')} ms",
    ]
