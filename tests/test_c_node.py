"""The C node layer (firmware/include/canergy/node.h) against firmware_model's FirmwareNode.

Both run the same life in virtual time, in lockstep: a node drawing a constant power every
tick, reporting telemetry (periodic, low water, after a commit or an admission), giving back what
exceeds its return level, a Python supervisor granting when the node reports a low level, a
lossy channel, corrupted frames and reboots. The C side is driven the way a port drives it (its
own actuator tick calls ``canergy_node_draw``, its deadline calls ``canergy_node_poll``). Every
frame either node sends must be the same, and so must the energy counters, the halted flag, the
decode-error count and the record each NV image holds. (The images themselves differ in their
counters: firmware_model writes once per Persist, the C node once per call.)
"""

from __future__ import annotations

import ctypes
import random

import pytest
from test_c_binding import (
    NEVER,
    ClientConfig,
    CNodeState,
    NodeConfig,
    Out,
    library,
    rx,
)
from test_c_sidebyside import MemNv, write_slot

from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.core import Acknowledged, Send, Supervisor, Timing
from canergy.core.state import Phase
from canergy.messages import Direction, Telemetry
from firmware_model import node as firmware_node
from firmware_model.actuator import Actuator, PowerProfile
from firmware_model.node import FirmwareNode
from firmware_model.node import NodeConfig as PyNodeConfig

NODE = 3
CODEC = Codec()
TIMING = Timing(
    response_timeout_us=20_000, retries=2, command_timeout_us=40_000, return_retry_us=40_000
)
STEP_US = 5_000


class CNode:
    """The C node and what its port keeps: the actuator tick, the NV image."""

    def __init__(self, cfg: PyNodeConfig, raw: bytearray, nonce: int, now: int) -> None:
        self.lib = library()
        self.cfg = NodeConfig(
            ClientConfig(
                CODEC.id_base, cfg.timing.command_timeout_us, cfg.timing.return_retry_us, NODE
            ),
            cfg.telemetry_period_us,
            cfg.low_water,
            0xFFFF_FFFF if cfg.return_above is None else cfg.return_above,
        )
        self.tick_us = cfg.tick_us
        self.raw = raw
        self.n = CNodeState()
        self.out = Out()
        buf = ctypes.create_string_buffer(bytes(raw), max(len(raw), 1))
        self.lib.canergy_node_start(
            ctypes.byref(self.n),
            ctypes.byref(self.cfg),
            buf,
            len(raw),
            nonce,
            now,
            ctypes.byref(self.out),
        )
        self.actuator = Actuator(cfg.power, now, now)
        self.next_tick = now + cfg.tick_us
        self.pending = self._done()  # the JOIN of a node without books

    def _done(self) -> list[tuple[int, bytes]]:
        if self.out.persist:
            write_slot(self.raw, self.out.nv_slot, bytes(self.out.nv_image))
        return self.out.sent()

    def frame(self, arbitration_id: int, data: bytes, now: int) -> list[tuple[int, bytes]]:
        frame, buf = rx(arbitration_id, data)
        self.lib.canergy_node_on_frame(
            ctypes.byref(self.n), ctypes.byref(frame), now, ctypes.byref(self.out)
        )
        del buf
        return self._done()

    def next_wakeup(self) -> int:
        if self.pending:
            return 0
        return min(self.next_tick, self.lib.canergy_node_deadline(ctypes.byref(self.n)))

    def wakeup(self, now: int) -> list[tuple[int, bytes]]:
        sent, self.pending = self.pending, []
        if now >= self.next_tick:  # the port's actuator period
            self.next_tick = now + self.tick_us
            wanted = self.actuator.need(now)
            granted = self.lib.canergy_node_draw(
                ctypes.byref(self.n), wanted, now, ctypes.byref(self.out)
            )
            sent += self._done()  # persisted before the actuator runs on it
            self.actuator.run(granted, wanted)
        else:
            self.lib.canergy_node_poll(ctypes.byref(self.n), now, ctypes.byref(self.out))
            sent += self._done()
        return sent


def encoded(messages: list) -> list[tuple[int, bytes]]:
    return [CODEC.encode(m) for m in messages]


def live(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = random.Random(seed)
    nonces = iter(range(0x4000 + seed, 0x5000))
    nonce = next(nonces)
    monkeypatch.setattr(firmware_node.secrets, "randbits", lambda bits: nonce)
    config = PyNodeConfig(
        power=PowerProfile.constant(rng.choice([0.05, 0.2, 1.5])),
        tick_us=100_000,
        telemetry_period_us=rng.choice([300_000, 1_000_000]),
        low_water=rng.choice([0, 50_000, 400_000]),
        return_above=rng.choice([None, 300_000, 700_000]),
        timing=TIMING,
    )
    py_raw, c_raw = bytearray(), bytearray()
    now = 0
    py = FirmwareNode(NODE, MemNv(py_raw, NODE), config, now)
    c = CNode(config, c_raw, nonce, now)
    sup = Supervisor([NODE], 20_000_000, timing=TIMING)
    to_node: list[tuple[int, bytes]] = []
    loss = rng.choice([0.0, 0.1, 0.25])

    def from_node(frames: list[tuple[int, bytes]]) -> None:
        for arbitration_id, data in frames:
            if rng.random() < loss:
                continue
            msg = CODEC.decode(arbitration_id, data, direction=Direction.TO_SUPERVISOR)
            if isinstance(msg, Telemetry):
                idle = sup.session(NODE).phase is Phase.IDLE
                if idle and not msg.flags & Telemetry.JOINING and msg.level_mj < 200:
                    to_sup(sup.begin(NODE, rng.choice([100, 500, 2000]) * 1000, now))
            else:
                to_sup(sup.receive(msg, now))

    def to_sup(actions: list) -> None:
        for a in actions:
            if isinstance(a, Acknowledged):
                to_sup((sup.commit if rng.random() < 0.8 else sup.abort)(NODE, now))
            elif isinstance(a, Send) and rng.random() >= loss:
                to_node.append(CODEC.encode(a.message))

    def compare() -> None:
        s = py.client.state
        cs = c.n.client.rec
        assert (cs.usable_uj, cs.spent_uj, cs.credited_mj) == (
            s.usable,
            s.spent,
            s.credited // 1000,
        )
        assert c.n.halted == py.actuator.halted
        assert c.n.decode_errors == py.decode_errors
        assert c.n.overflow_refused == py.overflow_refused
        py_loaded, c_loaded = MemNv(py_raw, NODE).load(), MemNv(c_raw, NODE).load()
        assert py_loaded == c_loaded

    for _ in range(800):  # 4 s of virtual time
        now += STEP_US
        while to_node:
            arbitration_id, data = to_node.pop(0)
            if rng.random() < 0.02:  # a damaged frame: both count it
                data = bytes([data[0] ^ 0x10, *data[1:]])
            c_out = c.frame(arbitration_id, data, now)
            try:
                msg = CODEC.decode(arbitration_id, data, direction=Direction.TO_CLIENT)
            except DecodeError as err:
                assert err.reason is DecodeErrorReason.BAD_CRC and c_out == []
                py.decode_errors += 1  # what NodeHost.on_decode_error does
                continue
            py_out = encoded(py.on_message(msg, now))  # type: ignore[arg-type]
            assert c_out == py_out
            from_node(c_out)
        assert c.next_wakeup() == py.next_wakeup()
        if py.next_wakeup() <= now:
            py_out = encoded(py.on_wakeup(now))
            c_out = c.wakeup(now)
            assert c_out == py_out
            from_node(c_out)
        if sup.get_timer() is not None and sup.get_timer() <= now:
            to_sup(sup.handle_timer(now))
        compare()
        if rng.random() < 0.004:  # a reboot of the node, from its NV
            nonce = next(nonces)
            py = FirmwareNode(NODE, MemNv(py_raw, NODE), config, now)
            c = CNode(config, c_raw, nonce, now)
            compare()
    assert sup.state.sessions[0].delivered > 0, "the scenario never granted anything"
    assert NEVER > 0


@pytest.mark.parametrize("seed", range(8))
def test_c_node_lives_like_firmware_model(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    live(seed, monkeypatch)
