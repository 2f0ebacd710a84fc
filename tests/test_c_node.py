"""The C node layer (firmware/include/canergy/node.h) against firmware_model's FirmwareNode.

Both run the same life in virtual time, in lockstep: a node drawing a constant power every
tick, reporting telemetry (periodic, low water, after a commit or an admission), giving back what
exceeds its return level, a Python supervisor granting when the node reports a low level, a
lossy channel, corrupted frames, frames sent in the node's name (its own direction with its id,
a RETURN_ACK ahead of its return number, an ADMIT not for its JOIN: the TELEMETRY's witness) and
reboots. The C side
is driven the way a port drives it (its own actuator tick calls ``canergy_node_draw``, its
deadline calls ``canergy_node_poll``); the Python side gets each frame as the bus loop hands it
to a ``NodeHost``. Every frame either node sends must be the same, and so must the energy
counters, the halted flag, the decode-error count and the record each NV image holds. (The
images themselves differ in their counters: firmware_model writes once per Persist, the C node
once per call.)
"""

from __future__ import annotations

import random

import can
import pytest
from support.c_binding import (
    NEVER,
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
from support.mem_nv import MemNv, write_slot

from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.core import Acknowledged, Send, Supervisor, Timing
from canergy.core.state import Phase
from canergy.live.supervisor.witness import WITNESS_GAP_US
from canergy.messages import (
    Aborted,
    Ack,
    Admit,
    Committed,
    Direction,
    Join,
    Message,
    Return,
    ReturnAck,
    Telemetry,
)
from firmware_model import node as firmware_node
from firmware_model.actuator import Actuator, PowerProfile
from firmware_model.node import FirmwareNode, NodeHost
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
        buf = cbuf(bytes(raw), max(len(raw), 1))
        self.lib.canergy_node_start(
            ref(self.n),
            ref(self.cfg),
            buf,
            len(raw),
            nonce,
            now,
            ref(self.out),
        )
        self.actuator = Actuator(cfg.power, now, now)
        self.next_tick = now + cfg.tick_us
        self.pending = self._done()  # the JOIN of a node without books

    def _done(self) -> list[tuple[int, bytes]]:
        if self.out.persist:
            write_slot(self.raw, self.out.nv_slot, bytes(self.out.nv_image))
        return out_frames(self.out)

    def frame(self, arbitration_id: int, data: bytes, now: int) -> list[tuple[int, bytes]]:
        frame, buf = rx(arbitration_id, data)
        self.lib.canergy_node_on_frame(ref(self.n), ref(frame), now, ref(self.out))
        del buf
        return self._done()

    def next_wakeup(self) -> int:
        if self.pending:
            return 0
        return min(self.next_tick, self.lib.canergy_node_deadline(ref(self.n)))

    def wakeup(self, now: int) -> list[tuple[int, bytes]]:
        sent, self.pending = self.pending, []
        if now >= self.next_tick:  # the port's actuator period
            self.next_tick = now + self.tick_us
            wanted = self.actuator.need(now)
            granted = self.lib.canergy_node_draw(ref(self.n), wanted, now, ref(self.out))
            sent += self._done()  # persisted before the actuator runs on it
            self.actuator.run(granted, wanted)
        else:
            self.lib.canergy_node_poll(ref(self.n), now, ref(self.out))
            sent += self._done()
        return sent


def encoded(messages: list) -> list[tuple[int, bytes]]:
    return [CODEC.encode(m) for m in messages]


def py_receive(host: NodeHost, arbitration_id: int, data: bytes, now: int) -> list[Message]:
    """A frame as the bus loop (canergy.live.runtime) hands it to firmware_model's host: a frame
    in the node's own direction to ``on_foreign_direction``, a refused one to
    ``on_decode_error``, a message to ``on_message``."""
    frame = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True)
    try:
        msg = CODEC.decode(arbitration_id, data, direction=Direction.TO_CLIENT)
    except DecodeError as err:
        if err.reason is DecodeErrorReason.WRONG_DIRECTION:
            return list(host.on_foreign_direction(frame, now))
        if err.reason is not DecodeErrorReason.FOREIGN:
            host.on_decode_error(err, frame)
        return []
    return list(host.on_message(msg, now))


def in_its_name(rng: random.Random, c: CNode) -> tuple[tuple[int, bytes], int]:
    """A frame someone else sends in node NODE's name, and by how much the witness must grow:
    its own direction (a valid message or any length), a RETURN_ACK ahead of its return number,
    an ADMIT not for this start's JOIN (1); or one that looks like a late duplicate (a
    RETURN_ACK behind its number, its own JOIN's ADMIT) or another node's ACK (0)."""
    u16 = rng.randrange(0x10000)
    return_seq = c.n.client.rec.return_seq
    kind = rng.randrange(6)
    if kind == 0:
        msg = rng.choice(
            [
                Ack(NODE, u16),
                Committed(NODE, u16),
                Aborted(NODE, u16),
                Return(NODE, u16, rng.randrange(1, 0x10000)),
                Join(NODE, u16),
                Telemetry(NODE, rng.randrange(1 << 24), 0, u16, rng.randrange(256)),
            ]
        )
        return CODEC.encode(msg), 1
    if kind == 1:
        code = rng.randrange(0x9, 0xF)
        arbitration_id = CODEC.id_base | code << 8 | NODE
        return (arbitration_id, rng.randbytes(rng.randrange(9))), 1
    if kind == 2:
        ahead = rng.randrange(1, 0x8000)
        return CODEC.encode(ReturnAck(NODE, (return_seq + ahead) & 0xFFFF)), 1
    if kind == 3:
        behind = rng.randrange(1, 0x8001)  # 0x8000: half the wire away counts as behind
        return CODEC.encode(ReturnAck(NODE, (return_seq - behind) & 0xFFFF)), 0
    if kind == 4:
        ours = c.n.joined and rng.random() < 0.5
        nonce = c.n.join_nonce if ours else (c.n.join_nonce + rng.randrange(1, 0x10000)) & 0xFFFF
        admit = Admit(NODE, nonce, u16, rng.randrange(0x10000))
        if ours and c.n.client.phase == 2:  # it would be admitted: not a spoof then
            return CODEC.encode(Ack(NODE + 1, u16)), 0
        return CODEC.encode(admit), 0 if ours else 1
    return CODEC.encode(Ack(NODE + 1, u16)), 0


def check_telemetry(c: CNode, frames: list[tuple[int, bytes]]) -> None:
    """Every TELEMETRY the C node sends carries its return number (16 bits) and its witness."""
    for arbitration_id, data in frames:
        msg = CODEC.decode(arbitration_id, data, direction=Direction.TO_SUPERVISOR)
        if isinstance(msg, Telemetry):
            assert msg.return_seq == c.n.client.rec.return_seq & 0xFFFF
            assert msg.witness == c.n.witness


def live(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = random.Random(seed)
    nonces = iter(range(0x4000 + seed, 0x5000))
    nonce = next(nonces)
    monkeypatch.setattr(firmware_node.secrets, "randbits", lambda bits: nonce)
    config = PyNodeConfig(
        power=PowerProfile.constant(rng.choice([0.05, 0.2, 1.5, 0.0337])),  # 3.37 mJ a tick
        tick_us=100_000,
        telemetry_period_us=rng.choice([300_000, 1_000_000]),
        low_water=rng.choice([0, 50_000, 400_000]),
        return_above=rng.choice([None, 300_000, 700_000]),
        timing=TIMING,
    )
    py_raw, c_raw = bytearray(), bytearray()
    now = 0
    py = FirmwareNode(NODE, MemNv(py_raw, NODE), config, now)
    host = NodeHost([py])
    c = CNode(config, c_raw, nonce, now)
    sup = Supervisor([NODE], 20_000_000, timing=TIMING)
    to_node: list[tuple[int, bytes]] = []
    loss = rng.choice([0.0, 0.1, 0.25])
    spoofing = (0.0, 0.01, 0.05)[seed % 3]

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
            py_out = encoded(py_receive(host, arbitration_id, data, now))
            assert c_out == py_out
            check_telemetry(c, c_out)
            from_node(c_out)
        if rng.random() < spoofing:  # someone speaks in the node's name: counted, no answer
            (arbitration_id, data), grows = in_its_name(rng, c)
            witness = (c.n.witness + grows) & 0xFF
            c_out = c.frame(arbitration_id, data, now)
            assert c_out == encoded(py_receive(host, arbitration_id, data, now)) == []
            assert c.n.witness == witness
        assert c.next_wakeup() == py.next_wakeup()
        if py.next_wakeup() <= now:
            py_out = encoded(py.on_wakeup(now))
            c_out = c.wakeup(now)
            assert c_out == py_out
            check_telemetry(c, c_out)
            from_node(c_out)
        if sup.get_timer() is not None and sup.get_timer() <= now:
            to_sup(sup.handle_timer(now))
        compare()
        if rng.random() < 0.004:  # a reboot of the node, from its NV
            nonce = next(nonces)
            py = FirmwareNode(NODE, MemNv(py_raw, NODE), config, now)
            host = NodeHost([py])
            c = CNode(config, c_raw, nonce, now)
            assert c.n.witness == 0  # kept in RAM only: the NV layout is unchanged
            compare()
    assert sup.state.sessions[0].delivered > 0, "the scenario never granted anything"
    assert NEVER > 0


@pytest.mark.parametrize("seed", range(8))
def test_c_node_lives_like_firmware_model(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    live(seed, monkeypatch)


def test_frames_in_its_name_are_witnessed_and_reported_at_the_next_poll() -> None:
    """Each rule of the witness once, on the C node alone; its TELEMETRY read by canergy.codec."""
    config = PyNodeConfig(telemetry_period_us=1_000_000, timing=TIMING)
    c = CNode(config, bytearray(), 0x1234, 0)
    c.wakeup(0)
    t = WITNESS_GAP_US  # its boot report at 0: the next one a gap later at the soonest

    def telemetry(now: int) -> Telemetry:
        (frame,) = [f for f in c.wakeup(now) if f[0] >> 8 & 0xF == 0xD]
        msg = CODEC.decode(*frame, direction=Direction.TO_SUPERVISOR)
        assert isinstance(msg, Telemetry)
        return msg

    def witnessed(msg: Message, now: int) -> int:
        before = c.n.witness
        assert c.frame(*CODEC.encode(msg), now) == []
        return (c.n.witness - before) & 0xFF

    assert witnessed(Admit(NODE, 0x4321, 40, 7), t + 10) == 1  # joining: not its nonce
    assert witnessed(ReturnAck(NODE, 1), t + 11) == 1  # a return it never made
    assert witnessed(ReturnAck(NODE, 0), t + 12) == 0  # its own number: no answer to nothing
    assert telemetry(t + 12) == Telemetry(NODE, 0, Telemetry.JOINING, 0, 2)
    assert witnessed(Admit(NODE, 0x1234, 40, 7), t + 20) == 0 and c.n.client.phase == 0
    assert witnessed(Admit(NODE, 0x1234, 40, 7), t + 21) == 0  # a duplicate of its answer
    assert witnessed(Admit(NODE, 0x1235, 40, 7), t + 22) == 1
    assert witnessed(ReturnAck(NODE, 8), t + 23) == 1 and witnessed(ReturnAck(NODE, 7), t + 23) == 0
    assert witnessed(Ack(NODE, 41), t + 24) == 1  # its own direction, its id
    assert witnessed(Ack(NODE + 1, 41), t + 25) == 0  # another node's
    usable = c.n.client.rec.usable_uj
    assert witnessed(Return(NODE, 8, 65535), t + 26) == 1 and c.n.client.rec.usable_uj == usable
    assert telemetry(t + 26) == Telemetry(NODE, 0, 0, 7, 6)


@pytest.mark.parametrize("return_seq", [0xFFFF, 0x1_0000, 0x1_2345, 0xFFFF_FFFF])
def test_telemetry_carries_the_return_number_as_the_wire_does(return_seq: int) -> None:
    config = PyNodeConfig(telemetry_period_us=1_000_000, timing=TIMING)
    c = CNode(config, bytearray(), 0x1234, 0)
    c.frame(*CODEC.encode(Admit(NODE, 0x1234, 0, return_seq & 0xFFFF)), 0)
    c.n.client.rec.return_seq = return_seq  # the record keeps 32 bits; the wire 16
    (frame,) = [f for f in c.wakeup(1) if f[0] >> 8 & 0xF == 0xD]
    msg = CODEC.decode(*frame, direction=Direction.TO_SUPERVISOR)
    assert isinstance(msg, Telemetry) and msg.return_seq == return_seq & 0xFFFF
