"""The cost of authenticated mode: CPU per frame (MAC built and checked) against the plain codec
in the same process, and frames and data bytes per nominal transaction in each layout."""

from __future__ import annotations

import statistics
import time
from typing import Any

from canergy.auth.frames import FrameAuth, Layout, freshness
from canergy.codec import Codec
from canergy.messages import Ack, Commit, Committed, Direction, Intention, Message

TRANSACTION: list[Message] = [
    Intention(5, 1234, 2500, 777_000),
    Ack(5, 1234),
    Commit(5, 1234, 2500),
    Committed(5, 1234),
]
"""A nominal transaction: intention, acknowledge, commit, committed."""


def _pair(layout: Layout) -> tuple[FrameAuth, FrameAuth]:
    codec, key = Codec(), bytes(16)

    def fresh(msg: Message) -> int:
        return freshness(msg, 1234, 9)

    return (
        FrameAuth(codec, layout, lambda n: key, Direction.TO_SUPERVISOR, fresh),
        FrameAuth(codec, layout, lambda n: key, Direction.TO_CLIENT, fresh),
    )


def _median_us(fn: Any, loops: int, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(loops):
            fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) / loops / len(TRANSACTION) * 1e6


def overhead(loops: int = 500, repeats: int = 7) -> dict[str, Any]:
    codec = Codec()

    def plain() -> None:
        for msg in TRANSACTION:
            arbitration_id, data = codec.encode(msg)
            codec.decode(arbitration_id, data)

    baseline = _median_us(plain, loops, repeats)
    rows = [
        {
            "layout": "plain",
            "us_per_frame": baseline,
            "frames_per_tx": len(TRANSACTION),
            "bytes_per_tx": sum(len(codec.encode(m)[1]) for m in TRANSACTION),
        }
    ]
    for layout in Layout:
        sup, node = _pair(layout)

        def authenticated(sup: FrameAuth = sup, node: FrameAuth = node) -> None:
            for msg in TRANSACTION:
                receiver = node if msg.TYPE.direction is Direction.TO_CLIENT else sup
                sender = sup if receiver is node else node
                for frame in sender.frames(msg):
                    receiver.accept(frame)

        frames = [f for m in TRANSACTION for f in (sup if m.TYPE < 8 else node).frames(m)]
        us = _median_us(authenticated, loops, repeats)
        rows.append(
            {
                "layout": layout.value,
                "us_per_frame": us,
                "vs_plain": us / baseline,
                "frames_per_tx": len(frames),
                "bytes_per_tx": sum(len(f.data) for f in frames),
            }
        )
    return {"transaction": [type(m).__name__ for m in TRANSACTION], "rows": rows}
