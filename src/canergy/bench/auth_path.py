"""The C core's own code per frame with ``--auth`` (FD layout) against without a key, in one run.

A service on the compiled core behind its bus loop (``BusRuntime`` with the core's frame path,
as the builder hands it over) keeps a 1 mJ grant in flight to each node over an in-memory wire;
scripted nodes answer each INTENTION with ACK and each COMMIT with COMMITTED (signed in the FD
layout under their keys when there is one). Only the supervisor's turns are timed (CPU time of
the thread), per frame it sent or received: ACK and COMMITTED verified, ruled and answered in
one C call, the INTENTION begun and protected in C.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from canergy.auth.frames import MAC_TYPE, FrameAuth, Layout
from canergy.bench.live import TIMING
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor.build import (
    AuthConfig,
    CoreConfig,
    SupervisorConfig,
    build_supervisor,
)
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import (
    Ack,
    Commit,
    Committed,
    Direction,
    Intention,
    Message,
    MsgType,
    Telemetry,
)
from canergy.seqnum import unwrap


class _Wire(can.BusABC):
    """One end of an in-memory wire: what it sends, its peer's inbox gets (no copy)."""

    def __init__(self) -> None:
        super().__init__(channel="wire")
        self.inbox: deque[can.Message] = deque()
        self.peer = self

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.peer.inbox.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.popleft() if self.inbox else None), False


def _nodes_answer(
    wire: _Wire,
    key_for: Callable[[int], bytes] | None,
    tx: dict[int, int],
    layout: Layout = Layout.FD,
) -> None:
    """Each INTENTION answered with ACK, each COMMIT with COMMITTED (not timed)."""
    codec = Codec()
    signer = (
        None
        if key_for is None
        else FrameAuth(codec, layout, key_for, Direction.TO_CLIENT, lambda m: tx[m.node])
    )
    while wire.inbox:
        frame = wire.inbox.popleft()
        kind = frame.arbitration_id >> 8 & 0xF
        data = bytes(frame.data)
        if kind == MAC_TYPE[Direction.TO_CLIENT]:
            continue  # classic: a MAC frame, not checked here
        if signer is not None:
            data = data[: codec.data_length(MsgType(kind))]
        msg = codec.decode(frame.arbitration_id, data, direction=Direction.TO_CLIENT)
        answer: Message
        if isinstance(msg, Intention):
            answer = Ack(msg.node, msg.tx)
        elif isinstance(msg, Commit):
            answer = Committed(msg.node, msg.tx)
        else:
            continue
        tx[msg.node] = unwrap(msg.tx, tx.get(msg.node, 0), 16) & 0xFFFF_FFFF
        if signer is not None:
            for signed in signer.frames(answer):
                wire.send(signed)
        else:
            arbitration_id, body = codec.encode(answer)
            wire.send(can.Message(arbitration_id=arbitration_id, data=body))


def supervisor_cpu(
    nodes: int, seconds: float, *, auth: bool, layout: Layout = Layout.FD
) -> dict[str, Any]:
    """The supervisor's CPU per frame on the C core's frame path, with or without a key (in
    ``layout``)."""
    from canergy.auth.keys import frame_auth_keys, new_master

    ids = list(range(1, nodes + 1))
    sup_end, node_end = _Wire(), _Wire()
    sup_end.peer, node_end.peer = node_end, sup_end
    master = new_master(1)
    config = SupervisorConfig(
        core=CoreConfig(tuple(ids), 10**15, timing=TIMING, kind="c"),
        service=ServiceConfig(status_period_us=10**12, fsync=False),
        auth=AuthConfig(master, fd=layout is Layout.FD) if auth else None,
    )
    built = build_supervisor(config, [sup_end])
    service, loop = built.service, built.loop
    assert isinstance(loop, BusRuntime)
    key_for = frame_auth_keys(master) if auth else None

    def ask(node: int) -> None:
        service.request_grant(node, 1_000, lambda result: ask(node))

    tx: dict[int, int] = {}
    for n in ids:
        service.on_message(Telemetry(n, 0), loop.clock())  # heard: grants may begin
        ask(n)
    for _ in range(20):  # warm up: every node through a transaction or two
        loop.poll(0)
        _nodes_answer(node_end, key_for, tx, layout)
    counters = loop.counters
    frames0 = counters.frames_sent + counters.frames_received
    spent = 0.0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        start = time.thread_time()
        loop.poll(0)
        spent += time.thread_time() - start
        _nodes_answer(node_end, key_for, tx, layout)
    frames = counters.frames_sent + counters.frames_received - frames0
    status = service.status()
    built.close()
    sup_end.shutdown()
    node_end.shutdown()
    return {
        "nodes": nodes,
        "auth": layout.value if auth else None,
        "frame_path": status["frame_path"],
        "frames_in_c": service.frames_in_c,
        "refused": sum(counters.auth_failures.values()),
        "frames": frames,
        "supervisor_cpu_us_per_frame": 1e6 * spent / frames if frames else None,
    }


def compare(seconds: float, nodes: tuple[int, ...] = (16, 127)) -> dict[str, Any] | None:
    """Plain against ``--auth`` FD, by node count, in this run (None: no compiled core)."""
    from canergy.ccore.supervisor import missing

    if missing() is not None:
        return None
    rows = []
    for n in nodes:
        plain = supervisor_cpu(n, seconds, auth=False)
        fd = supervisor_cpu(n, seconds, auth=True)
        a, b = plain["supervisor_cpu_us_per_frame"], fd["supervisor_cpu_us_per_frame"]
        rows.append({"nodes": n, "plain": plain, "fd": fd, "ratio": b / a if a and b else None})
    return {"rows": rows, "target_ratio": 2.0}
