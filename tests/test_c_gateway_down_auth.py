"""The C gateway's authenticated leg below (``canergy_auth_gateway_down_frame`` and
``canergy_auth_gateway_down_protect``, firmware/src/auth.c) side by side with the Python
gateway's (``canergy gateway --auth``: ``FrameAuth`` receiving ``TO_SUPERVISOR`` over the
supervisor's sessions, with the freshness ``SupervisorService.freshness`` gives).

Two Python emulated nodes (``canergy.core.Client`` behind their own ``FrameAuth`` with their node
keys, as ``python -m firmware_model --auth`` runs them) speak to both supervisors at once: every
frame a node sends reaches both as bytes, and both must come to the same verdict (taken, nothing,
or the same refusal), send back the same bytes (data and MAC frames, both layouts; an ADMIT binds
the 32-bit FV of the JOIN it answers) and keep the same books. Node 5's session starts above
2^16, so its counters wrap on the wire. Replayed, MAC-flipped and keyless frames below, and a
TELEMETRY from before the window, move nothing on either.
"""

from __future__ import annotations

from typing import Any

import can
import pytest
from support.c_binding import OK, CGateway, SupervisorConfig, cbuf, library, ref, rx
from support.c_session import fields_of, timing_of

from canergy.auth.frames import AuthFailure, FrameAuth, Layout, Verdict, expected_freshness
from canergy.auth.keys import derive_node_key
from canergy.codec import Codec
from canergy.core import Acknowledged, Client, Send, Supervisor, Timing
from canergy.core.state import Session, SupervisorState
from canergy.messages import QUANTUM_UJ, Direction, Message, MsgType, Telemetry

NODES = (3, 5)
MASTER, EPOCH = bytes(range(32, 48)), 7
T = Timing(response_timeout_us=1_000, retries=2, command_timeout_us=2_000, return_retry_us=2_000)
CODEC = Codec()
INITIAL = 10**9
HIGH_TX, HIGH_SEQ = 0x1_FFFE, 0x2_0001
"""Node 5's session counters at the start: above 2^16, and about to wrap on the wire."""
C_LAYOUTS = {Layout.FD: "CANERGY_AUTH_FD", Layout.CLASSIC: "CANERGY_AUTH_CLASSIC"}
REFUSALS = {
    AuthFailure.MAC_BAD: "CANERGY_AUTH_MAC_BAD",
    AuthFailure.STALE: "CANERGY_AUTH_STALE",
    AuthFailure.NO_DATA: "CANERGY_AUTH_NO_DATA",
    AuthFailure.MALFORMED: "CANERGY_AUTH_MALFORMED",
    AuthFailure.UNAUTHENTICATED: "CANERGY_AUTH_UNAUTHENTICATED",
}


def key_for(node: int) -> bytes:
    return derive_node_key(MASTER, node, EPOCH)


class Node:
    """A Python emulated node with its own key."""

    def __init__(self, node: int, layout: Layout, rules: str = "hardened") -> None:
        self.client = Client(node, timing=T, variant=rules)
        self.auth = FrameAuth(CODEC, layout, key_for, Direction.TO_CLIENT, self._fv)
        self.sent: list[can.Message] = []

    def _fv(self, msg: Message) -> Any:
        c = self.client.state
        return expected_freshness(msg, c.last_tx, c.return_seq)

    def send(self, actions: list[Any]) -> list[can.Message]:
        frames = [f for a in actions if isinstance(a, Send) for f in self.auth.frames(a.message)]
        self.sent += frames
        return frames

    def telemetry(self) -> list[can.Message]:
        c = self.client.state
        joining = Telemetry.JOINING if self.client.state.phase.name == "JOINING" else 0
        msg = Telemetry(self.client.node, c.usable // QUANTUM_UJ, joining, c.return_seq & 0xFFFF)
        frames = self.auth.frames(msg)
        self.sent += frames
        return frames


class Below:
    """The two supervisors below, the C gateway's and the Python gateway's, and their nodes."""

    def __init__(self, layout: Layout, rules: str = "hardened") -> None:
        self.lib = lib = library()
        self.now = 0
        sessions = (Session(3), Session(5, tx=HIGH_TX, returns_credited=HIGH_SEQ))
        books = SupervisorState(INITIAL, INITIAL, 0, sessions)
        self.py = Supervisor(NODES, INITIAL, timing=T, state=books, variant=rules)
        self.py_auth = FrameAuth(CODEC, layout, key_for, Direction.TO_SUPERVISOR, self._py_fv)
        self.gw = CGateway(lib=lib)
        cfg = SupervisorConfig(CODEC.id_base, timing_of(T, rules, lib=lib), lib=lib)
        assert (
            lib.canergy_supervisor_init(
                ref(self.gw.down), ref(cfg), cbuf(bytes(NODES), lib=lib), 2, INITIAL
            )
            == OK
        )
        self.gw.down.sessions[1].tx, self.gw.down.sessions[1].returns_credited = HIGH_TX, HIGH_SEQ
        self.keys = lib.new("struct canergy_auth[2]")
        for i, node in enumerate(NODES):
            key = lib.new("uint8_t[16]")
            lib.canergy_auth_node_key(MASTER, node, EPOCH, key)
            assert bytes(key) == key_for(node)  # the C KDF gives the Python key
            layout_c = getattr(lib, C_LAYOUTS[layout])
            to_sup = lib.CANERGY_TO_SUPERVISOR
            assert (
                lib.canergy_auth_init(ref(self.keys[i]), key, CODEC.id_base, node, layout_c, to_sup)
                == OK
            )
        self.nodes = {n: Node(n, layout, rules) for n in NODES}
        self.out = lib.new("struct canergy_supervisor_out *")
        self.msg = lib.new("struct canergy_msg *")
        self.verified = lib.new("struct canergy_frame *")

    def _py_fv(self, msg: Message) -> Any:
        if msg.node not in NODES:
            return None
        s = self.py.session(msg.node)
        return expected_freshness(msg, s.tx, s.returns_credited)

    # -- the two supervisors --------------------------------------------------------------------
    def _c_sent(self, out: Any) -> list[tuple[int, bytes]]:
        sent = []
        for f in out.frames[0 : out.frame_count]:
            two = self.lib.new("struct canergy_auth_frame[2]")
            n = self.lib.canergy_auth_gateway_down_protect(self.keys, ref(self.gw), ref(f), two)
            assert n in (1, 2)
            sent += [(g.id, bytes(g.data[0 : g.len])) for g in list(two)[0:n]]
        acked = [
            e.node
            for e in out.events[0 : out.event_count]
            if e.flags & self.lib.CANERGY_SUP_ACKNOWLEDGED
        ]
        for node in acked:  # committed at once, as the gateway does
            decided = self.lib.new("struct canergy_supervisor_out *")
            assert (
                self.lib.canergy_supervisor_decide(ref(self.gw.down), node, True, self.now, decided)
                == OK
            )
            sent += self._c_sent(decided)
        return sent

    def _py_sent(self, actions: list[Any]) -> list[can.Message]:
        sent: list[can.Message] = []
        for a in actions:
            if isinstance(a, Acknowledged):
                sent += self._py_sent(self.py.commit(a.node, self.now))
            elif isinstance(a, Send):
                sent += self.py_auth.frames(a.message)
        return sent

    def _same(self, c_sent: list[tuple[int, bytes]], py_sent: list[can.Message]) -> None:
        assert c_sent == [(f.arbitration_id, bytes(f.data)) for f in py_sent]
        for i, node in enumerate(NODES):
            assert fields_of(self.gw.down.sessions[i]) == fields_of(self.py.session(node))
        assert self.gw.down.usable_uj == self.py.usable

    def _judged(self, frame: can.Message) -> Verdict:
        """``frame`` checked by C's and Python's authentication below: the same verdict."""
        r, _buf = rx(frame.arbitration_id, bytes(frame.data), lib=self.lib)
        status = self.lib.canergy_auth_gateway_down_frame(
            self.keys, ref(self.gw), ref(r), self.verified
        )
        verdict = self.py_auth.accept(frame)
        if verdict.failure is not None:
            assert status == getattr(self.lib, REFUSALS[verdict.failure])
        elif verdict.message is None:
            assert status == self.lib.CANERGY_AUTH_PENDING
        else:
            assert status == OK
        return verdict

    def receive(self, frame: can.Message) -> Verdict:
        """One frame from below to both supervisors: the same verdict, frames and books; what
        they send goes to the nodes."""
        verdict = self._judged(frame)
        c_sent: list[tuple[int, bytes]] = []
        py_sent: list[can.Message] = []
        if verdict.message is not None and not isinstance(verdict.message, Telemetry):
            v = self.verified
            plain, _pbuf = rx(v.id, bytes(v.data[0 : v.dlc]), lib=self.lib)
            to_sup = self.lib.CANERGY_TO_SUPERVISOR
            assert self.lib.canergy_decode(CODEC.id_base, ref(plain), to_sup, self.msg) == OK
            assert (
                self.lib.canergy_supervisor_on_msg(ref(self.gw.down), self.msg, self.now, self.out)
                == OK
            )
            c_sent = self._c_sent(self.out)
            py_sent = self._py_sent(self.py.receive(verdict.message, self.now))  # type: ignore[arg-type]
        self._same(c_sent, py_sent)
        self.to_nodes(py_sent)
        return verdict

    def begin(self, node: int, amount_mj: int) -> list[can.Message]:
        """A grant from both supervisors: the same INTENTION; returned, not delivered."""
        code = self.lib.canergy_supervisor_begin(
            ref(self.gw.down), node, amount_mj * QUANTUM_UJ, self.now, self.out
        )
        assert code == OK
        py_sent = self._py_sent(self.py.begin(node, amount_mj * QUANTUM_UJ, self.now))
        self._same(self._c_sent(self.out), py_sent)
        return py_sent

    # -- the nodes ------------------------------------------------------------------------------
    def to_nodes(self, frames: list[can.Message]) -> None:
        for frame in frames:
            node = self.nodes[frame.arbitration_id & 0xFF]
            verdict = node.auth.accept(frame)
            assert verdict.failure is None
            if verdict.message is not None:
                self.deliver(node.send(node.client.receive(verdict.message, self.now)))  # type: ignore[arg-type]

    def deliver(self, frames: list[can.Message]) -> list[Verdict]:
        return [self.receive(f) for f in frames]

    def join(self, node: int, nonce: int, high: int) -> list[can.Message]:
        """The node JOINs with 16 random bits of freshness above its nonce; its frames."""
        self.nodes[node].auth.join_fv[node] = high << 16 | nonce
        return self.nodes[node].send(self.nodes[node].client.books_lost(nonce, self.now))

    def grant(self, node: int, amount_mj: int) -> None:
        self.to_nodes(self.begin(node, amount_mj))

    def books(self) -> tuple[Any, ...]:
        views = tuple(fields_of(s) for s in self.gw.down.sessions[0:2])
        return views, self.gw.down.usable_uj, self.py.state


def taken(verdicts: list[Verdict]) -> bool:
    return any(v.message is not None for v in verdicts) and all(v.failure is None for v in verdicts)


@pytest.mark.parametrize("layout", list(Layout))
def test_the_c_gateways_leg_below_takes_and_sends_what_the_python_gateways_does(
    layout: Layout,
) -> None:
    below = Below(layout)
    join = below.join(5, 0x4321, 0xBEEF)
    assert taken(below.deliver(join))  # ADMIT at the session's high half, bound to the JOIN
    s5, node5 = below.py.session(5), below.nodes[5].client.state
    assert (node5.last_tx, node5.return_seq) == (s5.tx, s5.returns_credited)
    assert s5.tx > 0xFFFF and s5.returns_credited > 0xFFFF
    admitted_tx = s5.tx
    assert taken(below.deliver(below.join(3, 0x0007, 0x1234)))
    for node in NODES:
        assert taken(below.deliver(below.nodes[node].telemetry()))  # with its books now
    for k in range(1, 5):  # node 5's tx wraps past 0x2_0000 on the wire
        below.grant(3, 100 * k)
        below.grant(5, 200 * k)
        for node in NODES:
            assert taken(below.deliver(below.nodes[node].telemetry()))
    for node in NODES:
        below.deliver(
            below.nodes[node].send(below.nodes[node].client.give_back(300_000, below.now))
        )
    s3, s5 = below.py.session(3), below.py.session(5)
    assert (s3.delivered, s5.delivered) == (1_000 * QUANTUM_UJ, 2_000 * QUANTUM_UJ)
    assert s3.returned == s5.returned == 300_000
    assert s5.tx == admitted_tx + 4
    assert below.gw.down.usable_uj == INITIAL - 3_000_000 + 600_000


def _flipped(frames: list[can.Message]) -> list[can.Message]:
    """The same frames with one bit of the MAC flipped (the last byte of the last frame)."""
    last = frames[-1]
    data = bytearray(last.data)
    data[-1] ^= 0x01
    copy = can.Message(
        arbitration_id=last.arbitration_id, data=data, is_fd=last.is_fd, bitrate_switch=last.is_fd
    )
    return [*frames[:-1], copy]


def _by_message(frames: list[can.Message], layout: Layout) -> list[list[can.Message]]:
    per = 2 if layout is Layout.CLASSIC else 1
    return [frames[i : i + per] for i in range(0, len(frames), per)]


def _type(frames: list[can.Message]) -> int:
    return frames[0].arbitration_id >> 8 & 0xF


def _plain(frame: can.Message) -> can.Message:
    """The classic frame an authenticated frame carries, without its MAC: what anyone can send."""
    length = CODEC.data_length(MsgType(frame.arbitration_id >> 8 & 0xF))
    return can.Message(arbitration_id=frame.arbitration_id, data=bytes(frame.data[:length]))


@pytest.mark.parametrize("layout", list(Layout))
def test_replayed_flipped_and_keyless_frames_below_move_nothing_on_either(layout: Layout) -> None:
    """Node 3's frames of its first grant (TELEMETRY, ACK, COMMITTED, RETURN), replayed after a
    second grant: refused as stale or, a current duplicate, answered again; every one with a bit
    of its MAC flipped: refused; keyless copies: refused. The books never move."""
    below = Below(layout)
    node = below.nodes[3]
    below.deliver(below.join(3, 0x0042, 0x5A5A))
    mark = len(node.sent)  # the JOIN is not replayed: the C gateway holds no JOIN (see docs)
    below.deliver(node.telemetry())
    below.grant(3, 500)
    below.deliver(node.send(node.client.give_back(200_000, below.now)))
    recorded = _by_message(node.sent[mark:], layout)
    below.deliver(node.telemetry())
    below.grant(3, 700)
    before = below.books()
    refused: list[AuthFailure | None] = []
    for frames in recorded:
        verdicts = below.deliver(frames)
        refused += [v.failure for v in verdicts]
        assert below.books() == before, frames
    assert refused.count(AuthFailure.STALE) >= 3  # the TELEMETRY, the ACK, the COMMITTED
    for frames in _by_message(node.sent, layout):
        verdicts = below.deliver(_flipped(frames))
        assert verdicts[-1].failure is AuthFailure.MAC_BAD, frames
        assert below.books() == before
    keyless = [_plain(f[0]) for f in recorded]
    failures = {v.failure for v in below.deliver(keyless)}
    assert AuthFailure.UNAUTHENTICATED in failures and below.books() == before
    assert below.py.session(3).delivered == 1_200 * QUANTUM_UJ


@pytest.mark.parametrize("layout", list(Layout))
def test_under_the_witnessed_rules_an_admit_binds_the_resumes_freshness_alike(
    layout: Layout,
) -> None:
    """Witnessed rules below: a node's RESUME carries 16 random bits of freshness above its nonce
    (as ``python -m firmware_model --auth`` sends it); both supervisors take it and answer with
    the same ADMIT, whose MAC binds those bits; the node takes it."""
    below = Below(layout, "witnessed")
    below.deliver(below.join(3, 0x0101, 0x7777))
    node = below.nodes[3]
    below.deliver(node.telemetry())
    below.grant(3, 400)
    resume_nonce = 0x0202
    node.auth.resume_fv[3] = 0xA5A5 << 16 | resume_nonce
    resume = node.send(node.client.power_loss(below.now, resume_nonce))
    assert resume and _type(resume) == MsgType.DEBIT
    assert taken(below.deliver(resume))
    below.deliver(node.telemetry())
    below.grant(3, 100)
    assert below.py.session(3).delivered == 500 * QUANTUM_UJ
