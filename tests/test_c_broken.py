"""The side-by-side machine has teeth: a C library with one rule broken on purpose is caught.

The ``broken`` build (canergy.ccore.build) has ``-DCANERGY_BREAK_REPEATED_TX``: a COMMIT for the
transaction the client already resolved is applied a second time (energy created) instead of
being answered with the recorded reply. The machine of tests/test_c_sidebyside.py
(``support.side_by_side``) must find a difference with the Python rules within its default
budget of examples. It also has ``-DCANERGY_BREAK_RETURN_AGAIN`` (a duplicated RETURN credited
again by the supervisor's session): tests/test_ccore.py's machine, ``canergy.ccore``'s core on
that build, must find it.
"""

from __future__ import annotations

import pytest
from hypothesis import Phase as HypothesisPhase
from hypothesis import settings
from hypothesis.stateful import run_state_machine_as_test
from support.c_binding import CClient, CLib, library
from support.side_by_side import SideBySide, run_side_by_side
from test_ccore import SideBySide as CoreSideBySide

from canergy.core import Timing
from canergy.messages import Admit, Commit, Intention


class BrokenSideBySide(SideBySide):
    lib: CLib | None = None


def test_the_broken_rule_is_really_broken() -> None:
    """Scripted: a duplicated COMMIT credits twice in the broken build, once in the real one."""
    for lib, expected in ((library(), 4000), (library("broken"), 8000)):
        c = CClient(1, timing=Timing(), lib=lib)
        c.join(7, 0)
        c.message(Admit(1, 7, 0, 0), 1)
        c.message(Intention(1, 1, 4, 0), 2)
        c.message(Commit(1, 1, 4), 3)
        c.message(Commit(1, 1, 4), 4)  # the duplicate
        assert c.view()["usable_uj"] == expected


def test_the_machine_finds_the_broken_rule() -> None:
    BrokenSideBySide.lib = library("broken")
    with pytest.raises(AssertionError, match="differ"):
        run_side_by_side(
            BrokenSideBySide,
            database=None,
            derandomize=True,
            max_examples=1000,
            phases=[HypothesisPhase.generate],  # no shrinking: finding it is the point
        )


class BrokenCoreSideBySide(CoreSideBySide):
    build = "broken"


def test_the_compiled_core_machine_finds_the_broken_session_rule() -> None:
    """tests/test_ccore.py's machine (``canergy.ccore``'s ``CompiledSupervisor`` beside
    ``core.Supervisor``) on the broken build: a duplicated RETURN credited again
    (``CANERGY_BREAK_RETURN_AGAIN``) is found: the cores' actions or states differ (every
    assertion of the machine compares the two; the report names the machine's failing run)."""
    with pytest.raises(AssertionError, match="state = BrokenCoreSideBySide"):
        run_state_machine_as_test(
            BrokenCoreSideBySide,
            settings=settings(
                database=None,
                derandomize=True,
                max_examples=1000,
                stateful_step_count=60,
                deadline=None,
                phases=[HypothesisPhase.generate],
            ),
        )
