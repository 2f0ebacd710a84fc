"""Passivity as a theorem (the ``prove`` extra: z3-solver): an inductive invariant of the
hardened rules of one session, with any set of messages in flight, checked by z3 for any number
of transactions.

- ``symbolic``: the hardened cells as SMT terms, tested against the Python tables;
- ``world``: the session, its client, the ghost state and messages;
- ``invariant``: the clauses, ``P(m, world)`` of messages in flight, the assumptions;
- ``steps``: every cell as a step of a world; ``rules``: the hardened set and unsound ones;
- ``witnessed``, ``witnessed_proof``: the witnessed cells as terms, then as steps with both
  restore steps, and the invariant proved of them under assumption 2 narrowed (``NARROWED``);
- ``obligations``: each (step, clause) checked by z3, with counterexamples to induction.

``canergy prove`` runs it. The names below need no z3.
"""

EFFORT = 1_500_000_000
"""z3's resource limit per check (its ``rlimit``, a count of its own steps): where a check stops
does not depend on the machine's speed or load (a wall-clock limit alone once let a goal proved
in 73 s here fail after 600 s on a loaded CI machine). What z3 does within it still depends on
its seed and on the terms the process built before (one check of the witnessed proof took 61
million to over 1,500 million steps so, until a lemma made it a check of seconds): a check made
alone is begun again with other seeds (``obligations.RESTARTS``). z3 did about 7 million steps a
second here (74 million in 10.7 s, 500 million in 73 s)."""

RULE_NAMES = (
    "hardened",
    "paper",
    "trusting-nv",
    "early-grant",
    "split-save",
    "old-image",
    "witnessed",
)
"""The rule sets ``canergy prove --rules`` takes; ``SOUND`` ones prove, the others fail."""
SOUND = ("hardened", "witnessed")
"""The rule sets that prove: ``hardened`` under every assumption, ``witnessed`` (both restore
steps) under assumption 2 narrowed (``NARROWED``; docs/protocol.md, assumption 2)."""
NARROWED = {
    "witnessed": (
        "assumption 2 narrowed, not dropped: a record put back is a copy that side wrote "
        "while no start of its waited, or while a start from its own record waited (the "
        "node's RESUME after a power loss or its answer to a SYNC, the supervisor not behind "
        "it; the supervisor's "
        "before the node's books raised Gs), and since its record last went back (shown to be an "
        "older image of the kind the restore steps take), and not both records rolled back "
        "past the same event (docs/protocol.md, 'Passivity as a theorem', assumption 2)"
    ),
}
"""Sound rule sets whose proof takes a narrower form of an assumption, said with a pass."""

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
