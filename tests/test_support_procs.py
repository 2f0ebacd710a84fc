"""``support.procs``: a process that outlives its stop's timeout is ended, and the failure
shows where each of its threads was (faulthandler, on SIGABRT)."""

from __future__ import annotations

import signal

import pytest
from support.procs import Procs, python, wait
from support.procs import procs as procs  # the fixture

STUCK = """
import signal, sys, threading
signal.signal(signal.SIGTERM, signal.SIG_IGN)
def blocked_here():
    threading.Event().wait()
print("ready", file=sys.stderr, flush=True)
blocked_here()
"""


def test_a_process_that_will_not_stop_is_ended_and_its_stacks_shown(procs: Procs) -> None:
    proc = procs.start("stuck", python("-c", STUCK))
    wait(lambda: "ready" in procs.stderr("stuck"), "the process up", 60)
    with pytest.raises(AssertionError) as failed:
        procs.stop("stuck", timeout=0.5)
    said = str(failed.value)
    assert "stuck did not end within 0.5 s of signal" in said
    assert "most recent call first" in said and "blocked_here" in said, said
    assert proc.poll() == -signal.SIGABRT  # faulthandler wrote the stacks, then it aborted
