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
