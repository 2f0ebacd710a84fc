"""Codec speed against cantools on the same frames: encode + decode, every message type.

cantools gets the DBC that ``canergy dbc`` writes (``dbc/canergy.dbc``, which a test keeps equal),
generated here so that an installed canergy needs no source tree."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import cantools

from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.dbc import dbc_text
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Commit,
    Committed,
    FinalAck,
    Intention,
    Message,
    Return,
    ReturnAck,
    StatusRequest,
    Telemetry,
)

SAMPLES: list[Message] = [
    Intention(5, 1234, 2500, 777_000),
    Commit(5, 1234, 2500),
    Abort(5, 1234, 2500),
    ReturnAck(5, 9),
    StatusRequest(5, 1234),
    FinalAck(5, 1234),
    Ack(5, 1234),
    Committed(5, 1234),
    Aborted(5, 1234),
    Return(5, 9, 120),
    Telemetry(5, 1500, 1),
]


def _best_of(fn: Callable[[], None], repeats: int) -> float:
    """Median of ``repeats`` timings of ``fn`` (seconds)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def compare(loops: int = 2000, repeats: int = 7) -> dict[str, Any]:
    """Per frame encode+decode time of canergy's codec and of cantools with the DBC, paired
    in the same process on the same frames; the ratio of medians per message type."""
    codec = Codec()
    db = cantools.database.load_string(dbc_text(DEFAULT_ID_BASE), database_format="dbc")
    assert isinstance(db, cantools.database.can.Database)
    rows: list[dict[str, Any]] = []
    for msg in SAMPLES:
        arbitration_id, data = codec.encode(msg)
        frame = db.get_message_by_frame_id(arbitration_id)
        signals = frame.decode(data, scaling=False)

        def ours(msg: Message = msg, arbitration_id: int = arbitration_id) -> None:
            for _ in range(loops):
                _, payload = codec.encode(msg)
                codec.decode(arbitration_id, payload)

        def theirs(arbitration_id: int = arbitration_id, signals: Any = signals) -> None:
            for _ in range(loops):
                payload = db.encode_message(arbitration_id, signals, scaling=False)
                db.decode_message(arbitration_id, payload, scaling=False)

        a, b = _best_of(ours, repeats), _best_of(theirs, repeats)
        rows.append(
            {
                "type": msg.TYPE.name,
                "canergy_us": a / loops * 1e6,
                "cantools_us": b / loops * 1e6,
                "speedup": b / a,
            }
        )
    return {
        "rows": rows,
        "median_speedup": statistics.median(r["speedup"] for r in rows),
        "min_speedup": min(r["speedup"] for r in rows),
        "canergy_us_per_frame": statistics.median(r["canergy_us"] for r in rows),
    }
