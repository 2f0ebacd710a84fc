"""Core throughput: complete transactions per second, supervisor and clients in memory (no bus)."""

from __future__ import annotations

import random
import time
from collections import deque
from typing import Any

from canergy.ccore.supervisor import make_supervisor
from canergy.core import Acknowledged, Client, Phase, Send, Timing
from canergy.messages import Direction, ToClient, ToSupervisor

AMOUNT = 1_000


def transactions_per_second(
    nodes: int, loss: float, duration_s: float, seed: int = 0, core: str = "python"
) -> dict[str, Any]:
    """Grant 1 mJ to every node in turn, delivering each frame unless ``loss`` drops it; time
    advances 1 ms per frame so timeouts fire and re-sends recover lost frames (255 re-sends
    before a write-off: never reached). ``core``: the supervisor core, "python" or "c"."""
    rng = random.Random(seed)
    timing = Timing(response_timeout_us=10_000, retries=255, command_timeout_us=20_000)
    ids = list(range(1, nodes + 1))
    sup = make_supervisor(core, ids, 10**15, timing=timing)
    clients = {n: Client(n, timing=timing) for n in ids}
    now = 0
    done = 0
    frames = 0
    start = time.perf_counter()
    deadline = start + duration_s
    while time.perf_counter() < deadline:
        for n in ids:
            queue = deque(sup.begin(n, AMOUNT, now))
            while True:
                while queue:
                    action = queue.popleft()
                    if isinstance(action, Acknowledged):
                        queue.extend(sup.commit(action.node, now))
                    elif isinstance(action, Send):
                        frames += 1
                        now += 1_000
                        if loss and rng.random() < loss:
                            continue
                        msg = action.message
                        if msg.TYPE.direction is Direction.TO_CLIENT:
                            assert isinstance(msg, ToClient)
                            queue.extend(clients[msg.node].receive(msg, now))
                        else:
                            assert isinstance(msg, ToSupervisor)
                            queue.extend(sup.receive(msg, now))
                if sup.session(n).phase is Phase.IDLE and clients[n].get_timer() is None:
                    break
                now += 10_000  # nothing in flight: let the timers fire
                queue.extend(sup.handle_timer(now))
                queue.extend(clients[n].handle_timer(now))
            done += 1
    seconds = time.perf_counter() - start
    return {
        "nodes": nodes,
        "core": core,
        "loss": loss,
        "transactions": done,
        "seconds": seconds,
        "tx_per_s": done / seconds,
        "frames_per_tx": frames / done,
    }
