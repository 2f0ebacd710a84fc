"""The hardened C node put back to an older copy of its NV file, against ``canergy supervisor
--variant hardened --core c --lost-after 10`` as the CLI builds it (its bus loop, the compiled
core's frame path), in virtual time: tests/test_vcan_c_witnessed.py's hardened case without
SocketCAN, the node's library driven as ``canergy-node`` drives it.

Whenever the copy is taken and the node stopped relative to the transaction in flight, and with
both processes held off now and then, the pair is never stuck: the first intention after the
restore pays the older record back what was granted after the copy, and two more grants follow
once the node has used what it then holds above the target. That time is as long as the first
life ran past the copy (the vcan test times its wait from it)."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import can
import pytest
from support.c_binding import (
    ClientConfig,
    CNodeState,
    NodeConfig,
    Out,
    cbuf,
    library,
    out_frames,
    ref,
    rx,
)
from support.mem_nv import write_slot

from canergy.cli import build_parser
from canergy.cli.supervisor import supervisor_config
from canergy.codec import DEFAULT_ID_BASE
from canergy.live.supervisor.build import build_supervisor, open_core

NODE = 6
POWER_UW = 200_000  # the vcan suite's --power 0.2W
TARGET_UJ = 1_000_000  # and --target 1J
TIMEOUT_US = 300_000  # its --response-timeout 0.3
STEP_US = 1_000
SLACK_S = 10
"""Two grants after the node is below its target again, at most (virtual time)."""


class _End(can.BusABC):
    """The supervisor's end of the wire: frames to it wait in ``inbox`` until delivered."""

    def __init__(self, wire: _Wire) -> None:
        super().__init__(channel="wire")
        self.wire = wire

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.wire.send("node", msg.arbitration_id, bytes(msg.data))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        got = self.wire.take("sup", 1)
        if not got:
            return None, False
        ident, data = got[0]
        return can.Message(arbitration_id=ident, data=data, is_extended_id=True), False


class _Wire:
    """Frames in flight to each side, delivered in order after a random latency."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.now = 10_000_000
        self.queues: dict[str, list[tuple[int, int, bytes]]] = {"sup": [], "node": []}

    def send(self, to: str, ident: int, data: bytes) -> None:
        queue = self.queues[to]
        at = max(self.now + self.rng.randint(100, 3_000), queue[-1][0] if queue else 0)
        queue.append((at, ident, data))

    def take(self, to: str, most: int | None = None) -> list[tuple[int, bytes]]:
        queue = self.queues[to]
        n = 0
        while n < len(queue) and queue[n][0] <= self.now and (most is None or n < most):
            n += 1
        taken, queue[:n] = queue[:n], []
        return [(ident, data) for _, ident, data in taken]


class _Node:
    """One life of the C node, as the Linux port drives its library: an actuator at 0.2 W every
    100 ms, the library's deadline, each NV image written before the frames of its step."""

    def __init__(self, raw: bytearray, nonce: int, now: int) -> None:
        self.lib = library()
        client = ClientConfig(DEFAULT_ID_BASE, 2 * TIMEOUT_US, 2 * TIMEOUT_US, NODE)
        self.cfg = NodeConfig(client, 500_000, 0, 0xFFFF_FFFF)  # --keep-all: no returns
        self.raw, self.n, self.out = raw, CNodeState(), Out()
        buf = cbuf(bytes(raw), max(len(raw), 1))
        self.lib.canergy_node_start(
            ref(self.n), ref(self.cfg), buf, len(raw), nonce, now, ref(self.out)
        )
        self.sent = self._done()
        self.last_draw = self.next_tick = now
        self.remainder_pj = self.drawn = 0

    def _done(self) -> list[tuple[int, bytes]]:
        if self.out.persist:
            write_slot(self.raw, self.out.nv_slot, bytes(self.out.nv_image))
        return out_frames(self.out)

    def run(self, frames: list[tuple[int, bytes]], now: int) -> list[tuple[int, bytes]]:
        sent, self.sent = self.sent, []
        for ident, data in frames:
            frame, buf = rx(ident, data)
            self.lib.canergy_node_on_frame(ref(self.n), ref(frame), now, ref(self.out))
            del buf
            sent += self._done()
        if now >= self.lib.canergy_node_deadline(ref(self.n)):
            self.lib.canergy_node_poll(ref(self.n), now, ref(self.out))
            sent += self._done()
        if now >= self.next_tick:
            self.next_tick = now + 100_000
            pj = POWER_UW * (now - self.last_draw) + self.remainder_pj
            self.last_draw, self.remainder_pj = now, pj % 1_000_000
            wanted = pj // 1_000_000
            granted = self.lib.canergy_node_draw(ref(self.n), wanted, now, ref(self.out))
            sent += self._done()
            self.drawn += granted
            if granted < wanted:
                self.remainder_pj = 0
        return sent

    @property
    def usable(self) -> int:
        return int(self.n.client.rec.usable_uj)

    @property
    def credited(self) -> int:
        return int(self.n.client.rec.credited_mj) * 1000


class _Bench:
    """The supervisor and one node life on the wire, stepped 1 ms at a time; ``held_off``: the
    chance per step that a process is not scheduled (up to 0.5 s)."""

    def __init__(self, tmp: Path, seed: int, held_off: float) -> None:
        self.rng = random.Random(seed)
        self.wire = _Wire(self.rng)
        argv = [
            *("supervisor", "-i", "virtual", "-c", "unused", "--nodes", str(NODE)),
            *("--initial", "100J", "--target", "1J", "--max-grant", "0.5J"),
            *("--state", str(tmp / "state.json"), "--no-fsync", "--response-timeout", "0.3"),
            *("--variant", "hardened", "--core", "c", "--lost-after", "10"),
        ]
        config = supervisor_config(build_parser(["supervisor"]).parse_args(argv), (), None)
        self.end = _End(self.wire)
        core = open_core(config, self.clock())
        built = build_supervisor(config, [self.end], core=core, clock=self.clock)
        self.service, self.loop = built.service, built.loop
        self.raw = bytearray()
        self.node: _Node | None = None
        self.held_off = held_off
        self.off_until = {"sup": 0, "node": 0}

    def clock(self) -> int:
        return self.wire.now

    def start_node(self) -> _Node:
        self.node = _Node(self.raw, self.rng.randrange(1, 1 << 16), self.wire.now)
        return self.node

    def _runs(self, who: str) -> bool:
        now = self.wire.now
        if now < self.off_until[who]:
            return False
        if self.held_off and self.rng.random() < self.held_off:
            self.off_until[who] = now + self.rng.randint(1, 500_000)
            return False
        return True

    def run(self, condition: Any, within_s: float) -> bool:
        """Step until ``condition()`` (True) or ``within_s`` virtual seconds (False)."""
        end = self.wire.now + int(within_s * 1e6)
        while not condition():
            if self.wire.now >= end:
                return False
            self.wire.now += STEP_US
            if self._runs("sup"):
                self.loop.poll(0)
            if self.node is not None and self._runs("node"):
                for ident, data in self.node.run(self.wire.take("node"), self.wire.now):
                    self.wire.send("sup", ident, data)
        return True

    def books(self) -> Any:
        return self.service.nodes[NODE]

    def where(self) -> dict[str, Any]:
        status = self.service.status()["nodes"][str(NODE)]
        node = self.node
        mine = None if node is None else {"usable": node.usable, "credited": node.credited}
        return {"books": status, "node": mine}


def _restore(tmp: Path, offset: int, ran_past_copy_s: float, held_off: float) -> None:
    """Life 1 runs, its NV file is copied, it runs ``ran_past_copy_s`` more (stopped
    ``offset`` steps of ~83 ms into the transaction cycle), the copy is put back and life 2
    starts from it a second later: paid back, then two grants once it is below its target."""
    bench = _Bench(tmp, offset, held_off)
    first = bench.start_node()
    assert bench.run(lambda: bench.books().committed >= 2 and first.drawn > 0, 60)
    copy, at_copy = bytes(bench.raw), first.drawn
    assert bench.run(lambda: first.drawn >= at_copy + 400_000, 60)
    bench.run(lambda: False, ran_past_copy_s - 2 + offset * 0.083)
    bench.node = None  # stopped: only its NV file stays
    done, granted = bench.books().committed, bench.service.core.session(NODE).delivered
    bench.run(lambda: False, 1.0)
    bench.raw[:] = copy
    second = bench.start_node()
    paid = bench.run(lambda: second.credited >= granted, 10)
    assert paid, ("never paid back", offset, bench.where())
    above_s = max(0, second.usable - TARGET_UJ) / POWER_UW
    assert above_s >= ran_past_copy_s / 2, (above_s, offset)  # what it used past the copy
    again = bench.run(lambda: bench.books().committed >= done + 2, above_s + SLACK_S)
    assert again, ("no two grants", offset, above_s, bench.where())
    bench.end.shutdown()


@pytest.mark.parametrize("held_off", [0.0, 0.002], ids=["on time", "held off"])
@pytest.mark.parametrize("ran_past_copy_s", [2, 30])
def test_a_restored_hardened_c_node_is_granted_again_once_it_used_its_payback(
    tmp_path: Path, ran_past_copy_s: int, held_off: float
) -> None:
    for offset in range(6):
        (tmp_path / str(offset)).mkdir()
        _restore(tmp_path / str(offset), offset, ran_past_copy_s, held_off)
