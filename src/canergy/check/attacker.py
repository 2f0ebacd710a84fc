"""The frames a bus participant without a key can build (``canergy check --forgeries N``).

The codec and its CRC-8 are public, so a forger can send any valid frame. The model keeps the
choice finite but covers what can move energy. Per node, from the supervisor's counters (its
``tx``, Gs and the last return number credited ``q``), with amounts ``a`` of 1..units:

- to the client: INTENTION(tx or tx+1, a, Gs or Gs+1 unit), COMMIT and ABORT(tx or tx+1, a),
  RETURN_ACK(q or q+1), STATUS_REQUEST and FINAL_ACK(tx or tx+1), and while the node is joining
  ADMIT(its nonce, read off its JOIN; tx or tx+1; q or q+1);
- to the supervisor: ACK, COMMITTED and ABORTED(tx or tx+1), RETURN(q or q+1, a) and JOIN(the
  node's nonce, 0 when it is not joining: one no start drew).

Only the types the variant's tables handle are built (no ADMIT for ``paper``, no STATUS_REQUEST
for ``hardened``). A replayer (``--replays N``, the authenticated mode) builds nothing: it sends
again a frame already seen on the bus, which the world keeps in ``World.seen``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from canergy.core.state import ClientState, Phase, Session
from canergy.core.variants import Variant
from canergy.messages import (
    DELIVERED_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    TX_BITS,
    Abort,
    Aborted,
    Ack,
    Admit,
    Commit,
    Committed,
    FinalAck,
    Intention,
    Join,
    Message,
    Return,
    ReturnAck,
    StatusRequest,
)
from canergy.seqnum import wrap


def handled(variant: Variant) -> frozenset[type]:
    """The message types some cell of the variant's tables acts on."""
    tables = (variant.supervisor, variant.client)
    return frozenset(event for table in tables for _, event in table.listed)


def forgeable(
    variant: Variant, sessions: Sequence[Session], clients: Sequence[ClientState], units: int
) -> Iterator[Message]:
    """Every frame the forger may send now, in a fixed order."""
    types = handled(variant)
    amounts = range(1, units + 1)
    for s, c in zip(sessions, clients, strict=True):
        n = s.node
        txs = (wrap(s.tx, TX_BITS), wrap(s.tx + 1, TX_BITS))
        seqs = (wrap(s.returns_credited, SEQ_BITS), wrap(s.returns_credited + 1, SEQ_BITS))
        gs = s.delivered // QUANTUM_UJ
        frames: list[Message] = [
            *(
                Intention(n, tx, a, wrap(g, DELIVERED_BITS))
                for tx in txs
                for a in amounts
                for g in (gs, gs + 1)
            ),
            *(cls(n, tx, a) for cls in (Commit, Abort) for tx in txs for a in amounts),
            *(ReturnAck(n, q) for q in seqs),
            *(cls(n, tx) for cls in (StatusRequest, FinalAck) for tx in txs),
            *(Admit(n, c.nonce, tx, q) for tx in txs for q in seqs if c.phase is Phase.JOINING),
            *(cls(n, tx) for cls in (Ack, Committed, Aborted) for tx in txs),
            *(Return(n, q, a) for q in seqs for a in amounts),
            Join(n, c.nonce),
        ]
        yield from (m for m in frames if type(m) in types)
