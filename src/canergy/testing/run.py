"""Running parts of a test in its own process: a ``BusRuntime`` (a node host, a supervisor
service) in a thread of its own (``Loop``), and waiting for a condition (``until``)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from canergy.live.runtime import BusRuntime


class Loop:
    """``runtime`` run in a daemon thread (``max_wait_s``: its longest wait for a frame) until
    ``halt``; ``error`` keeps whatever ended it otherwise."""

    def __init__(self, runtime: BusRuntime, max_wait_s: float = 0.02) -> None:
        self.runtime, self.max_wait_s = runtime, max_wait_s
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="canergy-loop", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.runtime.run(self.stop.is_set, max_wait_s=self.max_wait_s)
        except BaseException as exc:  # kept for the test to inspect
            self.error = exc

    def halt(self, timeout_s: float = 30.0) -> None:
        """Stop between two steps (a power loss after the last completed write: what survives
        is what the host wrote) and shut its bus down; once halted, nothing."""
        if self.stop.is_set():
            return
        self.stop.set()
        self.thread.join(timeout_s)
        self.runtime.bus.shutdown()


def until(
    condition: Callable[[], bool],
    what: str = "the condition",
    timeout_s: float = 60.0,
    show: Callable[[], object] | None = None,
    period_s: float = 0.02,
) -> None:
    """Poll ``condition`` every ``period_s`` until it holds; after ``timeout_s``
    ``AssertionError`` naming ``what`` and showing what ``show`` returns then."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            shown = f": {show()}" if show is not None else ""
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}{shown}")
        time.sleep(period_s)
