"""The Python core's frame path: a received frame taken in one call, as the compiled core's.

``FrameAnswers`` is one bus's ``SupervisorCore.answer_on`` for ``Supervisor``: given a frame's
identifier and bytes it does for an answer what C's ``canergy_supervisor_on_answer`` does, with
the Python codec and rules: an ACK, COMMITTED or ABORTED of a managed node that names no
transaction ahead of its session is decoded, ruled, decided (an ACK committed, or aborted when
the caller says it stops) and its replies encoded; the caller gets the other actions and the
frames. Anything else comes back untouched (``LEFT``): a TELEMETRY, RETURN, JOIN or DEBIT,
which C decodes in its call for the tables it keeps there, is decoded by the bus loop with the
same codec and handed to the service's tables as before; a frame not decodable here, of another
node or ahead of the books is judged there its usual way.

Sans-IO: identifiers, bytes and times from the caller.
"""

from __future__ import annotations

from dataclasses import replace

from canergy.codec import Codec, DecodeError
from canergy.core.actions import Acknowledged, Action, Send
from canergy.core.common import never_begun
from canergy.core.supervisor import BUS_SHIFT, Supervisor
from canergy.messages import Aborted, Ack, Committed, Direction, Message

TAKEN, LEFT = 0, 2
"""A frame's status: taken (its actions and frames given), or left (nothing done: the bus loop
takes the frame its usual way)."""

Answered = tuple[int, list[Action], list[tuple[int, bytes]], Message | None, int]
"""(status, actions but the frames, the frames encoded, None: nothing is given back decoded, a
verdict: 0, no table of the service's is kept in the Python core): ``Answer``'s shape."""

_ANSWERS = frozenset(int(t.TYPE) for t in (Ack, Committed, Aborted))
"""The type codes of the frames taken (an identifier's bits 8-11)."""


class FrameAnswers:
    """Bus ``bus``'s frame path into a Python ``Supervisor`` (``Supervisor.answer_on``)."""

    def __init__(self, core: Supervisor, codec: Codec, bus: int = 0) -> None:
        self._core = core
        self._codec = codec
        self._key = bus << BUS_SHIFT
        """What turns a node id on this bus into its session key (``canergy.bus_keys``)."""

    def __call__(
        self,
        arbitration_id: int,
        data: bytes | bytearray,
        extended: bool,
        remote: bool,
        now: int,
        abort: bool,
    ) -> Answered:
        """The frame's status and what was done (``Answered``)."""
        if arbitration_id >> 8 & 0xF not in _ANSWERS:  # the bus loop decodes it as ever
            return LEFT, [], [], None, 0
        try:
            msg = self._codec.decode(
                arbitration_id,
                data,
                extended=extended,
                remote=remote,
                direction=Direction.TO_SUPERVISOR,
            )
        except DecodeError:
            return LEFT, [], [], None, 0
        key = self._key | msg.node
        core = self._core
        if key not in core._index:
            return LEFT, [], [], None, 0
        if key != msg.node:
            msg = replace(msg, node=key)
        assert isinstance(msg, Ack | Committed | Aborted)  # by its type code, decoded
        if never_begun(msg.tx, core.state.sessions[core._index[key]]):  # judged the usual way
            return LEFT, [], [], None, 0
        actions = core.receive(msg, now)
        kept: list[Action] = []
        frames: list[tuple[int, bytes]] = []
        encode = self._codec.encode
        i = 0
        while i < len(actions):  # grows at its end: the decision follows the ACK
            action = actions[i]
            i += 1
            if isinstance(action, Send):
                sent = action.message
                if sent.node >> BUS_SHIFT:  # on the wire, the node id alone
                    sent = replace(sent, node=sent.node & 0xFF)
                frames.append(encode(sent))
            elif isinstance(action, Acknowledged):
                decide = core.abort if abort else core.commit
                actions.extend(decide(action.node, now))
            else:
                kept.append(action)
        return TAKEN, kept, frames, None, 0
