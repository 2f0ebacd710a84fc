"""Authenticated mode, witnessed rules: a JOIN answered again is signed as its first answer was.

The supervisor keeps the last JOIN it admitted and answers a copy of it with the same ADMIT (k,
C). An ADMIT's FV is the high half of its counters above its nonce, and a joining node takes its
counters' high half from that FV. The FV was taken from the session's tx when sent: a copy
answered after tx had crossed into the next 2^16 block was signed one block up, and the node
that took it stood 65,536 transactions ahead of the supervisor (its intentions old to it, its
debits beyond C, until a start). The FV now comes from the ADMIT's own k, extended next to tx,
in both languages (``freshness``, ``canergy_auth_freshness``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.c_binding import compiled_core, library

from canergy.auth.frames import FrameAuth, Layout, expected_freshness, freshness
from canergy.codec import Codec
from canergy.core import Client, Supervisor, Timing
from canergy.core.actions import Send
from canergy.core.state import Session, SupervisorState
from canergy.messages import Admit, Direction, Message

CODEC = Codec()
KEY = bytes(range(16))
TIMING = Timing(
    response_timeout_us=100, retries=2, command_timeout_us=1000, return_retry_us=300, window=32
)
BLOCK_END = 0xFFF0
"""The session's tx when the JOIN is admitted: 16 transactions before the block ends."""


def _sends(actions: list[Any]) -> list[Message]:
    return [a.message for a in actions if isinstance(a, Send)]


def _supervisor_auth(sup: Supervisor, layout: Layout) -> FrameAuth:
    def fresh(msg: Message) -> int:
        s = sup.session(msg.node)
        return expected_freshness(msg, s.tx, s.returns_credited)  # type: ignore[return-value]

    return FrameAuth(CODEC, layout, lambda n: KEY, Direction.TO_SUPERVISOR, fresh)


def _node_auth(node: Client, layout: Layout) -> FrameAuth:
    def fresh(msg: Message) -> int:
        return expected_freshness(msg, node.state.last_tx, node.state.return_seq)  # type: ignore[return-value]

    return FrameAuth(CODEC, layout, lambda n: KEY, Direction.TO_CLIENT, fresh)


def _through(frames: list[can.Message], auth: FrameAuth) -> Message | None:
    verdict = None
    for frame in frames:
        verdict = auth.accept(frame)
    assert verdict is not None and verdict.failure is None, verdict
    return verdict.message


@pytest.mark.parametrize("layout", list(Layout), ids=[layout.value for layout in Layout])
@pytest.mark.parametrize("core", [Supervisor, compiled_core], ids=["python", "c"])
def test_a_join_answered_after_tx_crossed_a_block_gets_the_first_admits_frames(
    core: Callable[..., Supervisor], layout: Layout
) -> None:
    state = SupervisorState(10**7, 10**7, sessions=(Session(1, tx=BLOCK_END, witness=BLOCK_END),))
    sup = core([1], 0, variant="witnessed", timing=TIMING, state=state)
    node = Client(1, variant="witnessed", timing=TIMING)
    sup_auth, node_auth = _supervisor_auth(sup, layout), _node_auth(node, layout)
    (join,) = _sends(node.books_lost(7, 0))
    taken = _through(node_auth.frames(join), sup_auth)
    assert taken == join
    (admit,) = _sends(sup.receive(join, 0))
    first = sup_auth.frames(admit)  # lost on the bus
    now = 0
    while sup.session(1).tx <= 0xFFFF:  # begins whose INTENTIONs are lost, closed by timers
        sup.begin(1, 1000, now)
        while (due := sup.get_timer()) is not None:
            now = max(now, due)
            sup.handle_timer(now)
    assert sup.session(1).tx >> 16 == 1
    (again,) = _sends(sup.receive(join, now))  # the node's JOIN re-sent: answered again
    assert again == admit
    frames = sup_auth.frames(again)
    assert [bytes(f.data) for f in frames] == [bytes(f.data) for f in first]
    seen = _through(frames, node_auth)
    assert isinstance(seen, Admit) and seen.tx == BLOCK_END, seen
    node.receive(seen, now)
    assert node.state.last_tx == BLOCK_END  # not 65,536 above the supervisor's k


def _c_freshness(wire_tx: int, nonce: int, tx: int) -> int:
    lib = library()
    m = lib.new("struct canergy_msg *")
    m.type, m.node, m.tx, m.nonce = lib.CANERGY_ADMIT, 1, wire_tx, nonce
    return int(lib.canergy_auth_freshness(m, tx & 0xFFFF_FFFF, 0))


@given(
    k=st.integers(0, 2**30 - 1),
    ahead=st.integers(0, 2**15 - 1),
    nonce=st.integers(0, 0xFFFF),
)
def test_an_admits_fv_is_its_ks_high_half_in_both_languages(k: int, ahead: int, nonce: int) -> None:
    """Whatever the session's tx since (up to 2^15 on, the wire's bound on age), an ADMIT
    numbered k is signed with k's high half, Python and C alike."""
    admit = Admit(1, nonce, k & 0xFFFF, 0)
    want = k & 0xFFFF_0000 | nonce
    assert freshness(admit, k + ahead, 0) == want
    assert _c_freshness(k & 0xFFFF, nonce, k + ahead) == want
