"""Protocol timeouts and retry bounds (all durations in integer microseconds)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Timing:
    """Timeouts shared by supervisor and clients.

    ``retries`` is N: how many times the supervisor re-sends an unanswered intention or command
    (hardened) or status request (paper) before it gives up with a write-off. Zero durations give
    abstract time: every armed deadline is 0 and a timer fires only when told to (model checking).
    """

    response_timeout_us: int = 50_000
    retries: int = 3
    command_timeout_us: int = 100_000
    return_retry_us: int = 100_000
    window: int = 64
    """B (witnessed rules): a supervisor begins transaction k only when k <= W + B, W the
    highest transaction the node has shown it persisted; a node answering a supervisor's start
    settles the next B transactions."""

    def __post_init__(self) -> None:
        for name in ("response_timeout_us", "command_timeout_us", "return_retry_us"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if self.retries < 0:
            raise ValueError("retries must be >= 0")
        if self.window < 1:
            raise ValueError("window must be >= 1")

    @property
    def quiet_timeout_us(self) -> int:
        """Paper client's TimeoutN: the time of N supervisor timeouts plus one."""
        return (self.retries + 1) * self.response_timeout_us
