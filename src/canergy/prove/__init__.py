"""Passivity as a theorem (the ``prove`` extra: z3-solver): an inductive invariant of the
hardened rules of one session, with any set of messages in flight, checked by z3 for any number
of transactions.

- ``symbolic``: the hardened cells as SMT terms, tested against the Python tables;
- ``world``: the session, its client, the ghost state and messages;
- ``invariant``: the clauses, ``P(m, world)`` of messages in flight, the assumptions;
- ``steps``: every cell as a step of a world; ``rules``: the hardened set and unsound ones;
- ``witnessed``, ``witnessed_proof``: the witnessed cells as terms, then as steps with both
  restore steps, and the invariant tried on them (not inductive yet: the SYNC's counts that
  end a supervisor's start fail);
- ``obligations``: each (step, clause) checked by z3, with counterexamples to induction.

``canergy prove`` runs it. The names below need no z3.
"""

RULE_NAMES = (
    "hardened",
    "paper",
    "trusting-nv",
    "early-grant",
    "split-save",
    "old-image",
    "witnessed",
)
"""The rule sets ``canergy prove --rules`` takes; only ``hardened`` proves (``witnessed``, with
both restore steps, is meant to and does not yet: docs/protocol.md, assumption 2)."""
UNPROVED = ("witnessed",)
"""Sound rule sets whose invariant is not yet inductive: their failures are the proof's, not
hazards (the bounded checker finds no trace)."""

CONFIRMED_BY: dict[str, tuple[str, ...]] = {
    "paper": ("canergy check --variant paper",),
    "trusting-nv": (),
    "early-grant": ("canergy check --topology chain --broken-gateway early-grant",),
    "split-save": (
        "canergy check --old-copies 1",
        "canergy check --topology chain --broken-gateway split-save",
    ),
    "old-image": (
        "canergy check --old-copies 1",
        "canergy check --supervisor-old-copies 1 --engine reference --clients 2",
    ),
}
"""The bounded checker's runs that find a real trace of each unsound rule set's hazard (a
node starting blank and trusting Gs has no CLI variant: tests/test_check.py checks it)."""
TRACE_IN_TESTS = "a node that starts blank and trusts Gs, tests/test_check.py (TRUSTING)"
"""Where the trace is for a rule set with no CLI command (the blank-record rule)."""
