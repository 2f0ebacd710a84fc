"""Python protocol states as z3 terms, for comparing the symbolic model with the Python tables
(tests/test_prove_symbolic.py, tests/test_prove.py). Needs the prove extra (z3-solver)."""

from __future__ import annotations

import z3

from canergy.core.state import ClientState, Session
from canergy.prove import symbolic as sym


def sym_client(c: ClientState) -> sym.Client:
    return sym.Client(
        usable=z3.IntVal(c.usable),
        credited=z3.IntVal(c.credited),
        spent=z3.IntVal(c.spent),
        last_tx=sym.counter(c.last_tx),
        outcome=z3.IntVal(int(c.outcome)),
        return_seq=sym.counter(c.return_seq),
        return_pending=z3.IntVal(c.return_pending),
        credited_unknown=z3.BoolVal(c.credited_unknown),
        held_tx=sym.counter(c.held_tx),
        held_amount=z3.IntVal(c.held_amount),
        phase=z3.IntVal(int(c.phase)),
        nonce=z3.BitVecVal(c.nonce, 16),
        pending_draw=z3.BoolVal(c.pending_draw),
    )


def sym_session(s: Session) -> sym.Session:
    return sym.Session(
        phase=z3.IntVal(int(s.phase)),
        tx=sym.counter(s.tx),
        reserved=z3.IntVal(s.reserved),
        delivered=z3.IntVal(s.delivered),
        decision=z3.IntVal(int(s.decision)),
        returns_credited=sym.counter(s.returns_credited),
        returned=z3.IntVal(s.returned),
        resume_nonce=z3.BitVecVal(s.resume_nonce, sym.KEY_BITS),
        resume_from=sym.counter(s.resume_from),
        resume_to=sym.counter(s.resume_to),
        witness=sym.counter(s.witness),
        sync_nonce=z3.BitVecVal(s.sync_nonce, 16),
        join_nonce=z3.BitVecVal(s.join_nonce, 16),
        join_tx=sym.counter(s.join_tx),
        join_seq=sym.counter(s.join_seq),
        resync=z3.BoolVal(s.resync),
    )
