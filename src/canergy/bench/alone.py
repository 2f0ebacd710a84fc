"""The supervisor's own code per frame: no bus driver, no second thread.

The supervisor's loop (``BusRuntime`` with the service, codec included) and the emulator's nodes
take turns in one thread over an in-memory wire that hands frames over without copying them. Only
the supervisor's turns are timed (CPU time of the thread). What the live bench adds to this
figure is the bus driver's cost and that of sharing a process with the nodes' thread; this one is
what canergy's code costs, and what its optimisations move.

Taking turns, each side reads every frame the other sent in its turn: long loop passes, the code
hot in the caches, the best case. With ``pace_s`` each pass reads one frame and the thread
sleeps between turns, as a supervisor does on a bus that is not saturated (a frame, then a wait
for the next): the same code then runs colder and pays a whole loop pass per frame.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Any

import can

from canergy.bench.live import TIMING, Emulator, NoAnswer
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, build_supervisor
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Direction


class _Wire(can.BusABC):
    """One end of an in-memory wire: what it sends, its peer receives (same object, no copy)."""

    def __init__(self) -> None:
        super().__init__(channel="wire")
        self.inbox: deque[can.Message] = deque()
        self.peer = self

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.peer.inbox.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.popleft() if self.inbox else None), False


def supervisor_alone(
    emulator: Emulator,
    nodes: int,
    duration_s: float,
    nv_dir: Path,
    *,
    state_file: bool = False,
    pace_s: float | None = None,
    core: str = "python",
) -> dict[str, Any]:
    """One grant of 1 mJ kept in flight to each of ``nodes`` for ``duration_s`` after every node
    completed one; the supervisor's CPU per frame it sent or received. ``pace_s``: one frame per
    loop pass on both sides (from the start: each loop is built so), and a sleep of that long
    between turns once measuring. ``core``: "python" or "c"."""
    ids = list(range(1, nodes + 1))
    batch = 512 if pace_s is None else 1
    sup_end, node_end = _Wire(), _Wire()
    sup_end.peer, node_end.peer = node_end, sup_end
    books = nv_dir / "supervisor.json" if state_file else None
    config = SupervisorConfig(
        core=CoreConfig(tuple(ids), 10**15, timing=TIMING, kind=core),
        service=ServiceConfig(status_period_us=10**12, fsync=False, state_path=books),
        max_batch=batch,
    )
    built = build_supervisor(config, [sup_end])
    service, supervisor = built.service, built.loop
    host = emulator.node_host(ids, nv_dir, TIMING, monotonic_us())
    node_loop = BusRuntime(
        node_end, host, codec=Codec(), receives=Direction.TO_CLIENT, max_batch=batch
    )
    committed: set[int] = set()

    def ask(node: int) -> None:
        def reply(result: dict[str, Any]) -> None:
            if result.get("outcome") == "COMMITTED":
                committed.add(node)
            ask(node)

        service.request_grant(node, 1_000, reply)

    for n in ids:
        ask(n)
    try:
        warm_up_end = time.monotonic() + 10.0
        while len(committed) < nodes and time.monotonic() < warm_up_end:
            supervisor.poll(0)
            node_loop.poll(0)
        if len(committed) < nodes:
            raise NoAnswer(f"{nodes - len(committed)} of {nodes} node(s) never committed")
        counters = supervisor.counters
        frames0 = counters.frames_sent + counters.frames_received
        received0 = counters.frames_received
        spent = 0.0
        passes = 0
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            start = time.thread_time()
            supervisor.poll(0)
            spent += time.thread_time() - start
            passes += 1
            node_loop.poll(0)
            if pace_s is not None:
                time.sleep(pace_s)
        frames = counters.frames_sent + counters.frames_received - frames0
        received = counters.frames_received - received0
    finally:
        sup_end.shutdown()
        node_end.shutdown()
    return {
        "nodes": nodes,
        "core": core,
        "state_file": state_file,
        "pace_s": pace_s,
        "frames": frames,
        "frames_received_per_pass": received / passes if passes else None,
        "supervisor_cpu_us_per_frame": 1e6 * spent / frames if frames else None,
    }
