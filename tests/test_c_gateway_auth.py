"""The C gateway's authenticated leg above (``canergy_auth_gateway_up_frame`` and
``canergy_auth_gateway_up_protect``, firmware/src/auth.c) side by side with the Python
gateway's (``canergy gateway --upstream-auth``: ``FrameAuth`` over ``canergy.core.Gateway`` with
the upstream client's counters, as ``Uplink.freshness`` gives them).

A Python root supervisor with the master key speaks to node 7 through its own ``FrameAuth``.
Both gateways JOIN with the same nonce and JOIN freshness, and every frame the root sends reaches
both as bytes; what they send back must be the same bytes (data and MAC frames, both layouts),
their client books the same after every frame (the ADMIT's high half included: the root's
counters start above 2^16), and a frame with a flipped bit or replayed moves nothing on either.
"""

from __future__ import annotations

from typing import Any

import can
import pytest
from support.c_binding import (
    OK,
    CClient,
    CGateway,
    Struct,
    SupervisorConfig,
    c_view,
    cbuf,
    library,
    ref,
    rx,
    struct_view,
)
from support.c_session import timing_of

from canergy.auth.frames import FrameAuth, Layout, expected_freshness
from canergy.auth.keys import derive_node_key
from canergy.codec import Codec
from canergy.core import Acknowledged, Persist, Send, Supervisor, Timing
from canergy.core.gateway import Gateway
from canergy.core.state import Session, SupervisorState
from canergy.messages import QUANTUM_UJ, Direction, Message

UP = 7
BELOW = (3, 5)
T = Timing(response_timeout_us=1_000, retries=2, command_timeout_us=2_000, return_retry_us=2_000)
CODEC = Codec()
MASTER = bytes(range(16))
KEY = derive_node_key(MASTER, UP, 1)
NONCE, JOIN_HIGH = 0x1234, 0xBEEF
ROOT_TX, ROOT_SEQ = 0x2_FFF0, 0x3_0005
"""The root's counters for node 7: above 2^16, so a joining gateway needs the ADMIT's high half."""

Auth, AuthFrame = Struct("auth"), Struct("auth_frame")
C_LAYOUTS = {Layout.FD: "CANERGY_AUTH_FD", Layout.CLASSIC: "CANERGY_AUTH_CLASSIC"}


class Tree:
    """The root and the two gateways, the C one behind its authenticated leg above."""

    def __init__(self, layout: Layout) -> None:
        self.lib = library()
        self.now = 0
        books = SupervisorState(
            10**9, 10**9, 0, (Session(UP, tx=ROOT_TX, returns_credited=ROOT_SEQ),)
        )
        self.root = Supervisor([UP], 10**9, timing=T, state=books)
        self.root_auth = FrameAuth(
            CODEC, layout, lambda n: KEY, Direction.TO_SUPERVISOR, self._root_freshness
        )
        self.py = Gateway(UP, BELOW, up_timing=T, down_timing=T)
        self.py_auth = FrameAuth(CODEC, layout, lambda n: KEY, Direction.TO_CLIENT, self._py_fv)
        self.gw = CGateway(lib=self.lib)
        client = CClient(UP, timing=T, lib=self.lib)
        self.config, self.out = client.config, client.out
        cfg = SupervisorConfig(CODEC.id_base, timing_of(T, lib=self.lib), lib=self.lib)
        ids = cbuf(bytes(BELOW), lib=self.lib)
        assert self.lib.canergy_supervisor_init(ref(self.gw.down), ref(cfg), ids, 2, 0) == OK
        self.auth = Auth(lib=self.lib)
        c_layout = getattr(self.lib, C_LAYOUTS[layout])
        init = self.lib.canergy_auth_init
        assert (
            init(ref(self.auth), KEY, CODEC.id_base, UP, c_layout, self.lib.CANERGY_TO_CLIENT) == 0
        )
        self.to_gateways: list[can.Message] = []
        self.refused = 0

    def _root_freshness(self, msg: Message) -> Any:
        s = self.root.session(UP)
        return expected_freshness(msg, s.tx, s.returns_credited)

    def _py_fv(self, msg: Message) -> Any:
        if msg.node != UP:
            return None
        c = self.py.up.state
        return expected_freshness(msg, c.last_tx, c.return_seq)

    # -- what each side sends -----------------------------------------------------------------
    def c_frames(self) -> list[tuple[int, bytes]]:
        """The C gateway's last out, protected by its leg above."""
        sent = []
        for f in self.out.frames[0 : self.out.frame_count]:
            frames = self.lib.new("struct canergy_auth_frame[2]")
            n = self.lib.canergy_auth_gateway_up_protect(
                ref(self.auth), ref(self.gw), ref(f), frames
            )
            assert n in (1, 2)
            sent += [(g.id, bytes(g.data[0 : g.len])) for g in list(frames)[0:n]]
        return sent

    def answered(self, actions: list[Any]) -> None:
        """The C gateway sent what the Python one did, byte for byte; the frames reach the
        root; the books agree."""
        frames = [f for a in actions if isinstance(a, Send) for f in self.py_auth.frames(a.message)]
        assert self.c_frames() == [(f.arbitration_id, bytes(f.data)) for f in frames]
        assert bool(self.out.persist) == any(isinstance(a, Persist) for a in actions)
        for frame in frames:
            verdict = self.root_auth.accept(frame)
            assert verdict.failure is None
            if verdict.message is not None:
                self._root(self.root.receive(verdict.message, self.now))  # type: ignore[arg-type]
        assert struct_view(self.gw.up) == c_view(self.py.up.state)
        assert self.gw.down.usable_uj == self.py.down.state.usable

    def _root(self, actions: list[Any]) -> None:
        for a in actions:
            if isinstance(a, Acknowledged):
                self._root(self.root.commit(a.node, self.now))
            elif isinstance(a, Send):
                self.to_gateways += self.root_auth.frames(a.message)

    # -- steps --------------------------------------------------------------------------------
    def join(self) -> None:
        start = self.lib.canergy_client_start
        assert (
            start(ref(self.gw.up), self.config, self.lib.ffi.NULL, 0, NONCE, 0, ref(self.out)) >= 0
        )
        self.lib.canergy_auth_set_join(ref(self.auth), JOIN_HIGH, NONCE)
        self.py_auth.join_fv[UP] = JOIN_HIGH << 16 | NONCE
        self.answered(self.py.books_lost(NONCE, self.now))

    def deliver(self, frame: can.Message) -> tuple[int, bool]:
        """One frame from above to both: the C status, and whether Python acted on it."""
        r, _buf = rx(frame.arbitration_id, bytes(frame.data), lib=self.lib)
        status = self.lib.canergy_auth_gateway_up_frame(
            ref(self.auth), ref(self.gw), ref(r), self.now, ref(self.out)
        )
        verdict = self.py_auth.accept(frame)
        actions = []
        if verdict.message is not None:
            actions = self.py.receive_upstream(verdict.message, self.now)  # type: ignore[arg-type]
        self.answered(actions)
        return status, verdict.failure is None

    def deliver_all(self) -> None:
        while self.to_gateways:
            status, taken = self.deliver(self.to_gateways.pop(0))
            assert taken and status in (OK, self.lib.CANERGY_AUTH_PENDING)

    def grant(self, amount_mj: int) -> None:
        self._root(self.root.begin(UP, amount_mj * QUANTUM_UJ, self.now))
        self.deliver_all()

    def give_back(self, uj: int) -> None:
        code = self.lib.canergy_gateway_give_back(ref(self.gw), uj, self.now, ref(self.out))
        assert code == OK
        self.answered(self.py.give_back(uj, self.now))
        self.deliver_all()


@pytest.mark.parametrize("layout", list(Layout))
def test_the_c_gateways_leg_above_sends_and_takes_what_the_python_gateways_does(
    layout: Layout,
) -> None:
    tree = Tree(layout)
    tree.join()
    tree.deliver_all()  # the ADMIT: both take the root's counters, above 2^16
    s = tree.root.session(UP)
    assert (tree.gw.up.rec.last_tx, tree.gw.up.rec.return_seq) == (s.tx, s.returns_credited)
    assert s.tx > 0xFFFF and s.returns_credited > 0xFFFF
    for k in range(1, 6):
        tree.grant(100 * k)
        tree.give_back(40_000 * k)
    s = tree.root.session(UP)
    assert s.delivered == 1_500 * QUANTUM_UJ and s.returned == 600_000
    assert tree.gw.down.usable_uj == 900_000 == tree.py.down.state.usable


@pytest.mark.parametrize("layout", list(Layout))
def test_a_forged_or_replayed_frame_above_moves_nothing_on_either_gateway(layout: Layout) -> None:
    tree = Tree(layout)
    tree.join()
    tree.deliver_all()
    tree._root(tree.root.begin(UP, 500 * QUANTUM_UJ, tree.now))
    granted = list(tree.to_gateways)  # the intention (and its MAC frame)
    tree.deliver_all()  # granted and committed: 0.5 J below
    before = struct_view(tree.gw.up), tree.gw.down.usable_uj
    assert before[1] == 500_000
    for frame in granted:  # replayed: the same outcome on both (``deliver``), nothing moves
        tree.deliver(frame)
    assert (struct_view(tree.gw.up), tree.gw.down.usable_uj) == before
    tree._root(tree.root.begin(UP, 300 * QUANTUM_UJ, tree.now))
    *first, last = tree.to_gateways
    tree.to_gateways = []
    for frame in first:  # classic: the data frame waits for its MAC frame
        assert tree.deliver(frame) == (tree.lib.CANERGY_AUTH_PENDING, True)
    data = bytearray(last.data)
    data[-1] ^= 1  # a MAC bit flipped
    forged = can.Message(arbitration_id=last.arbitration_id, data=bytes(data), is_fd=last.is_fd)
    assert tree.deliver(forged) == (tree.lib.CANERGY_AUTH_MAC_BAD, False)
    assert (struct_view(tree.gw.up), tree.gw.down.usable_uj) == before
