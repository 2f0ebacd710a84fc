"""Hypothesis strategies for wire messages."""

from __future__ import annotations

from hypothesis import strategies as st

from canergy.messages import (
    AMOUNT_MAX_MJ,
    MAX_NODE,
    MIN_NODE,
    Abort,
    Aborted,
    Ack,
    Commit,
    Committed,
    FinalAck,
    Intention,
    Join,
    Message,
    Return,
    ReturnAck,
    StatusRequest,
    Telemetry,
)

nodes = st.integers(MIN_NODE, MAX_NODE)
u16 = st.integers(0, 0xFFFF)
amounts = st.integers(1, AMOUNT_MAX_MJ)

messages: st.SearchStrategy[Message] = st.one_of(
    st.builds(Intention, nodes, u16, amounts, st.integers(0, 0xFFFFFF)),
    st.builds(Commit, nodes, u16, amounts),
    st.builds(Abort, nodes, u16, amounts),
    st.builds(ReturnAck, nodes, u16),
    st.builds(StatusRequest, nodes, u16),
    st.builds(FinalAck, nodes, u16),
    st.builds(Ack, nodes, u16),
    st.builds(Committed, nodes, u16),
    st.builds(Aborted, nodes, u16),
    st.builds(Return, nodes, u16, amounts),
    st.builds(
        Telemetry,
        nodes,
        st.integers(0, 0xFFFFFF),
        st.integers(0, 0xFF),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFF),
    ),
)


def client_answer(
    data: st.DataObject, node: int, tx: int, returns_credited: int, *, telemetry: bool = False
) -> Message:
    """A message a client could send its supervisor, its counters near the session's
    (``tx``, ``returns_credited``) or anywhere: ACK, COMMITTED, ABORTED, RETURN, JOIN (and
    TELEMETRY, which no supervisor rule takes)."""

    def near(counter: int) -> st.SearchStrategy[int]:
        return st.one_of(
            st.integers(-2, 2).map(lambda d: (counter + d) & 0xFFFF), st.integers(0, 0xFFFF)
        )

    wire_tx, seq = data.draw(near(tx)), data.draw(near(returns_credited))
    choices: list[Message] = [
        Ack(node, wire_tx),
        Committed(node, wire_tx),
        Aborted(node, wire_tx),
        Return(node, seq, data.draw(st.integers(1, 2_000))),
        Join(node, data.draw(st.integers(0, 0xFFFF))),
    ]
    if telemetry:
        choices.append(Telemetry(node, data.draw(st.integers(0, 0xFFFFFF))))
    return data.draw(st.sampled_from(choices))
