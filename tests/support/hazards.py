"""The paper's hazards (a)-(e) as scenarios: abstract steps on a ``support.harness.Harness``.

``HAZARDS`` names each scenario by its letter; a scenario drives whichever rule set and clients
its harness holds (tests/test_hazards.py: both variants; tests/test_c_hazards.py: the C client).
"""

from __future__ import annotations

from collections.abc import Callable

from support.harness import Harness, J

A = J  # the reservation in every scenario


def hazard_a(h: Harness) -> None:
    """ACK timeout re-sends the reservation; the client timeout-commits and spends the first."""
    h.begin(A)
    h.sup_timer()  # paper: INT#2 (new id); hardened: INT#1 again
    h.deliver_to_client(0)
    h.drop_to_sup()  # ACK lost
    assert h.client_timer()  # timeout-commit of the first intention
    h.drop_to_sup()  # COMMITTED lost
    h.spend()
    h.settle()  # second intention arrives, is acknowledged and committed


def timeout_commit_with_a_copy_in_flight(h: Harness) -> None:
    """The client timeout-commits an intention whose duplicate is still travelling."""
    h.begin(A)
    h.duplicate_to_client(0)
    h.deliver_to_client(0)
    h.drop_to_sup()  # ACK lost
    assert h.client_timer()  # timeout-commit
    h.drop_to_sup()  # COMMITTED lost


def hazard_b(h: Harness) -> None:
    """TimeoutN forgets a timeout-commit; a duplicated intention is then taken as new."""
    timeout_commit_with_a_copy_in_flight(h)
    h.client_timer()  # paper: TimeoutN; hardened: nothing armed
    h.spend()
    h.settle()


def hazard_c(h: Harness) -> None:
    """A duplicated RETURN."""
    h.begin(A)
    h.settle()
    h.give_back(A)
    h.duplicate_to_sup(0)
    h.settle()


def hazard_d(h: Harness) -> None:
    """After a client reset a late copy of an old intention is accepted again."""
    h.begin(A)
    h.duplicate_to_client(0)  # copy 0 is held back until after the reset
    h.deliver_to_client(1)
    h.deliver_to_sup(0)
    h.commit()
    while len(h.to_client) > 1 or h.to_sup:  # commit, confirmation (and paper's final ACK)
        h.deliver_to_sup(0) if h.to_sup else h.deliver_to_client(1)
    h.spend()
    h.client_reset()
    h.deliver_to_client(0)  # the late intention
    h.settle()
    h.client_timer()  # paper: timeout-commit of the replayed intention
    h.settle()


def hazard_e(h: Harness) -> None:
    """A reset right after a timeout-commit; the re-sent intention comes back."""
    timeout_commit_with_a_copy_in_flight(h)
    h.spend()
    h.client_reset()
    h.settle()


HAZARDS: dict[str, Callable[[Harness], None]] = {
    "a": hazard_a,
    "b": hazard_b,
    "c": hazard_c,
    "d": hazard_d,
    "e": hazard_e,
}
