"""The Python core's frame path (``canergy.core.frame_answers``, ``Supervisor.answer_on``): a
received frame in one call, as the compiled core's. Frame for frame it matches the service's
usual path through the service (tests/test_ccore_tables.py runs a service on each path and on
the C core's side by side); here, what it takes, what it gives back and what it leaves, and a
service on the Python core whose answers never reach the usual path."""

from __future__ import annotations

from typing import Any

import can
import pytest
from support.wire import Wire

from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.core.actions import Action, Persist, Resolved, Send
from canergy.core.frame_answers import LEFT, TAKEN
from canergy.core.state import Outcome
from canergy.core.supervisor import Supervisor
from canergy.core.timing import Timing
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Commit,
    Committed,
    Direction,
    Intention,
    Message,
    Telemetry,
)

T = Timing(response_timeout_us=1_000, retries=2)
CODEC = Codec()


def _answer(
    core: Supervisor, msg: Message, now: int = 10, abort: bool = False, codec: Codec = CODEC
) -> tuple[int, list[Action], list[tuple[int, bytes]], Message | None, int]:
    ident, data = codec.encode(msg)
    return core.answer_on(0)(ident, data, True, False, now, abort)


def _begun(node: int = 3) -> tuple[Supervisor, Intention]:
    core = Supervisor([3, 5], 10_000_000, timing=T)
    (sent,) = [a.message for a in core.begin(node, 2_000, 0) if isinstance(a, Send)]
    assert isinstance(sent, Intention)
    return core, sent


@pytest.mark.parametrize("abort", [False, True])
def test_an_ack_is_ruled_decided_and_its_reply_encoded_in_one_call(abort: bool) -> None:
    """The ACK of the open transaction: its rules, the decision (commit, or abort when the
    caller stops) and the reply encoded, as the usual path would send it; the frames are not
    among the actions given back, and the session went on as it would there."""
    core, intention = _begun()
    ref, _ = _begun()
    status, actions, frames, decoded, verdict = _answer(core, Ack(3, intention.tx), abort=abort)
    assert (status, decoded, verdict) == (TAKEN, None, 0)
    reply = (Abort if abort else Commit)(3, intention.tx, intention.amount_mj)
    assert frames == [CODEC.encode(reply)]
    assert not any(isinstance(a, Send) for a in actions)
    assert any(isinstance(a, Persist) for a in actions)
    ref.receive(Ack(3, intention.tx), 10)
    (ref.abort if abort else ref.commit)(3, 10)
    assert core.state == ref.state


def test_a_committed_resolves_the_transaction() -> None:
    core, intention = _begun()
    _answer(core, Ack(3, intention.tx))
    status, actions, frames, _, _ = _answer(core, Committed(3, intention.tx), now=20)
    assert status == TAKEN and frames == []
    (resolved,) = [a for a in actions if isinstance(a, Resolved)]
    assert (resolved.outcome, resolved.amount) == (Outcome.COMMITTED, 2_000)
    assert core.idle(3)


def test_what_is_no_answer_is_left_to_the_bus_loop_undecoded() -> None:
    """A TELEMETRY (C decodes it in its call for the tables it keeps there): left, nothing
    applied, for the bus loop to decode with the same codec and hand to the service."""
    core, _ = _begun()
    before = core.state
    status, actions, frames, decoded, _ = _answer(core, Telemetry(3, 1_000))
    assert (status, actions, frames, decoded) == (LEFT, [], [], None)
    assert core.state is before


@pytest.mark.parametrize(
    "frame",
    [
        pytest.param(lambda tx: CODEC.encode(Ack(3, tx + 1)), id="an answer ahead of the books"),
        pytest.param(lambda tx: CODEC.encode(Ack(9, tx)), id="a node not managed"),
        pytest.param(lambda tx: CODEC.encode(Commit(3, tx, 2)), id="the supervisor's direction"),
        pytest.param(
            lambda tx: (CODEC.encode(Ack(3, tx))[0], b"\x00" + CODEC.encode(Ack(3, tx))[1][1:]),
            id="a bad CRC",
        ),
        pytest.param(lambda tx: (0x123, b"\x01\x02"), id="a foreign identifier"),
    ],
)
def test_what_the_bus_loop_must_judge_is_left_untouched(frame: Any) -> None:
    """Left (nothing decoded, nothing applied) for the bus loop, which decodes and judges it
    its usual way: an intrusion, a frame of the other direction, a decode error."""
    core, intention = _begun()
    before = core.state
    ident, data = frame(intention.tx)
    status, actions, frames, decoded, _ = core.answer_on(0)(ident, data, True, False, 10, False)
    assert (status, actions, frames, decoded) == (LEFT, [], [], None)
    assert core.state is before


def test_a_remote_or_standard_frame_is_left() -> None:
    core, intention = _begun()
    ident, data = CODEC.encode(Ack(3, intention.tx))
    answer = core.answer_on(0)
    assert answer(ident, data, True, True, 10, False)[0] == LEFT
    assert answer(ident & 0x7FF, data, False, False, 10, False)[0] == LEFT
    assert core.session(3).tx == intention.tx and not core.idle(3)


def test_on_a_second_bus_the_session_key_inside_the_node_id_on_the_wire() -> None:
    """Bus 1's path: node 3 there is session 0x103; the actions name the key, the frames
    encoded name node 3."""
    key = 1 << 8 | 3
    core = Supervisor([3, key], 10_000_000, timing=T)
    (intention,) = [a.message for a in core.begin(key, 1_000, 0) if isinstance(a, Send)]
    ident, data = CODEC.encode(Ack(3, intention.tx))
    status, _, frames, _, _ = core.answer_on(1)(ident, data, True, False, 10, False)
    assert status == TAKEN and frames == [CODEC.encode(Commit(3, intention.tx, 1))]
    assert core.session(3).tx == 0 and not core.idle(key)
    ident, data = CODEC.encode(Committed(3, intention.tx))
    status, actions, _, _, _ = core.answer_on(1)(ident, data, True, False, 20, False)
    assert status == TAKEN and [a.node for a in actions if isinstance(a, Resolved)] == [key]


def test_a_core_on_another_identifier_block_takes_its_own_frames() -> None:
    """``id_base`` (a bus shared with another canergy system, ``--id-base``): its frames are
    taken, the default block's left."""
    block = DEFAULT_ID_BASE + (1 << 12)
    other = Codec(block)
    core = Supervisor([3], 10_000_000, timing=T, id_base=block)
    (intention,) = [a.message for a in core.begin(3, 1_000, 0) if isinstance(a, Send)]
    assert _answer(core, Ack(3, intention.tx))[0] == LEFT
    status, _, frames, _, _ = _answer(core, Ack(3, intention.tx), codec=other)
    assert status == TAKEN and frames == [other.encode(Commit(3, intention.tx, 1))]


def test_a_python_gateways_supervisor_role_takes_the_frames_of_its_own_block() -> None:
    """``canergy gateway --core python --id-base``: the role below (``make_below``'s
    ``Below``) takes answers on the block it was given, not on the default one."""
    from canergy.ccore.supervisor import make_below

    block = DEFAULT_ID_BASE + (2 << 12)
    make = make_below("python", block)
    assert make is not None
    core = make([3], 10_000_000, variant="hardened", timing=T, state=None, start_without=())
    (intention,) = [a.message for a in core.begin(3, 1_000, 0) if isinstance(a, Send)]
    assert _answer(core, Ack(3, intention.tx))[0] == LEFT
    assert _answer(core, Ack(3, intention.tx), codec=Codec(block))[0] == TAKEN


def test_on_the_python_core_answers_never_reach_the_usual_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A service on the Python core runs its core's frame path: a grant's ACK and COMMITTED
    are taken there (the service's ``on_message``, the usual path, never sees them), the
    COMMIT goes out, the grant is answered, and the status says the path and its frames."""
    usual: list[Message] = []
    on_message = SupervisorService.on_message

    def seen(self: SupervisorService, msg: Message, now: int) -> Any:
        usual.append(msg)
        return on_message(self, msg, now)

    monkeypatch.setattr(SupervisorService, "on_message", seen)
    wire, now = Wire(), [0]
    service = build_service(Supervisor([3], 10_000_000, timing=T), ServiceConfig(), 0)
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        frame_path=service.frame_path(),
        counters=service.bus_counters,
        clock=lambda: now[0],
    )

    def feed(msg: Message) -> None:
        now[0] += 100
        ident, data = CODEC.encode(msg)
        wire.inbox.append(can.Message(arbitration_id=ident, data=data, is_extended_id=True))
        loop.poll(0)

    replies: list[dict[str, Any]] = []
    service.request_grant(3, 1_000_000, replies.append)
    feed(Telemetry(3, 0))  # heard: the grant begins
    intention = CODEC.decode(*wire.sent[-1])
    assert isinstance(intention, Intention)
    feed(Ack(3, intention.tx))
    assert CODEC.decode(*wire.sent[-1]) == Commit(3, intention.tx, 1_000)
    feed(Committed(3, intention.tx))
    assert replies and replies[0]["outcome"] == "COMMITTED"
    assert usual == [Telemetry(3, 0)]  # decoded by the bus loop
    status = service.status()
    assert (status["frame_path"], status["frame_path_frames"]) == ("python", 2)
    assert "frame_path_off" not in status and service.frames_in_c == 0
    feed(Aborted(3, intention.tx + 1))  # ahead of the books: the usual path judges it
    assert usual[-1] == Aborted(3, intention.tx + 1) and service.status()["intrusions"] == 1
    loop.bus.shutdown()
