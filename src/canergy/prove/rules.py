"""Rule sets the prover can be given: the hardened tables, and rules known to be unsound, which
it must refuse (its teeth).

Each unsound set is the hardened model with some cells replaced:
- ``paper``: the paper's cells that have a counterpart in this state: RETURN credited for every
  copy that arrives (``paper.credit_any_return``), a supervisor reset that restarts transaction
  ids and counts Ts as delivered (``paper.reset_session``), a client without a valid record that
  starts blank and trusts the next Gs (``common.start_blank``). Its STATUS_REQUEST, FINAL_ACK,
  TimeoutN and roll-back have no counterpart here; the bounded checker covers them;
- ``trusting-nv``: only the blank start (the checker's ``TRUSTING`` variant in its tests);
- ``early-grant``: a node passes on (spends) a held intention before it is committed, as the
  chain checker's ``--broken-gateway early-grant`` gateway grants downstream;
- ``split-save``: a node's record written in two parts, a power loss between them leaving its
  usable budget new and its last transaction one back (``--broken-gateway split-save``, read for
  one node; the theorem assumes NV is never restored to an older image);
- ``old-image``: the hardened cells with assumption 2 dropped: steps put the node's record, or
  the supervisor's, back to an older image (``canergy check --old-copies 1`` for the node's;
  ``canergy check --supervisor-old-copies 1 --engine reference --clients 2`` for the
  supervisor's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from canergy.messages import QUANTUM_UJ, SEQ_BITS
from canergy.prove import symbolic as sym
from canergy.prove.symbolic import Term, z3


def credit_any_return(s: sym.Session, seq16: Term, amount_mj: Term) -> sym.SessionStep:
    """The paper: RETURN(q, x) credits x for every copy, nothing acknowledged."""
    seq = sym.unwrap(seq16, s.returns_credited, SEQ_BITS)
    latest = z3.If(seq - s.returns_credited > 0, seq, s.returns_credited)
    amount = amount_mj * QUANTUM_UJ
    credited = replace(s, returns_credited=latest, returned=s.returned + amount)
    return sym.SessionStep(credited, sym.Sent.none(), amount)


def reset_session(s: sym.Session) -> sym.SessionStep:
    """The paper: only Us survives a reset; Ts counts as delivered, ids restart at 0."""
    reset = replace(
        s,
        phase=sym.S_IDLE,
        tx=sym.counter(0),
        reserved=z3.IntVal(0),
        delivered=s.delivered + s.reserved,
        decision=sym.NO_DECISION,
    )
    return sym.SessionStep(reset, sym.Sent.none(), z3.IntVal(0))


def start_blank(c: sym.Client, nonce16: Term) -> tuple[sym.Client, sym.Sent]:
    """No valid record: start from zero as a new node would, trusting the next Gs in full."""
    blank, _ = sym.books_lost(c, nonce16)
    return replace(blank, phase=sym.IDLE, nonce=z3.BitVecVal(0, 16)), sym.Sent.none()


def spend_held(c: sym.Client, amount: Term) -> tuple[sym.Client, Term]:
    """Early grant: what a held intention offers may be passed on before its commit."""
    offered = z3.If(c.phase == sym.HOLDING, c.held_amount, 0)
    after, _ = sym.spend(c, amount)
    allowed = z3.And(c.phase != sym.JOINING, amount > 0, amount <= c.usable + offered)
    return after, allowed


def power_loss_split(c: sym.Client) -> tuple[sym.Client, sym.Sent]:
    """Split save: the reset finds the usable budget written and the last transaction not."""
    older, sent = sym.client_power_loss(c)
    back = replace(older, last_tx=c.last_tx - 1, outcome=sym.SETTLED)
    booked = z3.And(c.phase != sym.JOINING, c.last_tx != sym.counter(0))
    return sym.pick(booked, back, older), sent


@dataclass(frozen=True)
class Rules:
    """The symbolic cells a proof runs on (hardened unless replaced)."""

    name: str = "hardened"
    credit_return: Callable[[sym.Session, Term, Term], sym.SessionStep] = sym.credit_return
    supervisor_power_loss: Callable[[sym.Session], sym.SessionStep] = sym.supervisor_power_loss
    books_lost: Callable[[sym.Client, Term], tuple[sym.Client, sym.Sent]] = sym.books_lost
    spend: Callable[[sym.Client, Term], tuple[sym.Client, Term]] = sym.spend
    client_power_loss: Callable[[sym.Client], tuple[sym.Client, sym.Sent]] = sym.client_power_loss
    restores: bool = False
    """Steps put the node's record, or the supervisor's, back to an older image (assumption 2
    dropped)."""
    witnessed: bool = False
    """The witnessed tables (``canergy.prove.witnessed_proof``) replace every cell."""


HARDENED = Rules()
RULES: dict[str, Rules] = {
    r.name: r
    for r in (
        HARDENED,
        Rules(
            "paper",
            credit_return=credit_any_return,
            supervisor_power_loss=reset_session,
            books_lost=start_blank,
        ),
        Rules("trusting-nv", books_lost=start_blank),
        Rules("early-grant", spend=spend_held),
        Rules("split-save", client_power_loss=power_loss_split),
        Rules("old-image", restores=True),
        Rules("witnessed", restores=True, witnessed=True),
    )
}
"""Every rule set by name; only ``hardened`` is expected to prove."""
